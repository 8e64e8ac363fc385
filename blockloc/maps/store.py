"""The map store: a directory of PCD tiles/blocks with a versioned manifest, built atomically.

Layout of a store directory::

    manifest.json                  version, kind ('block' | 'grid'), frame, parameters, entries
    000.pcd 001.pcd ...            block maps (kind 'block'), plus CentroidCloud.pcd: one point per
                                   block, row i = centroid of block i (the released block-map layout)
    {cx}_{cy}.pcd ...              grid tiles (kind 'grid'), named by their centre in metres, plus an
                                   Autoware ``pointcloud_map_metadata.yaml``

Every entry of the manifest records id, file, bounds (min, max; map frame, metres), centroid,
point count, file size and sha256; :meth:`MapStore.load` verifies the checksum.

*Extras* are further files that belong to the map (e.g. the global-init place index): the
manifest's ``extras`` object maps a name to its file, size and sha256 (``MapWriter.add_extra``
during a build, :func:`add_extra` on an existing local store); :meth:`MapStore.load_extra`
verifies the checksum. Readers that predate extras ignore the key.

A directory in the released block-map layout (``%03d.pcd`` + ``CentroidCloud.pcd``, no manifest)
opens as a block map without checksums.

All reads of a store go through :class:`blockloc.maps.files.MapFiles`, the single file-access
layer: local paths read with the standard library, URLs (``http://``, ``s3://``, ...) through
fsspec (:mod:`blockloc.maps.remote`).

Builds are atomic: :class:`MapWriter` writes into a hidden temporary directory beside the output
carrying an ``.incomplete`` marker and renames it into place only after the manifest is written;
an interrupted build leaves no directory that :func:`open_map` accepts.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from blockloc.errors import BlocklocError, MapError
from blockloc.fileio import check_replaceable, replace_dir
from blockloc.maps.files import MapFiles, open_map_files
from blockloc.maps.pcd import decode_pcd, encode_pcd
from blockloc.outdir import process_alive

log = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"
MANIFEST_VERSION = 1
CENTROID_CLOUD = "CentroidCloud.pcd"
AUTOWARE_METADATA = "pointcloud_map_metadata.yaml"
INCOMPLETE_MARKER = ".incomplete"
KINDS = ("block", "grid")
_LEGACY_BLOCK = re.compile(r"^(\d{3,})\.pcd$")


@dataclass(frozen=True)
class MapEntry:
    """One block or tile of a store.

    bounds_min, bounds_max, centroid: (3,) float64, map frame, metres (bounds of the points; for
    grid tiles ``cell_min``/``cell_max`` in the parameters give the cell itself).
    num_points: points in the file. bytes: file size. sha256: hex digest of the file, or None
    (legacy block layout: not verified).
    """

    id: str
    file: str
    bounds_min: np.ndarray
    bounds_max: np.ndarray
    centroid: np.ndarray
    num_points: int
    bytes: int
    sha256: str | None
    keyframes: np.ndarray | None = None  # (K, 3) sensor positions a block was built from, or None

    def to_dict(self) -> dict[str, Any]:
        d = {
            "id": self.id, "file": self.file,
            "bounds_min": [float(v) for v in self.bounds_min],
            "bounds_max": [float(v) for v in self.bounds_max],
            "centroid": [float(v) for v in self.centroid],
            "num_points": int(self.num_points), "bytes": int(self.bytes), "sha256": self.sha256,
        }
        if self.keyframes is not None:
            d["keyframes"] = [[round(float(v), 3) for v in p] for p in self.keyframes]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str) -> "MapEntry":
        try:
            return cls(
                id=str(d["id"]), file=str(d["file"]),
                bounds_min=np.asarray(d["bounds_min"], float).reshape(3),
                bounds_max=np.asarray(d["bounds_max"], float).reshape(3),
                centroid=np.asarray(d["centroid"], float).reshape(3),
                num_points=int(d["num_points"]), bytes=int(d["bytes"]), sha256=d.get("sha256"),
                keyframes=(np.asarray(d["keyframes"], float).reshape(-1, 3)
                           if d.get("keyframes") is not None else None),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise MapError(f"{where}: malformed manifest entry {d!r:.80} ({exc})") from None


@dataclass(frozen=True)
class ExtraFile:
    """An extra file of a store (see the module docstring): its name (the key in the manifest's
    ``extras``), file name in the store, size in bytes and sha256 hex digest."""

    name: str
    file: str
    bytes: int
    sha256: str

    def to_dict(self) -> dict[str, Any]:
        return {"file": self.file, "bytes": int(self.bytes), "sha256": self.sha256}

    @classmethod
    def from_dict(cls, name: str, d: Any, where: str) -> "ExtraFile":
        try:
            extra = cls(str(name), str(d["file"]), int(d["bytes"]), str(d["sha256"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise MapError(f"{where}: malformed 'extras' entry {name!r} ({exc})") from None
        if not _is_plain_name(extra.file):
            raise MapError(f"{where}: extra {name!r} names file {extra.file!r}, expected a plain file name")
        return extra


def _is_plain_name(name: str) -> bool:
    return bool(name) and "/" not in name and "\\" not in name and name not in (".", "..") \
        and not name.startswith(".")


class MapStore:
    """An opened map store (see the module docstring). Entries are kept in manifest order."""

    def __init__(self, files: MapFiles, kind: str, frame: str, params: dict[str, Any],
                 entries: list[MapEntry], version: int = MANIFEST_VERSION, legacy: bool = False,
                 extras: dict[str, ExtraFile] | None = None):
        self.files = files
        self.extras: dict[str, ExtraFile] = dict(extras or {})
        self.kind = kind
        self.frame = frame
        self.params = dict(params)
        self.entries = list(entries)
        self.version = version
        self.legacy = legacy
        self._by_id = {e.id: e for e in self.entries}
        if len(self._by_id) != len(self.entries):
            raise MapError(f"{files.url(MANIFEST_NAME)}: duplicate entry ids in the manifest")
        self._bmin = np.array([e.bounds_min for e in self.entries]).reshape(-1, 3)
        self._bmax = np.array([e.bounds_max for e in self.entries]).reshape(-1, 3)

    @property
    def path(self) -> str:
        """The store's directory (or URL)."""
        return self.files.root

    def __len__(self) -> int:
        return len(self.entries)

    def __repr__(self) -> str:
        return f"MapStore({self.path!r}, kind={self.kind!r}, entries={len(self.entries)})"

    @property
    def ids(self) -> list[str]:
        return [e.id for e in self.entries]

    def entry(self, entry_id: str) -> MapEntry:
        try:
            return self._by_id[entry_id]
        except KeyError:
            raise MapError(f"{self.path}: no block/tile with id {entry_id!r}") from None

    def centroids(self) -> np.ndarray:
        """(M, 3) entry centroids, map frame, metres, in entry order."""
        return np.array([e.centroid for e in self.entries]).reshape(-1, 3)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min (3,), max (3,)) over all entries, map frame, metres."""
        if not self.entries:
            return np.zeros(3), np.zeros(3)
        return self._bmin.min(axis=0), self._bmax.max(axis=0)

    @property
    def total_points(self) -> int:
        return int(sum(e.num_points for e in self.entries))

    @property
    def total_bytes(self) -> int:
        return int(sum(e.bytes for e in self.entries))

    def entries_in_box(self, xy_min: Sequence[float], xy_max: Sequence[float]) -> list[MapEntry]:
        """Entries whose xy bounds intersect the box [xy_min, xy_max] (map frame, metres)."""
        if not self.entries:
            return []
        lo = np.asarray(xy_min, float)[:2]
        hi = np.asarray(xy_max, float)[:2]
        hit = np.all(self._bmax[:, :2] >= lo, axis=1) & np.all(self._bmin[:, :2] <= hi, axis=1)
        return [self.entries[i] for i in np.flatnonzero(hit)]

    def load(self, entry_id: str) -> tuple[np.ndarray, np.ndarray | None]:
        """Points (N, 3) float32 and intensity (N,) float32 | None of one entry.

        The file's sha256 and point count are checked against the manifest; a mismatch, a bad
        header or a truncated payload raises MapError naming the file.
        """
        e = self.entry(entry_id)
        data = self.files.read_bytes(e.file)
        url = self.files.url(e.file)
        if e.sha256 is not None:
            digest = hashlib.sha256(data).hexdigest()
            if digest != e.sha256:
                raise MapError(f"{url}: checksum mismatch (sha256 {digest[:12]}..., manifest says "
                               f"{e.sha256[:12]}...): the file is corrupt or was changed")
        points, intensity = decode_pcd(data, url)
        if len(points) != e.num_points:
            raise MapError(f"{url}: holds {len(points)} points, manifest says {e.num_points}")
        return points, intensity

    def load_points(self, ids: Iterable[str]) -> np.ndarray:
        """Concatenated points (N, 3) float32 of the given entries, map frame."""
        parts = [self.load(i)[0] for i in ids]
        return np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)

    def has_extra(self, name: str) -> bool:
        """Whether the manifest lists the extra file ``name``."""
        return name in self.extras

    def load_extra(self, name: str) -> bytes:
        """Bytes of the extra ``name``, checked against the manifest's size and sha256.

        MapError naming the file when the store has no such extra, the file is missing, or its
        checksum differs. Over HTTP/S3 the file goes through the store's checksum-validated cache.
        """
        extra = self.extras.get(name)
        if extra is None:
            have = ", ".join(sorted(self.extras)) or "none"
            raise MapError(f"{self.files.url(MANIFEST_NAME)}: the map has no extra {name!r} (extras: {have})")
        expect = getattr(self.files, "expect", None)
        if expect is not None:  # remote stores: cache the file under its sha256
            expect(extra.file, extra.sha256)
        data = self.files.read_bytes(extra.file)
        digest = hashlib.sha256(data).hexdigest()
        if digest != extra.sha256 or len(data) != extra.bytes:
            raise MapError(f"{self.files.url(extra.file)}: checksum mismatch (sha256 {digest[:12]}..., "
                           f"{len(data)} bytes; manifest says {extra.sha256[:12]}..., {extra.bytes} bytes): "
                           "the file is corrupt or was changed")
        return data


def open_map(path: str | Path, **remote_options: Any) -> MapStore:
    """Open a store: a local directory or a URL (http(s)://, s3://), holding a manifest store or
    the released block-map layout. ``remote_options`` go to
    :class:`blockloc.maps.remote.RemoteMapFiles` (cache_dir, cache_bytes, retry, ...) and are
    ignored for local paths (see ``blockloc.app.assemble.remote_options``)."""
    files = open_map_files(path, **remote_options)
    if not files.is_remote and not Path(files.root).exists():
        raise MapError(f"{path}: no such map directory")
    if not files.is_remote and not files.is_dir():
        raise MapError(f"{path}: not a map directory (a file; to tile a global PCD use "
                       "'blockloc map tile')")
    if files.exists(INCOMPLETE_MARKER):
        raise MapError(f"{path}: an incomplete (interrupted) map build; rebuild it")
    if files.exists(MANIFEST_NAME):
        return _open_manifest(files)
    if not files.is_remote and files.exists(CENTROID_CLOUD):
        return _open_legacy_block(files)
    raise MapError(f"{path}: not a map store (no {MANIFEST_NAME}, and no {CENTROID_CLOUD} of the "
                   "released block-map layout)")


def open_manifest(files: MapFiles) -> MapStore:
    """The store whose ``manifest.json`` ``files`` (local or remote :class:`MapFiles`) hold."""
    return _open_manifest(files)


def _open_manifest(files: MapFiles) -> MapStore:
    where = files.url(MANIFEST_NAME)
    try:
        doc = json.loads(files.read_bytes(MANIFEST_NAME).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapError(f"{where}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise MapError(f"{where}: expected a JSON object")
    version = doc.get("version")
    if not isinstance(version, int) or version < 1:
        raise MapError(f"{where}: missing or bad 'version' (expected an integer >= 1)")
    if version > MANIFEST_VERSION:
        raise MapError(f"{where}: manifest version {version} is newer than this blockloc reads "
                       f"({MANIFEST_VERSION}); upgrade blockloc")
    kind = doc.get("kind")
    if kind not in KINDS:
        raise MapError(f"{where}: 'kind' is {kind!r}, expected one of {', '.join(KINDS)}")
    raw_entries = doc.get("entries")
    if not isinstance(raw_entries, list):
        raise MapError(f"{where}: 'entries' must be a list")
    entries = [MapEntry.from_dict(d, where) for d in raw_entries]
    raw_extras = doc.get("extras") or {}
    if not isinstance(raw_extras, dict):
        raise MapError(f"{where}: 'extras' must be an object (name -> file, bytes, sha256)")
    extras = {n: ExtraFile.from_dict(n, d, where) for n, d in raw_extras.items()}
    return MapStore(files, kind, str(doc.get("frame", "map")), _parameters(doc.get("parameters"), where),
                    entries, version, extras=extras)


#: Parameters the map's readers compute with: (must be > 0, must be an integer).
_NUMERIC_PARAMETERS = {"block_size_m": (True, False), "tile_size_m": (True, False), "voxel_size_m": (False, False),
                       "keyframe_distance_m": (False, False), "keyframe_angle_deg": (False, False),
                       "name_decimals": (False, True), "num_keyframes": (False, True)}


def _parameters(raw, where: str) -> dict:
    """The manifest's ``parameters``, the ones readers compute with checked (a hand-edited or
    corrupted value fails here, naming the manifest, not later in whatever reads it)."""
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise MapError(f"{where}: 'parameters' must be an object")
    for key, (positive, integer) in _NUMERIC_PARAMETERS.items():
        if key not in raw:
            continue
        v = raw[key]
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) \
            and (not integer or float(v).is_integer()) and (v > 0 if positive else v >= 0)
        if not ok:
            what = "a positive number" if positive else ("a whole number >= 0" if integer else "a number >= 0")
            raise MapError(f"{where}: parameters.{key} is {v!r:.40}, expected {what}")
    origin = raw.get("origin")
    if origin is not None and not (isinstance(origin, list) and len(origin) == 2 and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in origin)):
        raise MapError(f"{where}: parameters.origin is {origin!r:.40}, expected [x, y] in metres")
    return raw


def _open_legacy_block(files: MapFiles) -> MapStore:
    """The released block-map layout: ``%03d.pcd`` blocks + ``CentroidCloud.pcd`` (row i = block i)."""
    centroids, _ = decode_pcd(files.read_bytes(CENTROID_CLOUD), files.url(CENTROID_CLOUD))
    names = {int(m.group(1)): n for n in files.list_names() if (m := _LEGACY_BLOCK.match(n))}
    if len(centroids) == 0:
        raise MapError(f"{files.url(CENTROID_CLOUD)}: holds no block centroids")
    entries = []
    for i, c in enumerate(centroids):
        if i not in names:
            raise MapError(f"{files.url(f'{i:03d}.pcd')}: missing block {i} named by "
                           f"{CENTROID_CLOUD} ({len(centroids)} centroids)")
        data = files.read_bytes(names[i])
        pts, _ = decode_pcd(data, files.url(names[i]))
        lo = pts.min(axis=0) if len(pts) else np.asarray(c, float)
        hi = pts.max(axis=0) if len(pts) else np.asarray(c, float)
        entries.append(MapEntry(f"{i:03d}", names[i], np.asarray(lo, float), np.asarray(hi, float),
                                np.asarray(c, float), len(pts), len(data), None))
    log.info("%s: released block-map layout, %d blocks (no checksums)", files.root, len(entries))
    return MapStore(files, "block", "map", {"layout": "released-block-map"}, entries, legacy=True)


def entry_stats(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bounds_min, bounds_max, centroid), each (3,) float64, of (N, 3) points (zeros when empty)."""
    if len(points) == 0:
        z = np.zeros(3)
        return z, z.copy(), z.copy()
    p = np.asarray(points, np.float64)
    return p.min(axis=0), p.max(axis=0), p.mean(axis=0)


