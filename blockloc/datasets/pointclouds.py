"""Point-cloud files as exported by SLAM systems and drivers: PCD, KITTI ``.bin`` and PLY.

Readers return a :class:`CloudData`: points (N, 3) in the file's own frame (metres), intensity,
ring and per-point time offsets when the file carries them. Libraries do the parsing:
``pypcd4`` for PCD (``ascii``, ``binary``, ``binary_compressed``; any field set), ``plyfile``
for PLY (ascii and binary, every vertex property of any type kept, and an exception for a
truncated file; open3d's tensor reader, tried here, skipped uint16/uint32 properties such as
``ring`` and Ouster's ``t``, returned a half-truncated file as a full cloud with only a warning,
and a non-PLY file as an empty cloud), numpy for KITTI ``.bin`` (float32 x y z intensity records).

Field names are matched case-insensitively, with CloudCompare's ``scalar_`` prefix stripped:
- intensity: ``intensity``, ``i``, ``reflectance``, ``remission``, ``reflectivity`` (first found);
- ring: ``ring``, ``line``, ``channel``, ``laser_id``, ``ring_id``, ``beam`` -> uint16;
- per-point time: ``time``, ``t``, ``timestamp``, ``offset_time``, ``time_offset``,
  ``time_stamp``, ``stamp``, ``ts``, each optionally with a unit suffix ``_s``, ``_ms``, ``_us``,
  ``_ns`` (``_sec``, ``_msec``, ``_usec``, ``_nsec``), which then fixes the unit.

Per-point time rules (:func:`decode_point_times`), with ``lo``, ``hi`` the smallest and largest
value and ``span = hi - lo``:
- *absolute* (UNIX time) when ``lo > 1e5`` and ``lo > 100 * span``: real offsets start near 0
  (or below it), absolute stamps sit far from 0 compared with the sweep they span. Unit by
  magnitude of ``lo``: < 1e11 seconds, < 1e14 milliseconds, < 1e17 microseconds, else nanoseconds.
  Absolute times stored as float32 (about 2 min resolution at today's epoch) are useless and are
  ignored with a warning.
- otherwise *relative* offsets, unit by the span (a sweep lasts well under 2 s): span <= 2
  seconds (integers: never seconds), <= 2e3 milliseconds, <= 2e6 microseconds, else nanoseconds.
Offsets come back in seconds relative to the scan stamp: to the ``stamp`` given to
:func:`read_point_cloud`, or, for absolute times without one, to the earliest point (the sweep
start, which then becomes ``CloudData.stamp``). Relative offsets are returned as stored (relative
to whatever stamp the exporter used).

Points with a NaN/inf coordinate (organised clouds pad with them) are dropped and counted
(logged at INFO, ``CloudData.num_dropped``). A missing, unreadable, truncated or malformed file
raises :class:`~blockloc.errors.DatasetError` naming the path and what was expected.
"""

from __future__ import annotations

import logging
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from blockloc.errors import DatasetError
from blockloc.fileio import atomic_path

log = logging.getLogger(__name__)

#: File suffixes the readers accept (case-insensitive).
CLOUD_SUFFIXES = (".pcd", ".bin", ".ply")

INTENSITY_NAMES = ("intensity", "i", "reflectance", "remission", "reflectivity")
RING_NAMES = ("ring", "line", "channel", "laser_id", "ring_id", "beam")
TIME_NAMES = ("time", "t", "timestamp", "offset_time", "time_offset", "time_stamp", "stamp", "ts")
_UNIT_SUFFIX = {"s": 1.0, "sec": 1.0, "ms": 1e-3, "msec": 1e-3, "us": 1e-6, "usec": 1e-6,
                "ns": 1e-9, "nsec": 1e-9}
_TIME_RE = re.compile(r"^(?P<base>%s)(_(?P<unit>%s))?$" % ("|".join(TIME_NAMES),
                                                           "|".join(_UNIT_SUFFIX)))
_KITTI_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])


