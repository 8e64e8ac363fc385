"""The voxels a scan's rays pass through, compiled: what the change detector and the dynamic-point
remover spend their time on.

:func:`free_voxels` gives exactly the voxels of
:func:`blockloc.maps.changes.detect.ray_free_keys`: each ray sampled
every half voxel, at ``(k + 0.5) * step`` from the origin while short of its usable length, the
sample's voxel taken by ``floor(p / voxel_m)``, with the same float64 operations in the same order
(numba does not fuse them), so the same voxels. It marks them in a dense byte grid over the scan's
bounding box instead of sorting every sample's key: 30k rays of up to 80 m are ~6M samples, of
which some 200k voxels are distinct.

Pure numpy / numba on arrays in one frame (metres).
"""

from __future__ import annotations

import numpy as np

#: above this many cells in the scan's bounding box (a stray far point) the dense grid is not
#: worth its memory: the caller's sorting path runs instead (returns None)
MAX_GRID_CELLS = 64_000_000

_kernel = None


def _compiled():
    global _kernel
    if _kernel is None:
        import numba

        off = np.int64(1 << 20)  # detect.pack_keys' layout: 21 bits per axis, offset 2^20 (tests check)
        b21 = np.int64(21)

        @numba.njit(cache=True, nogil=True, inline="always")
        def pack(i, j, k):
            return ((i + off) << (2 * b21)) | ((j + off) << b21) | (k + off)

        @numba.njit(cache=True, nogil=True, inline="always")
        def found(table, key):
            n = table.shape[0]
            if n == 0:
                return False
            j = np.searchsorted(table, key)
            return j < n and table[j] == key

        @numba.njit(cache=True, nogil=True)
        def mark(origin, u, usable, step, voxel_m, lo, grid, use_map, map_keys, fine_m, fine_keys,
                 use_hits, hit_fine):
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
                    if use_map and found(map_keys, pack(vx, vy, vz)):
                        # inside a map voxel: through only where it crosses an occupied fine cell
                        # that is not next to one of this scan's own hits
                        fx = np.int64(np.floor(px / fine_m))
                        fy = np.int64(np.floor(py / fine_m))
                        fz = np.int64(np.floor(pz / fine_m))
                        if not found(fine_keys, pack(fx, fy, fz)):
                            continue
                        if use_hits:
                            near = False
                            for a in range(-1, 2):
                                for b in range(-1, 2):
                                    for c in range(-1, 2):
                                        if not near and found(hit_fine, pack(fx + a, fy + b, fz + c)):
                                            near = True
                            if near:
                                continue
                    ix, iy, iz = vx - lo[0], vy - lo[1], vz - lo[2]
                    if 0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz:
                        grid[ix, iy, iz] = 1

        _kernel = mark
    return _kernel


def free_voxels(origin: np.ndarray, endpoints: np.ndarray, voxel_m: float, margin_m,
                fine: tuple | None = None, hit_fine: np.ndarray | None = None) -> np.ndarray | None:
    """(M, 3) int64 indices (``floor(p / voxel_m)``), in row-major order, of the voxels the rays
    ``origin`` (3,) -> each of ``endpoints`` (N, 3) pass through, up to ``margin_m`` (a number or
    (N,) per ray) short of the endpoint; ``fine`` and ``hit_fine`` as
    :func:`~blockloc.maps.changes.detect.ray_free_keys` takes them (keys packed as its
    ``pack_keys`` packs them). None when the scan's bounding box would need more than
    :data:`MAX_GRID_CELLS` cells."""
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(endpoints, dtype=np.float64)[:, :3] - origin
    length = np.linalg.norm(d, axis=1)
    usable = length - margin_m
    keep = usable > 0
    d, length, usable = d[keep], length[keep], usable[keep]
    if not len(d):
        return np.zeros((0, 3), dtype=np.int64)
    u = d / length[:, None]
    ends = np.vstack([origin[None], origin + d])
    lo = np.floor(ends.min(axis=0) / voxel_m).astype(np.int64) - 1
    hi = np.floor(ends.max(axis=0) / voxel_m).astype(np.int64) + 1
    shape = hi - lo + 1
    if int(np.prod(shape)) > MAX_GRID_CELLS:
        return None
    grid = np.zeros(tuple(int(s) for s in shape), np.uint8)
    empty = np.zeros(0, np.int64)
    map_keys, fine_m, fine_keys = fine if fine is not None else (empty, 1.0, empty)
    _compiled()(origin, np.ascontiguousarray(u), np.ascontiguousarray(usable, np.float64),
                voxel_m / 2.0, float(voxel_m), lo, grid, fine is not None,
                np.ascontiguousarray(map_keys, np.int64), float(fine_m),
                np.ascontiguousarray(fine_keys, np.int64), hit_fine is not None,
                empty if hit_fine is None else np.ascontiguousarray(hit_fine, np.int64))
    flat = np.flatnonzero(grid.view(np.bool_))  # row-major: i slowest, then j, then k
    i, rest = np.divmod(flat, grid.shape[1] * grid.shape[2])
    j, k = np.divmod(rest, grid.shape[2])
    return np.stack([i + lo[0], j + lo[1], k + lo[2]], axis=1)
