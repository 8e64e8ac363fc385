"""Leave moving objects out of a map built from one drive: per-voxel scan evidence.

The change detector's evidence (:class:`blockloc.maps.changes.detect.Evidence`), here without a
prior map: every voxel (edge ``voxel_m``) counts the scans with a point in it (``n_hit``) and the
scans whose rays passed through it (``n_free``; a ray marks free space only up to ``margin_m``
short of its endpoint, never next to one of that scan's hits, and rays ending on the ground
stop further short the flatter they run). A voxel is **dynamic** when rays passed through it in
``min_free`` scans or more and the free evidence outweighs the hits (log-odds
``n_hit * l_occ + n_free * l_free < 0``): a pedestrian or a car passing, seen through once it
has gone. Points in dynamic voxels are left out of the map; everything else is kept. One scan
never decides, and a voxel hit as often as it is seen through (foliage that stops some rays and
lets others pass) stays: the free evidence must outweigh the hits.

Pure numpy on arrays in one world frame (metres).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from blockloc.maps.changes.detect import Evidence, in_sorted, voxel_keys


@dataclass(frozen=True)
class DynamicParams:
    """voxel_m: evidence voxel edge (m). margin_m: free space stops this short of a ray's endpoint
    (m). ray_voxel_m: a scan's endpoints are thinned to one per cell of this edge before rays are
    walked (None: voxel_m / 2). l_occ / l_free: log-odds per scan hit / seen free. min_free: scans
    that saw through a voxel before it can be dynamic. grow_rounds, grow_ratio: rounds of growing the
    dynamic voxels into the voxels above and below them hit in no more than ``grow_ratio`` times as
    many scans (see :func:`dynamic_voxels`)."""

    voxel_m: float = 0.4
    margin_m: float = 0.5
    ray_voxel_m: float | None = None
    l_occ: float = 0.85
    l_free: float = -0.4
    min_free: int = 2
    grow_rounds: int = 2
    grow_ratio: float = 2.0


def scan_evidence(scans: Iterable[tuple[np.ndarray, np.ndarray]], params: DynamicParams = DynamicParams(),
                  up: np.ndarray | None = None, progress: Callable[[int, int], None] | None = None,
                  total: int = 0) -> Evidence:
    """Evidence over ``scans``: (origin (3,), points (N, 3)) in the world frame, metres. up: (3,)
    unit vector against gravity (None: no ground-ray margin). progress: (done, total)."""
    from blockloc.voxels import voxel_select

    ev = Evidence(params.voxel_m, params.margin_m)
    ray_voxel = params.ray_voxel_m or params.voxel_m / 2
    for done, (origin, pts) in enumerate(scans, 1):
        pts = np.asarray(pts, np.float64)
        ev.add_scan(np.asarray(origin, np.float64), pts[voxel_select(pts, ray_voxel)], up)
        if progress is not None:
            progress(done, total)
    ev.flush()
    return ev


def dynamic_voxels(ev: Evidence, params: DynamicParams = DynamicParams(), up: np.ndarray | None = None) -> np.ndarray:
    """Sorted int64 keys of the dynamic voxels (module docstring), then grown vertically.

    Free space is never marked next to a scan's hits, so the voxels of a walker or a car just
    above the ground (neighbours of ground hits) never collect free evidence. Each growing round
    makes a hit voxel directly above or below a dynamic one dynamic too when it was hit in no more
    than ``grow_ratio`` times the scans that neighbour was: the walker's lower voxels were hit only
    while it stood there, the ground under it in every scan that looked (it stays). Growing only
    along the vertical (the voxel axis nearest ``up``; z when None) keeps walls and foliage beside
    a passing car. (On the small world's busiest stretch, growing into all 26 neighbours cost 1 to
    10 points of SA for the same DA: docs/dynamic_points.md.)"""
    from blockloc.maps.changes.detect import pack_keys, unpack_keys

    L = ev.logodds(params.l_occ, params.l_free)
    dyn = (ev.n_free >= params.min_free) & (ev.n_hit >= 1) & (L < 0)
    axis = 2 if up is None else int(np.argmax(np.abs(np.asarray(up, float).reshape(3))))
    steps = np.zeros((2, 3), np.int64)
    steps[0, axis], steps[1, axis] = 1, -1
    hit = np.flatnonzero(ev.n_hit >= 1)
    for _ in range(params.grow_rounds):
        cand = hit[~dyn[hit]]
        if not len(cand) or not dyn.any():
            break
        ijk = unpack_keys(ev.keys[cand])
        best = np.zeros(len(cand), np.int64)  # most hits of a dynamic vertical neighbour (0: none)
        for off in steps:
            nb = pack_keys(ijk + off)
            j = np.minimum(np.searchsorted(ev.keys, nb), len(ev.keys) - 1)
            ok = (ev.keys[j] == nb) & dyn[j]
            best = np.where(ok, np.maximum(best, ev.n_hit[j]), best)
        grow = (best > 0) & (ev.n_hit[cand] <= params.grow_ratio * best)
        if not grow.any():
            break
        dyn[cand[grow]] = True
    return ev.keys[dyn]


def static_mask(points: np.ndarray, dynamic_keys: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N,) bool: points (N, 3) outside every dynamic voxel (sorted keys of edge ``voxel_m``)."""
    return ~in_sorted(voxel_keys(points, voxel_m), dynamic_keys)


def static_masks(evidence: list[tuple[np.ndarray, np.ndarray]], own: Iterable[int],
                 params: DynamicParams = DynamicParams(), up: np.ndarray | None = None) -> list[np.ndarray]:
    """(N_i,) bool keep-masks of the scans ``evidence[i]`` for i in ``own``: the evidence of every
    scan in ``evidence`` ((origin (3,), points (N, 3)), world frame, m), points in its dynamic
    voxels left out. How ``map build --remove-dynamic`` filters a task's keyframes, with the
    keyframes around them as ``evidence`` too."""
    ev = scan_evidence(evidence, params, up=up)
    keys = dynamic_voxels(ev, params, up)
    return [static_mask(evidence[i][1], keys, params.voxel_m) for i in own]