@dataclass
class CloudData:
    """One point cloud read from a file.

    points: (N, 3) float32 (float64 when the file stores float64 coordinates), file frame, metres,
        all finite.
    intensity: (N,) float32 or None. ring: (N,) uint16 or None.
    time_offsets: (N,) float32 seconds relative to the scan stamp, or None (no time field).
    stamp: absolute time (s) the offsets refer to, when the file's times are absolute (the
        ``stamp`` asked for, or the earliest point's time); None for relative or no times.
    time_field: the field the times came from, or None. num_dropped: non-finite points dropped.
    """

    path: Path
    points: np.ndarray
    intensity: np.ndarray | None = None
    ring: np.ndarray | None = None
    time_offsets: np.ndarray | None = None
    stamp: float | None = None
    time_field: str | None = None
    num_dropped: int = 0

    def __len__(self) -> int:
        return len(self.points)


# ----------------------------------------------------------------------------- field matching


def _canonical(name: str) -> str:
    low = name.lower()
    return low[len("scalar_"):] if low.startswith("scalar_") else low


def _find_field(names, wanted) -> str | None:
    by_canon = {}
    for n in names:
        by_canon.setdefault(_canonical(n), n)
    return next((by_canon[w] for w in wanted if w in by_canon), None)


def _find_time_field(names) -> tuple[str | None, float | None]:
    """(field name, unit scale in s or None when the unit is to be inferred)."""
    best = None
    for n in names:
        m = _TIME_RE.match(_canonical(n))
        if m is None:
            continue
        rank = TIME_NAMES.index(m["base"])
        if best is None or rank < best[0]:
            best = (rank, n, _UNIT_SUFFIX[m["unit"]] if m["unit"] else None)
    return (None, None) if best is None else (best[1], best[2])


# ----------------------------------------------------------------------------- per-point times


def decode_point_times(values: np.ndarray, unit_s: float | None = None,
                       source: str = "cloud") -> tuple[float, np.ndarray, bool] | None:
    """A per-point time field (N,) -> (base_s, rel_s (N,) float64, absolute) or None if unusable.

    The times in seconds are ``base_s + rel_s``; ``absolute`` says whether they are UNIX times
    (see the module docstring for the rules). ``unit_s``: the unit when a field-name suffix gave
    it, else inferred. Kept apart as base + relative so that float64 keeps microseconds at
    today's epoch and int64 nanoseconds are not rounded. None (with a warning naming ``source``)
    for float32 absolute times.
    """
    v = np.asarray(values)
    if v.size == 0:
        return 0.0, np.zeros(0), False
    finite = np.isfinite(v) if np.issubdtype(v.dtype, np.floating) else np.ones(len(v), bool)
    if not finite.any():
        return None
    is_int = np.issubdtype(v.dtype, np.integer)
    lo = v[finite].min()
    hi = v[finite].max()
    span = float(hi) - float(lo)
    absolute = float(lo) > 1e5 and float(lo) > 100.0 * span
    if unit_s is None:
        if absolute:
            mag = float(lo)
            unit_s = 1.0 if mag < 1e11 else 1e-3 if mag < 1e14 else 1e-6 if mag < 1e17 else 1e-9
        elif span <= 2.0 and not is_int:
            unit_s = 1.0
        else:
            unit_s = 1e-3 if span <= 2e3 else 1e-6 if span <= 2e6 else 1e-9
    if absolute and v.dtype == np.float32:
        log.warning("%s: per-point times are absolute but stored as float32 (resolution ~%.0f s);"
                    " ignored", source, float(np.spacing(np.float32(lo))) * unit_s)
        return None
    if is_int:
        base = int(lo) if absolute else 0
        rel = (v.astype(np.int64) - np.int64(base)).astype(np.float64) * unit_s
        return base * unit_s, rel, absolute
    base = float(lo) if absolute else 0.0
    rel = (v.astype(np.float64) - base) * unit_s
    return base * unit_s, rel, absolute


# ----------------------------------------------------------------------------- raw readers


