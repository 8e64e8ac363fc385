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
        # the previous sample's voxel and whether it is a map voxel: samples come every half voxel,
        # so most share their voxel with the one before (one binary search saved each)
        px_v, py_v, pz_v, on_map = np.int64(-1), np.int64(-1), np.int64(-1), False
        first = True
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
            ix, iy, iz = vx - lo[0], vy - lo[1], vz - lo[2]
            if not (0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz) or grid[ix, iy, iz]:
                continue  # off the grid, or marked already (marks are only ever added): nothing to decide
            if not use_map:
                grid[ix, iy, iz] = 1
                continue
            if first or vx != px_v or vy != py_v or vz != pz_v:
                on_map = _found(map_keys, _pack(vx, vy, vz))
                px_v, py_v, pz_v, first = vx, vy, vz, False
            if on_map:
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
            grid[ix, iy, iz] = 1


_MASK21 = np.int64((1 << 21) - 1)


@njit(cache=True, nogil=True)
def near_any(keys, table, out):
    """``out[n]`` = the voxel of ``keys[n]`` or one of its 26 neighbours is in the sorted
    ``table`` (keys packed as :func:`_pack`): ``detect.near_sorted``'s test, one key at a time
    with an early exit, releasing the GIL."""
    for n in range(keys.shape[0]):
        key = keys[n]
        i = ((key >> (2 * _B21)) & _MASK21) - _OFF
        j = ((key >> _B21) & _MASK21) - _OFF
        k = (key & _MASK21) - _OFF
        found = _found(table, key)
        a = -1
        while not found and a <= 1:
            b = -1
            while not found and b <= 1:
                c = -1
                while not found and c <= 1:
                    found = _found(table, _pack(i + a, j + b, k + c))
                    c += 1
                b += 1
            a += 1
        out[n] = found


@njit(cache=True, nogil=True)
def merge_shifted(a, s):
    """The sorted unique union of ``a - s``, ``a`` and ``a + s`` (``a``: sorted unique int64):
    one axis of a 26-neighbour dilation of packed voxel keys (``s``: the axis' unit in the
    packing), a linear merge instead of a sort."""
    n = a.shape[0]
    out = np.empty(3 * n, np.int64)
    i0 = i1 = i2 = 0
    m = 0
    while i0 < n or i1 < n or i2 < n:
        v = np.int64(9223372036854775807)
        if i0 < n and a[i0] - s < v:
            v = a[i0] - s
        if i1 < n and a[i1] < v:
            v = a[i1]
        if i2 < n and a[i2] + s < v:
            v = a[i2] + s
        if i0 < n and a[i0] - s == v:
            i0 += 1
        if i1 < n and a[i1] == v:
            i1 += 1
        if i2 < n and a[i2] + s == v:
            i2 += 1
        out[m] = v
        m += 1
    return out[:m]


@njit(cache=True, nogil=True)
def merge_counts(k1, h1, f1, k2, h2, f2):
    """The sorted unique union of the sorted unique keys ``k1`` and ``k2`` with their counts
    (``h*``, ``f*``: int64 per key) added where a key is in both: one step of the evidence merge.
    Returns (keys, n_hit, n_free)."""
    n1, n2 = k1.shape[0], k2.shape[0]
    out = np.empty(n1 + n2, np.int64)
    oh = np.empty(n1 + n2, np.int64)
    of = np.empty(n1 + n2, np.int64)
    i = j = m = 0
    while i < n1 and j < n2:
        if k1[i] < k2[j]:
            out[m], oh[m], of[m] = k1[i], h1[i], f1[i]
            i += 1
        elif k2[j] < k1[i]:
            out[m], oh[m], of[m] = k2[j], h2[j], f2[j]
            j += 1
        else:
            out[m], oh[m], of[m] = k1[i], h1[i] + h2[j], f1[i] + f2[j]
            i += 1
            j += 1
        m += 1
    while i < n1:
        out[m], oh[m], of[m] = k1[i], h1[i], f1[i]
        i += 1
        m += 1
    while j < n2:
        out[m], oh[m], of[m] = k2[j], h2[j], f2[j]
        j += 1
        m += 1
    return out[:m], oh[:m], of[:m]


@njit(cache=True, nogil=True)
def point_keys(points, voxel_m, out):
    """``out[n]``: the packed key of the voxel ``floor(points[n] / voxel_m)`` (points (N, 3+)
    float64; the same float operations as ``detect.voxel_keys``), no (N, 3) temporaries."""
    for n in range(points.shape[0]):
        out[n] = _pack(np.int64(np.floor(points[n, 0] / voxel_m)), np.int64(np.floor(points[n, 1] / voxel_m)),
                       np.int64(np.floor(points[n, 2] / voxel_m)))


@njit(cache=True, nogil=True)
def union_sorted(a, b):
    """The sorted unique union of the sorted unique int64 ``a`` and ``b`` (a linear merge)."""
    na, nb = a.shape[0], b.shape[0]
    out = np.empty(na + nb, np.int64)
    i = j = m = 0
    while i < na and j < nb:
        if a[i] < b[j]:
            out[m] = a[i]
            i += 1
        elif b[j] < a[i]:
            out[m] = b[j]
            j += 1
        else:
            out[m] = a[i]
            i += 1
            j += 1
        m += 1
    while i < na:
        out[m] = a[i]
        i += 1
        m += 1
    while j < nb:
        out[m] = b[j]
        j += 1
        m += 1
    return out[:m]
