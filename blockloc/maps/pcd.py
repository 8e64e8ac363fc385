"""PCD point-cloud files: the tile/block payload format of every map store.

Written files are binary PCD v0.7 with fields ``x y z intensity`` (float32, count 1), the layout
PCL's ``savePCDFileBinary`` produces for ``PointXYZI``, so PCL, CloudCompare, open3d and Autoware
read them. Reading accepts ``ascii``, ``binary`` and ``binary_compressed`` data with any field
layout that has x, y, z (intensity optional; extra fields ignored).

Every malformed input raises :class:`~blockloc.errors.MapError` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from blockloc.errors import MapError
from blockloc.fileio import atomic_write_bytes

_NP_TYPES = {
    ("F", 4): np.float32, ("F", 8): np.float64,
    ("I", 1): np.int8, ("I", 2): np.int16, ("I", 4): np.int32, ("I", 8): np.int64,
    ("U", 1): np.uint8, ("U", 2): np.uint16, ("U", 4): np.uint32, ("U", 8): np.uint64,
}
_HEADER_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT",
                "POINTS", "DATA")


def encode_pcd(points: np.ndarray, intensity: np.ndarray | None = None) -> bytes:
    """Binary PCD bytes for ``points`` (N, 3) and optional ``intensity`` (N,) (zeros when None).

    Coordinates are stored as float32 (metres); N = 0 is allowed.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise MapError(f"points: expected an (N, 3) array, got shape {pts.shape}")
    n = len(pts)
    if intensity is not None:
        inten = np.asarray(intensity, dtype=np.float32).reshape(-1)
        if len(inten) != n:
            raise MapError(f"intensity: expected {n} values, got {len(inten)}")
    else:
        inten = np.zeros(n, np.float32)
    body = np.empty((n, 4), np.float32)
    body[:, :3] = pts
    body[:, 3] = inten
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    return header.encode("ascii") + body.tobytes()


def write_pcd(path: str | Path, points: np.ndarray, intensity: np.ndarray | None = None) -> int:
    """Write a binary PCD (x y z intensity float32) atomically (temp file, then rename).

    Returns the number of bytes written.
    """
    path = Path(path)
    data = encode_pcd(points, intensity)
    atomic_write_bytes(path, data)
    return len(data)