def read_fields(path: str | Path) -> np.ndarray:
    """All fields of a point-cloud file as a structured array (N,) (x, y, z and whatever else
    the file stores). PCD fields with COUNT > 1 appear as ``name__0000``, ``name__0001``, ...

    Raises DatasetError naming the path for a missing, truncated or malformed file, or a suffix
    other than .pcd, .bin or .ply.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise DatasetError(f"{path}: unknown point-cloud suffix {path.suffix!r}, expected one of "
                           f"{', '.join(CLOUD_SUFFIXES)}")
    if not path.is_file():
        raise DatasetError(f"{path}: no such point-cloud file")
    if suffix == ".pcd":
        arr = _read_pcd(path)
    elif suffix == ".bin":
        arr = _read_kitti_bin(path)
    else:
        arr = _read_ply(path)
    missing = [a for a in "xyz" if a not in (arr.dtype.names or ())]
    if missing:
        raise DatasetError(f"{path}: no field(s) {', '.join(missing)} (has "
                           f"{' '.join(arr.dtype.names or ())}); expected x, y, z coordinates")
    return arr


def _pcd_header(path: Path) -> tuple[list[str], int]:
    """Header lines (comments dropped) and the byte offset where the payload starts."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    lines, pos = [], 0
    while True:
        end = head.find(b"\n", pos)
        if end < 0:
            raise DatasetError(f"{path}: not a PCD file (no DATA line in its header), expected a "
                               "PCD v0.7 header (FIELDS, SIZE, TYPE, COUNT, POINTS, DATA)")
        try:
            line = head[pos:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise DatasetError(f"{path}: not a PCD file (binary bytes in its header), expected a "
                               "PCD v0.7 header") from None
        pos = end + 1
        if line and not line.startswith("#"):
            lines.append(line)
            if line.upper().startswith("DATA"):
                return lines, pos


def _read_pcd(path: Path) -> np.ndarray:
    import pypcd4

    lines, offset = _pcd_header(path)
    try:
        meta = pypcd4.MetaData.parse_header(lines)
        dtype = meta.build_dtype()
    except Exception as exc:  # noqa: BLE001 - pydantic / KeyError for an unsupported TYPE+SIZE
        raise DatasetError(f"{path}: malformed PCD header ({str(exc).splitlines()[0]}), expected "
                           "FIELDS/SIZE/TYPE/COUNT of equal length with TYPE F, I or U") from None
    n, kind = int(meta.points), meta.data.value
    payload = path.stat().st_size - offset
    what = f"{n} points ({' '.join(meta.fields)}" + (")" if kind == "ascii" else
                                                       f", {dtype.itemsize} bytes each)")
    if kind == "binary" and payload < n * dtype.itemsize:
        raise DatasetError(f"{path}: truncated binary PCD: {payload} payload bytes, expected "
                           f"{n * dtype.itemsize} for {what}")
    # a header that undercounts its payload would read as a silently shorter cloud
    width, height = int(getattr(meta, "width", n) or n), int(getattr(meta, "height", 1) or 1)
    if width * height != n:
        raise DatasetError(f"{path}: PCD header does not match itself: WIDTH {width} x HEIGHT {height} "
                           f"is {width * height} points, POINTS says {n}")
    if kind == "binary" and payload > n * dtype.itemsize:
        raise DatasetError(f"{path}: PCD header does not match its payload: {payload} payload bytes hold "
                           f"{payload / dtype.itemsize:g} points, the header says {what}")
    if kind == "ascii":
        with open(path, "rb") as fh:
            fh.seek(offset)
            rows = sum(1 for line in fh if line.strip())
        if rows < n:
            raise DatasetError(f"{path}: truncated ascii PCD: {rows} rows, expected {what}")
        if rows > n:
            raise DatasetError(f"{path}: PCD header does not match its payload: {rows} rows, the header "
                               f"says {what}")
    if kind.startswith("binary") and kind != "binary" and n > 0:
        with open(path, "rb") as fh:
            fh.seek(offset)
            sizes = fh.read(8)
        csize = struct.unpack("<II", sizes)[0] if len(sizes) == 8 else None
        if csize is None or payload < 8 + csize:
            raise DatasetError(f"{path}: truncated binary_compressed PCD: {payload} payload bytes, "
                               f"expected 8 + {csize if csize is not None else '?'} (LZF block) "
                               f"for {what}")
    try:
        with open(path, "rb") as fh:
            arr = pypcd4.PointCloud.from_fileobj(fh).pc_data
    except Exception as exc:  # noqa: BLE001 - any decoder failure means a corrupt payload
        raise DatasetError(f"{path}: corrupt {kind} PCD payload ({str(exc).splitlines()[0]}), "
                           f"expected {what}") from None
    arr = np.atleast_1d(arr)
    if len(arr) != n:
        raise DatasetError(f"{path}: truncated {kind} PCD: {len(arr)} points, expected {what}")
    return arr


def _read_kitti_bin(path: Path) -> np.ndarray:
    size = path.stat().st_size
    if size == 0 or size % _KITTI_DTYPE.itemsize:
        raise DatasetError(f"{path}: {size} bytes, expected a non-empty multiple of 16 (KITTI .bin: "
                           "float32 x y z intensity per point); truncated?")
    return np.fromfile(path, dtype=_KITTI_DTYPE)


def _read_ply(path: Path) -> np.ndarray:
    from plyfile import PlyData

    try:
        ply = PlyData.read(str(path), mmap=False)
        vertex = ply["vertex"]
        arr = np.asarray(vertex.data)
    except KeyError:
        raise DatasetError(f"{path}: PLY has no 'vertex' element, expected vertices with x y z") from None
    except Exception as exc:  # noqa: BLE001 - plyfile raises PlyParseError, ValueError, struct errors
        raise DatasetError(f"{path}: unreadable or truncated PLY ({str(exc).splitlines()[0]}), "
                           "expected a PLY file with a vertex element x y z") from None
    if len(arr) != vertex.count:
        raise DatasetError(f"{path}: truncated PLY: {len(arr)} vertices, expected {vertex.count}")
    return arr


# ----------------------------------------------------------------------------- the reader


def read_point_cloud(path: str | Path, *, stamp: float | None = None, min_range_m: float = 0.0,
                     max_range_m: float = np.inf) -> CloudData:
    """Read a PCD, KITTI ``.bin`` or PLY file -> :class:`CloudData` (see the module docstring).

    stamp: the scan's stamp (s), to which absolute per-point times are made relative.
    min_range_m, max_range_m: points outside this distance from the sensor origin are dropped
    (not counted as non-finite).
    """
    path = Path(path)
    arr = read_fields(path)
    names = arr.dtype.names
    xyz_dtype = np.float64 if any(arr.dtype[a] == np.float64 for a in "xyz") else np.float32
    pts = np.empty((len(arr), 3), xyz_dtype)
    for k, a in enumerate("xyz"):
        pts[:, k] = arr[a]
    finite = np.isfinite(pts).all(axis=1)
    dropped = int((~finite).sum())
    if dropped:
        log.info("%s: dropped %d of %d points with NaN/inf coordinates", path, dropped, len(pts))
    keep = finite
    if min_range_m > 0 or np.isfinite(max_range_m):
        r2 = np.einsum("ij,ij->i", pts.astype(np.float64), pts.astype(np.float64))
        keep = keep & (r2 >= min_range_m ** 2) & (r2 <= max_range_m ** 2)
    out = CloudData(path, pts[keep], num_dropped=dropped)
    name = _find_field(names, INTENSITY_NAMES)
    if name is not None:
        out.intensity = np.asarray(arr[name][keep], np.float32)
    name = _find_field(names, RING_NAMES)
    if name is not None:
        ring = np.asarray(arr[name][keep], np.float64)
        out.ring = np.clip(np.rint(np.nan_to_num(ring)), 0, 65535).astype(np.uint16)
    name, unit = _find_time_field(names)
    if name is not None:
        decoded = decode_point_times(arr[name][keep], unit, source=f"{path}:{name}")
        if decoded is not None:
            base, rel, absolute = decoded
            rel = np.nan_to_num(rel)
            if absolute:
                ref = float(base) if stamp is None else float(stamp)
                out.time_offsets = (rel + (base - ref)).astype(np.float32)
                out.stamp = ref
            else:
                out.time_offsets = rel.astype(np.float32)
                out.stamp = None if stamp is None else float(stamp)
            out.time_field = name
            if len(rel) and float(rel.max() - rel.min()) > 5.0:
                log.warning("%s: per-point times (field %r) span %.1f s, expected one sweep "
                            "(< 1 s): check their unit", path, name, float(rel.max() - rel.min()))
    return out


def cloud_time_range(path: str | Path) -> tuple[float, float] | None:
    """(earliest, latest) absolute per-point time (s) of a cloud file, or None when it has no
    absolute per-point times."""
    arr = read_fields(path)
    name, unit = _find_time_field(arr.dtype.names)
    if name is None:
        return None
    decoded = decode_point_times(arr[name], unit, source=f"{path}:{name}")
    if decoded is None or not decoded[2] or len(decoded[1]) == 0:
        return None
    base, rel, _ = decoded
    return base + float(np.nanmin(rel)), base + float(np.nanmax(rel))


# ----------------------------------------------------------------------------- writer


def write_point_cloud(path: str | Path, points: np.ndarray, *, intensity: np.ndarray | None = None,
                      ring: np.ndarray | None = None, extra: dict[str, np.ndarray] | None = None,
                      encoding: str = "binary", viewpoint=None) -> Path:
    """Write a cloud as PCD, KITTI ``.bin`` or PLY (by suffix), atomically.

    points: (N, 3) metres (stored float32, or float64 if given float64). intensity (N,) float32,
    ring (N,) uint16 and ``extra`` fields (name -> (N,) array, stored with its own dtype, e.g.
    ``{"time": offsets_f32}`` or ``{"t": ns_u32}``) are optional. ``encoding``: PCD ``ascii``,
    ``binary`` or ``binary_compressed``; PLY ``ascii`` or ``binary`` (little endian); ignored for
    ``.bin``, which holds x y z intensity only (intensity 0 when None). viewpoint: PCD only, the
    header's ``VIEWPOINT tx ty tz qw qx qy qz`` (the sensor pose in the cloud's frame; default
    identity).
    """
    path = Path(path)
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise DatasetError(f"{path}: points of shape {pts.shape}, expected (N, 3)")
    n = len(pts)
    cols: dict[str, np.ndarray] = {}
    xyz_t = np.float64 if pts.dtype == np.float64 else np.float32
    for k, a in enumerate("xyz"):
        cols[a] = pts[:, k].astype(xyz_t)
    if intensity is not None:
        cols["intensity"] = np.asarray(intensity, np.float32).reshape(-1)
    if ring is not None:
        cols["ring"] = np.asarray(ring, np.uint16).reshape(-1)
    for k, v in (extra or {}).items():
        cols[k] = np.asarray(v).reshape(-1)
    bad = [k for k, v in cols.items() if len(v) != n]
    if bad:
        raise DatasetError(f"{path}: field(s) {', '.join(bad)} do not hold {n} values, one per point")
    suffix = path.suffix.lower()
    with atomic_path(path) as tmp:
        if suffix == ".pcd":
            import pypcd4

            if encoding not in ("ascii", "binary", "binary_compressed"):
                raise DatasetError(f"{path}: PCD encoding {encoding!r}, expected ascii, binary or "
                                   "binary_compressed")
            pc = pypcd4.PointCloud.from_points(list(cols.values()), tuple(cols),
                                               tuple(v.dtype for v in cols.values()))
            if viewpoint is not None:
                pc.metadata.viewpoint = tuple(float(v) for v in np.asarray(viewpoint, float).reshape(7))
            with open(tmp, "wb") as fh:
                pc.save(fh, encoding=pypcd4.Encoding(encoding))
        elif suffix == ".bin":
            if set(cols) - {"x", "y", "z", "intensity"}:
                raise DatasetError(f"{path}: a KITTI .bin holds x y z intensity only; got "
                                   f"{' '.join(cols)}")
            rec = np.zeros(n, _KITTI_DTYPE)
            for k in ("x", "y", "z", "intensity"):
                if k in cols:
                    rec[k] = cols[k]
            rec.tofile(tmp)
        elif suffix == ".ply":
            from plyfile import PlyData, PlyElement

            if encoding not in ("ascii", "binary"):
                raise DatasetError(f"{path}: PLY encoding {encoding!r}, expected ascii or binary")
            rec = np.empty(n, [(k, v.dtype) for k, v in cols.items()])
            for k, v in cols.items():
                rec[k] = v
            PlyData([PlyElement.describe(rec, "vertex")], text=encoding == "ascii",
                    byte_order="<").write(str(tmp))
        else:
            raise DatasetError(f"{path}: unknown point-cloud suffix {path.suffix!r}, expected one "
                               f"of {', '.join(CLOUD_SUFFIXES)}")
    return path
