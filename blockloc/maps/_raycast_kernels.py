"""Numba kernel of :mod:`blockloc.maps.raycast` (compiled once, cached on disk; imported only
when rays are walked, so ``blockloc --help`` does not load numba)."""

from __future__ import annotations

import numpy as np
from numba import njit

_OFF = np.int64(1 << 20)  # detect.pack_keys' layout: 21 bits per axis, offset 2^20 (tests check)
_B21 = np.int64(21)


@njit(cache=True, nogil=True, inline="always")
def _pack(i, j, k):
    return ((i + _OFF) << (2 * _B21)) | ((j + _OFF) << _B21) | (k + _OFF)


@njit(cache=True, nogil=True, inline="always")
def _found(table, key):
    n = table.shape[0]
    if n == 0:
        return False
    j = np.searchsorted(table, key)
    return j < n and table[j] == key


@njit(cache=True, nogil=True)
def mark_free(origin, u, usable, step, voxel_m, lo, grid, use_map, map_keys, fine_m, fine_keys,
              use_hits, hit_fine):
    """Set ``grid[v - lo] = 1`` for the voxel v of every sample ``origin + u[r] * (k + 0.5) *
    step`` short of ``usable[r]`` (origin (3,), u (R, 3) unit rays, metres). With ``use_map``, a
    sample in a map voxel (its key in the sorted ``map_keys``) counts only in an occupied fine
    cell (sorted ``fine_keys``, edge ``fine_m``) with, when ``use_hits``, none of the 27 cells
    around it in the sorted ``hit_fine``."""
    nx, ny, nz = grid.shape
    for r in range(u.shape[0]):
        ll = usable[r]
        k = 0
        while True:
            t = (k + 0.5) * step
            if not t < ll:
                break
            k += 1
            px = origin[0] + u[r, 0] * t
            py = origin[1] + u[r, 1] * t
            pz = origin[2] + u[r, 2] * t
            vx = np.int64(np.floor(px / voxel_m))
            vy = np.int64(np.floor(py / voxel_m))
            vz = np.int64(np.floor(pz / voxel_m))
            if use_map and _found(map_keys, _pack(vx, vy, vz)):
                fx = np.int64(np.floor(px / fine_m))
                fy = np.int64(np.floor(py / fine_m))
                fz = np.int64(np.floor(pz / fine_m))
                if not _found(fine_keys, _pack(fx, fy, fz)):
                    continue
                if use_hits:
                    near = False
                    for a in range(-1, 2):
                        for b in range(-1, 2):
                            for c in range(-1, 2):
                                if not near and _found(hit_fine, _pack(fx + a, fy + b, fz + c)):
                                    near = True
                    if near:
                        continue
            ix, iy, iz = vx - lo[0], vy - lo[1], vz - lo[2]
            if 0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz:
                grid[ix, iy, iz] = 1
