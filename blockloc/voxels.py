"""Voxel grids over point clouds: the one voxel filter every stage uses.

Voxels are cubes of edge ``voxel_size_m`` aligned at the origin of the points' frame (voxel of a
point = ``floor(p / voxel_size_m)``). Two ways to reduce a cloud, for two needs:

- :func:`voxel_downsample` keeps the **centroid** of each occupied voxel (and the mean of an
  attribute such as intensity): what maps store and what registration targets are built from.
- :func:`voxel_select` keeps the **first real point** of each occupied voxel (input order) and
  returns its index: for scans whose per-point attributes (time offsets for deskewing, rings) must
  stay exact.

Both return voxels in ascending voxel-key order for :func:`voxel_downsample` and input order for
:func:`voxel_select`; the same input gives the same output on every machine.
"""

from __future__ import annotations

import numpy as np

from blockloc.errors import BlocklocError


def _check_size(voxel_size_m: float) -> float:
    size = float(voxel_size_m)
    if not np.isfinite(size) or size <= 0:
        raise BlocklocError(f"voxel size {voxel_size_m!r}: expected a positive number of metres")
    return size


def voxel_groups(points: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group points by voxel.

    points: (N, 3) float (extra columns ignored), any frame, metres; finite.
    Returns (inverse (N,) int64: each point's voxel number, first (M,) int64: index of the first
    point of each voxel, counts (M,) int64), voxels numbered in ascending key order.
    """
    size = _check_size(voxel_size_m)
    pts = np.asarray(points)[:, :3]
    keys = np.floor(pts.astype(np.float64) / size).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if np.prod(span.astype(np.float64)) < 2.0**62:
        flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        _, first, inverse, counts = np.unique(flat, return_index=True, return_inverse=True,
                                              return_counts=True)
    else:  # astronomically large extents: unique rows instead of one flat key
        _, first, inverse, counts = np.unique(keys, axis=0, return_index=True, return_inverse=True,
                                              return_counts=True)
    return inverse.reshape(-1), first, counts


def voxel_downsample(points: np.ndarray, voxel_size_m: float, intensity: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray | None]:
    """Centroid of the points (and mean intensity) in each occupied voxel.

    points: (N, 3) float, any frame, metres; non-finite rows are dropped first.
    intensity: (N,) or None. Returns (M, 3) float64 centroids and (M,) float32 mean intensity (or
    None), M <= N, in ascending voxel-key order. An empty cloud gives empty arrays;
    ``voxel_size_m <= 0`` returns the points unfiltered.
    """
    pts = np.asarray(points, dtype=np.float64)[:, :3] if len(points) else np.zeros((0, 3))
    inten = None if intensity is None else np.asarray(intensity, dtype=np.float64).reshape(-1)
    if not voxel_size_m > 0:  # no filter: the points as they are
        return pts, None if inten is None else inten.astype(np.float32)
    finite = np.isfinite(pts).all(axis=1)
    if not finite.all():
        pts = pts[finite]
        inten = None if inten is None else inten[finite]
    if len(pts) == 0:
        _check_size(voxel_size_m)
        return np.zeros((0, 3)), None if inten is None else np.zeros(0, np.float32)
    inverse, _, counts = voxel_groups(pts, voxel_size_m)
    m = len(counts)
    out = np.empty((m, 3), np.float64)
    for k in range(3):
        out[:, k] = np.bincount(inverse, weights=pts[:, k], minlength=m) / counts
    out_i = None
    if inten is not None:
        out_i = (np.bincount(inverse, weights=inten, minlength=m) / counts).astype(np.float32)
    return out, out_i


def voxel_select(points: np.ndarray, voxel_size_m: float,
                 range_m: tuple[float, float] | None = None) -> np.ndarray:
    """Indices (M,) int64, ascending, of the first point (input order) in each occupied voxel.

    points: (N, 3+) float32 or float64, any frame, metres (extra columns ignored); finite unless
    ``range_m`` is given. range_m: (min, max) metres from the frame's origin: only finite points
    at a range within [min, max] are considered (a scan's range filter, in the same pass).
    ``voxel_size_m <= 0`` keeps every point (in range).

    One pass with a hash table (``blockloc._voxel_kernels``); the numpy reference
    (:func:`voxel_select_numpy`, the same indices) serves clouds spanning more than 2**20 voxels.
    """
    pts = np.asarray(points)
    n = len(pts)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if not voxel_size_m > 0 or pts.dtype not in (np.float32, np.float64):
        return voxel_select_numpy(pts, voxel_size_m, range_m)
    size = _check_size(voxel_size_m)
    from blockloc._voxel_kernels import select_first, table_bits

    if not pts.flags.c_contiguous:
        pts = np.ascontiguousarray(pts[:, :3])
    lo, hi = (0.0, 0.0) if range_m is None else (float(range_m[0]), float(range_m[1]))
    idx, ok = select_first(pts, size, lo * lo, hi * hi, range_m is not None, table_bits(n))
    return idx if ok else voxel_select_numpy(pts, voxel_size_m, range_m)


def in_range(points: np.ndarray, min_range_m: float, max_range_m: float) -> np.ndarray:
    """Boolean mask (N,) of finite points whose range lies in [min_range_m, max_range_m]."""
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    r2 = np.einsum("ij,ij->i", pts, pts)
    return np.isfinite(r2) & (r2 >= min_range_m**2) & (r2 <= max_range_m**2)


def voxel_select_numpy(points: np.ndarray, voxel_size_m: float,
                       range_m: tuple[float, float] | None = None) -> np.ndarray:
    """The reference of :func:`voxel_select` (numpy: unique over flat voxel keys), same arguments
    and result; any extent."""
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    cand = np.arange(n) if range_m is None else np.flatnonzero(in_range(points, *range_m))
    if not voxel_size_m > 0:
        return cand.astype(np.int64)
    if len(cand) == 0:
        _check_size(voxel_size_m)
        return np.zeros(0, dtype=np.int64)
    pts = np.asarray(points)[cand] if range_m is not None else points
    _, first, _ = voxel_groups(pts, voxel_size_m)
    return cand[np.sort(first)].astype(np.int64)
