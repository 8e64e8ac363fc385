"""Where generated data is cached, and keys that change when the code or parameters that made it do.

The demo, the tests and the benchmarks reuse a simulated world and its maps across runs. A cache
entry is keyed by a fingerprint of the source of the modules that produced it plus their
parameters, so a change to the simulator or the map builder never serves stale data.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
from pathlib import Path


def cache_root() -> Path:
    """``$BLOCKLOC_CACHE`` or ``~/.cache/blockloc``."""
    root = os.environ.get("BLOCKLOC_CACHE")
    return Path(root).expanduser() if root else Path.home() / ".cache" / "blockloc"


def _module_files(name: str) -> list[Path]:
    spec = importlib.util.find_spec(name)
    if spec is None or spec.origin is None:
        raise ImportError(f"no module named {name!r}")
    if spec.submodule_search_locations:
        return sorted(p for d in spec.submodule_search_locations for p in Path(d).rglob("*.py"))
    return [Path(spec.origin)]


def fingerprint(*modules: str, params: object = None) -> str:
    """10 hex digits over the source files of ``modules`` (packages: all their .py files) and
    ``repr(params)``. The same code and parameters give the same key on every machine."""
    h = hashlib.sha256()
    for name in modules:
        for path in _module_files(name):
            h.update(path.name.encode())
            h.update(path.read_bytes())
    h.update(repr(params).encode())
    return h.hexdigest()[:10]


def disk_memo(name: str, key: str, build, *, min_build_s: float = 1.0):
    """``build()``, kept on disk under ``<cache root>/memo/<name>-<key>.pkl`` when it took at
    least ``min_build_s`` seconds of CPU, and loaded from there by later processes.

    For generated objects that are pure functions of code and parameters (``key`` should be a
    :func:`fingerprint` of both), such as a simulated city world: 19 s of CPU to build, 0.1 s
    to load, paid otherwise by every process (each Dask worker) that opens one of its drives.
    A file that cannot be read is rebuilt and replaced; one that cannot be written is skipped
    (the result is the same either way). Written through a temp file and a rename, so concurrent
    processes never read half a file. Writing an entry removes the entries of the same ``name``
    under other keys (``name`` holds the parameters, ``key`` the code: those were left by older
    code and nothing reads them again; a city world is ~100 MB).
    """
    import logging
    import pickle
    import time

    from blockloc.fileio import atomic_write_bytes

    path = cache_root() / "memo" / f"{name}-{key}.pkl"
    if path.is_file():
        try:
            with open(path, "rb") as f:
                return pickle.load(f)
        except Exception as exc:  # noqa: BLE001 - a damaged cache entry is rebuilt
            logging.getLogger(__name__).warning("%s: unreadable (%s); rebuilding it", path, exc)
    t0 = time.process_time()
    value = build()
    if time.process_time() - t0 >= min_build_s:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(path, pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
        except OSError as exc:
            logging.getLogger(__name__).warning("%s: not cached (%s)", path, exc)
        else:
            for old in superseded_memo_entries(path.parent, name, key):
                old.unlink(missing_ok=True)
    return value


def superseded_memo_entries(memo_dir: Path, name: str, key: str, *, suffix: str = ".pkl") -> list[Path]:
    """Entries ``<name>-<other key><suffix>`` in ``memo_dir``: the same name, a key of
    :func:`fingerprint`'s form (10 hex digits) other than ``key``; files, or directories when
    ``suffix`` is empty. Nothing else matches (not ``<name>-2-<key>.pkl``, another name; not a
    file blockloc did not name this way)."""
    import glob
    import re

    pat = re.compile(re.escape(name) + r"-([0-9a-f]{10})" + re.escape(suffix))
    return sorted(p for p in memo_dir.glob(f"{glob.escape(name)}-*{suffix}")
                  if (m := pat.fullmatch(p.name)) and m.group(1) != key and (p.is_file() if suffix else p.is_dir()))


class DiskTiles:
    """Arrays that are pure functions of ``key`` and a tile id (the raster tiles of a simulated
    world), one ``.npy`` file a tile under ``<cache root>/memo/<name>-<key>/``, shared by every
    process: a tile that one Dask worker (or an earlier run) computed is read by the others
    instead of being computed again. Written through a temp file and a rename; a tile that
    cannot be read or written is computed (the result is the same either way). Creating the
    directory removes the ones of the same ``name`` under other keys (older code's tiles)."""

    def __init__(self, name: str, key: str) -> None:
        self.name, self.key = name, key
        self.dir = cache_root() / "memo" / f"{name}-{key}"
        self._made = False

    def get(self, tile_id: str):
        """The tile's array, or None when it is not on disk (or unreadable)."""
        from blockloc.fileio import load_array

        try:
            return load_array(self.dir / f"{tile_id}.npy")
        except Exception:  # missing, or cut short / damaged (EOFError, ValueError, ...): compute it
            return None

    def put(self, tile_id: str, array) -> None:
        import io
        import logging
        import shutil

        import numpy as np

        from blockloc.fileio import atomic_write_bytes

        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
        try:
            if not self._made:
                self.dir.mkdir(parents=True, exist_ok=True)
                self._made = True
                for old in superseded_memo_dirs(self.dir.parent, self.name, self.key):
                    shutil.rmtree(old, ignore_errors=True)
            atomic_write_bytes(self.dir / f"{tile_id}.npy", buf.getvalue())
        except OSError as exc:
            logging.getLogger(__name__).debug("%s: tile %s not cached (%s)", self.dir, tile_id, exc)


def superseded_memo_dirs(memo_dir: Path, name: str, key: str) -> list[Path]:
    """Directories ``<name>-<other key>`` in ``memo_dir``, as :func:`superseded_memo_entries`."""
    return superseded_memo_entries(memo_dir, name, key, suffix="")
