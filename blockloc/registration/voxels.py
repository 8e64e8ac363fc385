"""Voxel-grid downsampling (numba hash accumulation, one pass)."""

from __future__ import annotations

import numpy as np

from blockloc.errors import RegistrationError


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Centroid of the points in each voxel of edge ``voxel_size`` (grid aligned at the origin).

    points: (N, 3) float (extra columns ignored), any frame, metres -> (M, 3) float64, M <= N,
    in order of first occurrence.
    """
    from blockloc.registration import _ndt_kernels as k

    size = float(voxel_size)
    if not np.isfinite(size) or size <= 0:
        raise RegistrationError(f"voxel_size {voxel_size!r}: expected a positive number of metres")
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise RegistrationError(f"points: expected an (N, 3) array, got shape {arr.shape}")
    xyz = np.ascontiguousarray(arr[:, :3], dtype=np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if len(xyz) == 0:
        return np.empty((0, 3))
    keys, count, sums, _outer, skipped = k.voxel_stats(xyz, 1.0 / size, size)
    if skipped:
        raise RegistrationError(
            f"points: {skipped} points beyond +-{2**20 * size:.0f} m at voxel size {size} m")
    centres = (k.unpack_keys(keys) + 0.5) * size
    return centres + sums / count[:, None]
