"""What a detection found, as voxel centres per block: the data the recording's changes layer and
the report's changes section draw (:mod:`blockloc.viz.changes_view`).

A voxel belongs to a block as :func:`.detect.block_report` counts it: a removed voxel to every
block whose occupied voxels hold it (blocks overlap, so one voxel may be in two), an added or
dynamic voxel to the block of the nearest keyframe. The per-block counts here therefore equal
``changes.json``'s ``removed_voxels``, ``added_voxels`` and ``dynamic_voxels``.
"""

from __future__ import annotations

import numpy as np

from blockloc.maps.changes.detect import unpack_keys

#: The classes drawn, in the order they are listed.
CLASSES = ("removed", "added", "dynamic")


def voxel_centres(keys: np.ndarray, voxel_m: float) -> np.ndarray:
    """(K,) int64 voxel keys -> (K, 3) float64 voxel centres, map frame, metres."""
    return (unpack_keys(keys).astype(np.float64) + 0.5) * voxel_m


def block_voxels(result) -> dict[str, dict[str, np.ndarray]]:
    """block id -> class (:data:`CLASSES`) -> (K, 3) float64 voxel centres (map frame, m) of a
    :class:`~blockloc.maps.changes.pipeline.ChangeResult`, for every examined block (empty
    arrays where a block has none of a class)."""
    from scipy.spatial import cKDTree

    vc = result.voxels
    ids = list(result.block_keys)
    kf = [np.asarray(result.block_keyframes.get(b, np.zeros((0, 3))), float).reshape(-1, 3) for b in ids]
    owner = np.concatenate([np.full(len(k), i) for i, k in enumerate(kf)]) if ids else np.zeros(0, int)
    kf_all = np.concatenate(kf) if ids else np.zeros((0, 3))
    tree = cKDTree(kf_all) if len(kf_all) else None

    def nearest(keys: np.ndarray) -> np.ndarray:
        if tree is None or not len(keys):
            return np.full(len(keys), -1)
        return owner[tree.query(voxel_centres(keys, vc.voxel_m))[1]]

    add_owner, dyn_owner = nearest(vc.added), nearest(vc.dynamic)
    out: dict[str, dict[str, np.ndarray]] = {}
    for i, b in enumerate(ids):
        rm = vc.removed[np.isin(vc.removed, result.block_keys[b])]
        out[b] = {"removed": voxel_centres(rm, vc.voxel_m),
                  "added": voxel_centres(vc.added[add_owner == i], vc.voxel_m),
                  "dynamic": voxel_centres(vc.dynamic[dyn_owner == i], vc.voxel_m)}
    return out