class MapWriter:
    """Builds a store atomically. Use as a context manager::

        with MapWriter(out, "grid", params={...}) as w:
            w.add("1.0_-3.0", points, intensity)
            store = w.commit()

    Files go to a hidden temporary directory beside ``out`` (marked incomplete); ``commit`` writes
    the kind's extra files and the manifest, then renames the directory to ``out``. Leaving the
    block without ``commit`` (an exception, a kill) removes or abandons the temporary directory;
    ``out`` is never touched until the rename.
    """

    def __init__(self, out: str | Path, kind: str, *, frame: str = "map",
                 params: dict[str, Any] | None = None, overwrite: bool = False):
        if kind not in KINDS:
            raise MapError(f"map kind {kind!r}: expected one of {', '.join(KINDS)}")
        self.out = Path(out)
        self.kind = kind
        self.frame = frame
        self.params = dict(params or {})
        self.overwrite = overwrite
        self.entries: list[MapEntry] = []
        self.extras: dict[str, ExtraFile] = {}
        self._ids: set[str] = set()
        self._committed = False
        if self.out.exists() and not overwrite:
            raise MapError(f"{self.out}: already exists (choose another --out, or --overwrite to "
                           "replace the map there)")
        if self.out.exists():
            try:
                check_replaceable(self.out, "--out", ("map store",), "a map store")
            except BlocklocError as exc:
                raise MapError(f"{exc}; --overwrite replaces only a map store") from None
        parent = self.out.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            remove_stale_builds(parent)
            self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.building-", dir=parent))
        except OSError as exc:
            raise MapError(f"{self.out}: cannot create the output directory ({exc})") from None
        (self.tmp / INCOMPLETE_MARKER).write_text(f"build started {time.ctime()} pid {os.getpid()}\n")

    def __enter__(self) -> "MapWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self._committed:
            self.abort()

    def abort(self) -> None:
        """Remove the temporary directory (nothing of ``out`` was written)."""
        shutil.rmtree(self.tmp, ignore_errors=True)

    def add(self, entry_id: str, points: np.ndarray, intensity: np.ndarray | None = None,
            file: str | None = None, centroid: np.ndarray | None = None,
            keyframes: np.ndarray | None = None) -> MapEntry:
        """Write one block/tile: ``points`` (N, 3) map frame metres, ``intensity`` (N,) or None.

        ``centroid`` defaults to the mean of the points.
        """
        if self._committed:
            raise MapError(f"{self.out}: writer already committed")
        file = file or f"{entry_id}.pcd"
        if entry_id in self._ids:
            raise MapError(f"{self.out}: duplicate entry id {entry_id!r}")
        self._ids.add(entry_id)
        data = encode_pcd(points, intensity)
        (self.tmp / file).write_bytes(data)
        lo, hi, mean = entry_stats(points)
        entry = MapEntry(entry_id, file, lo, hi, mean if centroid is None else np.asarray(centroid, float),
                         len(points), len(data), hashlib.sha256(data).hexdigest(),
                         None if keyframes is None else np.asarray(keyframes, float).reshape(-1, 3))
        self.entries.append(entry)
        return entry

    def add_entry(self, entry: MapEntry) -> MapEntry:
        """Record an entry whose file someone else (a build task) already wrote into
        :attr:`tmp` (or the store's URL), with its size and sha256."""
        if self._committed:
            raise MapError(f"{self.out}: writer already committed")
        if entry.id in self._ids:
            raise MapError(f"{self.out}: duplicate entry id {entry.id!r}")
        self._ids.add(entry.id)
        self.entries.append(entry)
        return entry

    def write_extra(self, name: str, data: bytes) -> None:
        """An extra file in the store directory (not an entry)."""
        (self.tmp / name).write_bytes(data)

    def add_extra(self, name: str, data: bytes) -> ExtraFile:
        """An extra file ``name`` recorded in the manifest with its size and sha256 (e.g. the
        global-init place index); read it back with :meth:`MapStore.load_extra`."""
        if self._committed:
            raise MapError(f"{self.out}: writer already committed")
        if not _is_plain_name(name) or name in (MANIFEST_NAME, CENTROID_CLOUD, AUTOWARE_METADATA, INCOMPLETE_MARKER) \
                or any(e.file == name for e in self.entries):
            raise MapError(f"{self.out}: extra name {name!r} is not a plain file name free in the store")
        self.write_extra(name, data)
        extra = ExtraFile(name, name, len(data), hashlib.sha256(data).hexdigest())
        self.extras[name] = extra
        return extra

    def commit(self) -> MapStore:
        """Write the kind's extra files and the manifest, rename into place, return the open store."""
        if self.kind == "block":
            cents = np.array([e.centroid for e in self.entries], np.float32).reshape(-1, 3)
            self.write_extra(CENTROID_CLOUD, encode_pcd(cents, np.arange(len(cents), dtype=np.float32)))
        elif self.kind == "grid":
            self.write_extra(AUTOWARE_METADATA, autoware_metadata(self.entries, self.params).encode())
        doc = {
            "version": MANIFEST_VERSION, "kind": self.kind, "frame": self.frame,
            "parameters": self.params, "created": _created(),
            "entries": [e.to_dict() for e in self.entries],
        }
        if self.extras:
            doc["extras"] = {n: x.to_dict() for n, x in self.extras.items()}
        (self.tmp / MANIFEST_NAME).write_text(json.dumps(doc, indent=1))
        _fsync_dir_files(self.tmp)
        (self.tmp / INCOMPLETE_MARKER).unlink()
        if self.out.exists() and not self.overwrite:
            self.abort()
            raise MapError(f"{self.out}: appeared during the build; not overwritten")
        replace_dir(self.tmp, self.out, "map store")
        self._committed = True
        log.info("wrote %s map %s: %d entries", self.kind, self.out, len(self.entries))
        return open_map(self.out)


