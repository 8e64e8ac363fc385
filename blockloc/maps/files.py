"""File access of a map store: one interface for a local directory and for a URL.

:class:`MapFiles` reads a local store directory (or ``file://``); :func:`open_map_files` returns
it, or :class:`blockloc.maps.remote.RemoteMapFiles` (same methods plus a checksum-validated
cache) for ``http(s)://``, ``s3://`` and other fsspec URLs. Every read of a store goes through one
of them, so the store code above never knows where its bytes come from.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from blockloc.errors import MapError


class MapFiles:
    """Read-only access to the files of one local store directory.

    Every read of a store goes through this interface; URLs (http(s)://, s3://) are served by
    :class:`blockloc.maps.remote.RemoteMapFiles`, which has the same methods plus a cache.
    """

    is_remote = False

    def __init__(self, root: str | Path):
        root_s = str(root)
        if root_s.startswith("file://"):
            root_s = root_s[len("file://"):]
        self.root = str(Path(root_s))

    def url(self, name: str) -> str:
        """Full path of a file of the store (for messages)."""
        return str(Path(self.root) / name)

    def read_bytes(self, name: str) -> bytes:
        """Bytes of the file ``name``; MapError naming it when missing or unreadable."""
        try:
            return (Path(self.root) / name).read_bytes()
        except FileNotFoundError:
            raise MapError(f"{self.url(name)}: missing map file") from None
        except OSError as exc:
            raise MapError(f"{self.url(name)}: cannot read ({exc})") from None

    def exists(self, name: str) -> bool:
        return (Path(self.root) / name).exists()

    def is_dir(self) -> bool:
        return Path(self.root).is_dir()

    def list_names(self) -> list[str]:
        """Names of the files directly in the store."""
        return sorted(p.name for p in Path(self.root).iterdir() if p.is_file())


def open_map_files(url_or_path: str | os.PathLike, **remote_options: Any):
    """``MapFiles`` for a local directory (or ``file://``), ``RemoteMapFiles`` for a URL.

    ``remote_options`` go to :class:`~blockloc.maps.remote.RemoteMapFiles` (cache_dir,
    cache_bytes, retry, storage_options, seed) and are ignored for local paths.
    """
    from blockloc.maps import remote

    if remote.is_url(url_or_path):
        return remote.RemoteMapFiles(str(url_or_path), **remote_options)
    return MapFiles(url_or_path)
