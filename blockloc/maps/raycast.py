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


def unit_rays(origin: np.ndarray, endpoints: np.ndarray, margin_m) -> tuple:
    """The rays that mark free space: (origin (3,), d (R, 3) origin -> endpoint, u (R, 3) unit
    directions, usable (R,) metres each marks, its length less ``margin_m``), rays no longer than
    their margin left out. Metres, one frame."""
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(endpoints, dtype=np.float64)[:, :3] - origin
    length = np.linalg.norm(d, axis=1)
    usable = length - margin_m
    keep = usable > 0
    d, length, usable = d[keep], length[keep], usable[keep]
    return origin, d, d / length[:, None], usable


def free_voxels(origin: np.ndarray, endpoints: np.ndarray, voxel_m: float, margin_m,
                fine: tuple | None = None, hit_fine: np.ndarray | None = None) -> np.ndarray | None:
    """(M, 3) int64 indices (``floor(p / voxel_m)``), in row-major order, of the voxels the rays
    ``origin`` (3,) -> each of ``endpoints`` (N, 3) pass through, up to ``margin_m`` (a number or
    (N,) per ray) short of the endpoint; ``fine`` and ``hit_fine`` as
    :func:`~blockloc.maps.changes.detect.ray_free_keys` takes them (keys packed as its
    ``pack_keys`` packs them). None when the scan's bounding box would need more than
    :data:`MAX_GRID_CELLS` cells."""
    origin, d, u, usable = unit_rays(origin, endpoints, margin_m)
    if not len(d):
        return np.zeros((0, 3), dtype=np.int64)
    ends = np.vstack([origin[None], origin + d])
    lo = np.floor(ends.min(axis=0) / voxel_m).astype(np.int64) - 1
    hi = np.floor(ends.max(axis=0) / voxel_m).astype(np.int64) + 1
    shape = hi - lo + 1
    if int(np.prod(shape)) > MAX_GRID_CELLS:
        return None
    grid = np.zeros(tuple(int(s) for s in shape), np.uint8)
    empty = np.zeros(0, np.int64)
    map_keys, fine_m, fine_keys = fine if fine is not None else (empty, 1.0, empty)
    from blockloc.maps._raycast_kernels import mark_free

    mark_free(origin, np.ascontiguousarray(u), np.ascontiguousarray(usable, np.float64),
                voxel_m / 2.0, float(voxel_m), lo, grid, fine is not None,
                np.ascontiguousarray(map_keys, np.int64), float(fine_m),
                np.ascontiguousarray(fine_keys, np.int64), hit_fine is not None,
                empty if hit_fine is None else np.ascontiguousarray(hit_fine, np.int64))
    flat = np.flatnonzero(grid.view(np.bool_))  # row-major: i slowest, then j, then k
    i, rest = np.divmod(flat, grid.shape[1] * grid.shape[2])
    j, k = np.divmod(rest, grid.shape[2])
    return np.stack([i + lo[0], j + lo[1], k + lo[2]], axis=1)