def add_extra(path: str | Path, name: str, data: bytes) -> MapStore:
    """Add (or replace) the extra file ``name`` of the existing local manifest store at ``path``.

    The file is written under a new name (temporary file, fsync, rename), then the manifest is
    replaced atomically: a reader sees the old manifest with the old file or the new one with
    the new file, never a mismatch. A replaced extra's old file is removed afterwards. Returns the
    reopened store.
    """
    from blockloc.fileio import atomic_write_bytes

    root = Path(path)
    store = open_map(root)
    if store.files.is_remote or store.legacy:
        raise MapError(f"{path}: extras can be added only to a local store with a manifest")
    if not _is_plain_name(name) or name in (MANIFEST_NAME, CENTROID_CLOUD, AUTOWARE_METADATA, INCOMPLETE_MARKER) \
            or any(e.file == name for e in store.entries):
        raise MapError(f"{path}: extra name {name!r} is not a plain file name free in the store")
    sha = hashlib.sha256(data).hexdigest()
    old = store.extras.get(name)
    if old is not None and old.sha256 == sha and old.bytes == len(data) and (root / old.file).exists():
        return store  # the same content is there already
    # A new file name when one is in use, so the old manifest never points at new bytes.
    file = name if old is None and not (root / name).exists() else f"{name}.{sha[:12]}"
    atomic_write_bytes(root / file, data)
    _fsync_dir_files_named(root, [file])
    where = root / MANIFEST_NAME
    try:
        doc = json.loads(where.read_text())
    except (OSError, ValueError) as exc:
        raise MapError(f"{where}: cannot read the manifest ({exc})") from None
    doc.setdefault("extras", {})[name] = ExtraFile(name, file, len(data), sha).to_dict()
    atomic_write_bytes(where, json.dumps(doc, indent=1).encode())
    if old is not None and old.file != file:
        (root / old.file).unlink(missing_ok=True)
    log.info("%s: extra %s written (%d bytes)", root, file, len(data))
    return open_map(root)