def read_pcd(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PCD file -> (points (N, 3) float32, intensity (N,) float32 or None)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise MapError(f"{path}: no such PCD file") from None
    except OSError as exc:
        raise MapError(f"{path}: cannot read ({exc.strerror})") from None
    return decode_pcd(data, str(path))


def _parse_header(data: bytes, name: str) -> tuple[dict[str, list[str]], int]:
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise MapError(f"{name}: not a PCD file (header ends before a DATA line)")
        raw = data[pos:end]
        pos = end + 1
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise MapError(f"{name}: not a PCD file (binary bytes in the header)") from None
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        key = key.upper()
        if key not in _HEADER_KEYS:
            raise MapError(f"{name}: not a PCD file (unexpected header line {line[:40]!r})")
        header[key] = values
        if key == "DATA":
            return header, pos
        if pos > 1 << 16:
            raise MapError(f"{name}: not a PCD file (no DATA line in the first 64 KiB)")


def decode_pcd(data: bytes, name: str = "<bytes>") -> tuple[np.ndarray, np.ndarray | None]:
    """Parse PCD bytes -> (points (N, 3) float32, intensity (N,) float32 or None).

    ``name`` (a path or URL) is used in error messages.
    """
    header, offset = _parse_header(data, name)
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in header:
            raise MapError(f"{name}: PCD header lacks {key}")
    fields = header["FIELDS"]
    try:
        sizes = [int(v) for v in header["SIZE"]]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(fields))]
        if "POINTS" in header:
            n = int(header["POINTS"][0])
        else:
            n = int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0])
    except (ValueError, IndexError, KeyError):
        raise MapError(f"{name}: PCD header has a non-integer SIZE/COUNT/POINTS/WIDTH") from None
    types = [t.upper() for t in header["TYPE"]]
    if not (len(fields) == len(sizes) == len(types) == len(counts)) or n < 0:
        raise MapError(f"{name}: PCD header FIELDS/SIZE/TYPE/COUNT lengths differ")
    for axis in ("x", "y", "z"):
        if axis not in fields:
            raise MapError(f"{name}: PCD has no '{axis}' field (fields: {' '.join(fields)})")
    dtype_list = []
    for i, (f, s, t, c) in enumerate(zip(fields, sizes, types, counts)):
        np_t = _NP_TYPES.get((t, s))
        if np_t is None:
            raise MapError(f"{name}: PCD field {f!r} has unsupported TYPE {t} SIZE {s}")
        fname = f if f != "_" else f"_pad{i}"
        dtype_list.append((fname, np_t, (c,)) if c != 1 else (fname, np_t))
    dtype = np.dtype(dtype_list)
    kind = header["DATA"][0].lower() if header["DATA"] else ""
    payload = memoryview(data)[offset:]
    if kind == "binary":
        need = n * dtype.itemsize
        if len(payload) < need:
            raise MapError(f"{name}: truncated PCD payload ({len(payload)} bytes, expected {need} "
                           f"for {n} points)")
        arr = np.frombuffer(payload[:need], dtype=dtype, count=n)
    elif kind == "ascii":
        text = bytes(payload).decode("ascii", errors="replace").split()
        ncols = sum(counts)
        if len(text) < n * ncols:
            raise MapError(f"{name}: truncated ASCII PCD ({len(text)} values, expected {n * ncols})")
        try:
            table = np.asarray(text[: n * ncols], dtype=np.float64).reshape(n, ncols)
        except ValueError:
            raise MapError(f"{name}: ASCII PCD payload has non-numeric values") from None
        arr = np.empty(n, dtype=dtype)
        col = 0
        for (fname, *_), c in zip(dtype_list, counts):
            arr[fname] = table[:, col] if c == 1 else table[:, col:col + c]
            col += c
    elif kind == "binary_compressed":
        arr = _decode_compressed(payload, dtype, n, name)
    else:
        raise MapError(f"{name}: unsupported PCD DATA kind {kind!r} (expected ascii, binary, "
                       "binary_compressed)")
    points = np.empty((n, 3), np.float32)
    points[:, 0], points[:, 1], points[:, 2] = arr["x"], arr["y"], arr["z"]
    intensity = np.asarray(arr["intensity"], np.float32).reshape(n) if "intensity" in fields else None
    return points, intensity


def _decode_compressed(payload: memoryview, dtype: np.dtype, n: int, name: str) -> np.ndarray:
    """binary_compressed: uint32 compressed size, uint32 raw size, LZF data stored field by field."""
    import io

    if len(payload) < 8:
        raise MapError(f"{name}: truncated binary_compressed PCD payload")
    csize, rsize = np.frombuffer(payload[:8], dtype="<u4")
    if len(payload) < 8 + int(csize):
        raise MapError(f"{name}: truncated binary_compressed PCD payload "
                       f"({len(payload) - 8} bytes, expected {int(csize)})")
    # pypcd4 carries a tested LZF decoder; use it rather than a hand-written one.
    try:
        import pypcd4

        pc = pypcd4.PointCloud.from_fileobj(io.BytesIO(_rebuild_header(dtype, n) + bytes(payload)))
        arr = pc.pc_data if hasattr(pc, "pc_data") else None
        if arr is None:
            cols = pc.numpy()
            arr = np.empty(n, dtype=dtype)
            for i, fname in enumerate(pc.fields):
                if fname in dtype.names:
                    arr[fname] = cols[:, i]
        return arr
    except MapError:
        raise
    except Exception as exc:  # noqa: BLE001 - any decoder failure means a corrupt payload
        raise MapError(f"{name}: corrupt binary_compressed PCD payload ({exc})") from None


def _rebuild_header(dtype: np.dtype, n: int) -> bytes:
    fields, sizes, types, counts = [], [], [], []
    rev = {v: k for k, v in _NP_TYPES.items()}
    for fname in dtype.names:
        sub = dtype.fields[fname][0]
        base, shape = (sub.base, sub.shape) if sub.shape else (sub, ())
        t, s = rev[base.type]
        fields.append(fname if not fname.startswith("_pad") else "_")
        sizes.append(str(s))
        types.append(t)
        counts.append(str(int(np.prod(shape)) if shape else 1))
    return (f"VERSION 0.7\nFIELDS {' '.join(fields)}\nSIZE {' '.join(sizes)}\nTYPE {' '.join(types)}\n"
            f"COUNT {' '.join(counts)}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
            "DATA binary_compressed\n").encode("ascii")