def _created() -> str:
    """The manifest's creation time: now, or $SOURCE_DATE_EPOCH (seconds, UTC) when set, so that
    two builds of the same inputs can be byte-identical (reproducible-builds.org)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if epoch.isdigit():
        return time.strftime("%Y-%m-%dT%H:%M:%S+0000", time.gmtime(int(epoch)))
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def remove_stale_builds(parent: Path) -> list[Path]:
    """Remove ``.NAME.building-*`` directories in ``parent`` left by builds whose process is gone
    (killed: nothing could clean up). A build whose process still runs, or whose marker cannot be
    read, is left alone. Returns what was removed."""
    removed = []
    for d in Path(parent).glob(".*.building-*"):
        marker = d / INCOMPLETE_MARKER
        try:
            pid = int(marker.read_text().split("pid")[-1].split()[0])
        except (OSError, ValueError, IndexError):
            continue
        if process_alive(pid):
            continue
        shutil.rmtree(d, ignore_errors=True)
        log.warning("removed %s, left by an interrupted build (process %d is gone)", d, pid)
        removed.append(d)
    return removed


def autoware_metadata(entries: list[MapEntry], params: dict[str, Any]) -> str:
    """Autoware ``pointcloud_map_metadata.yaml``: resolutions, then ``file: [min_x, min_y]`` per tile."""
    size = float(params["tile_size_m"])
    lines = [f"x_resolution: {size!r}", f"y_resolution: {size!r}"]
    for e in entries:
        cx, cy = (float(v) for v in e.id.split("_"))
        lines.append(f"{e.file}: [{round(cx - size / 2, 9)!r}, {round(cy - size / 2, 9)!r}]")
    return "\n".join(lines) + "\n"


def _fsync_dir_files(path: Path) -> None:
    _fsync_dir_files_named(path, [p.name for p in path.iterdir()])


def _fsync_dir_files_named(path: Path, names: list[str]) -> None:
    for p in (path / n for n in names):
        try:
            fd = os.open(p, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError:
            pass
