"""A map store + a run's trusted scans -> what changed, per block (``changes.json``).

Steps: pick the blocks the run came near; voxelize their points (the map's occupied voxels and
fine cells); for every trusted frame of the run (a
``ok`` pose after ``settle_frames`` ``ok`` ones, :mod:`.runs`), check the scan agrees with the
map (the consistency gate below), then add its hits and free rays to the evidence; keep the
scans' new points in cells the mapping day had in sight from its keyframes
(:func:`.detect.seen_by_keyframes`); classify the voxels; report per block. Each scan is deskewed with the run's poses around it (points moved with
the pose at their own time, :func:`sweep_poses`): a sweep taken while turning is otherwise smeared
sideways by up to ``yaw rate x 0.1 s x range`` (0.1 rad/s: 0.4 m at 40 m), and its rays cut past
the edges of the structure they hit.

Consistency gate: a pose can be marked ok and still be wrong (a bad registration the tracker
accepted). Such a scan would carve walls out of the map and add them elsewhere. Each scan's
points more than ``0.5 m`` above the ground around the sensor (along the map's up direction,
from the sequence's gravity) must fall in (or next to) a map voxel for at least
``min_agreement`` of them; a scan below is dropped, and counted. The ground is left out of the
test because a flat ground agrees with any horizontally shifted pose.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from blockloc.geometry import up_from_gravity
from blockloc.maps.changes.detect import (Evidence, Thresholds, VoxelChanges, block_report, classify,
                                          dilate_keys, ground_band, in_sorted, seen_by_keyframes, voxel_keys,
                                          without_lowest)
from blockloc.maps.changes.runs import RunPoses

log = logging.getLogger(__name__)


@dataclass
class ChangeResult:
    """What :func:`detect_changes` found. blocks: one dict per examined block
    (:func:`.detect.block_report`); voxels: the classified voxels; counts of frames."""

    blocks: list[dict]
    voxels: VoxelChanges
    frames_trusted: int
    scans_used: int
    scans_rejected: int
    params: dict = field(default_factory=dict)
    #: the examined blocks' occupied voxels (sorted keys) and keyframes (K, 3), by block id
    block_keys: dict = field(default_factory=dict)
    block_keyframes: dict = field(default_factory=dict)
    #: (P, 3) float32 map-frame points of the used scans off the map's voxels (and their
    #: neighbours), (P,) float32 intensity: what an update adds from (added voxels only)
    offmap_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    offmap_intensity: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))

    def to_json(self, **facts) -> dict:
        """The ``changes.json`` document."""
        return {"format": "blockloc-changes", "version": 1, **facts, "params": self.params,
                "frames_trusted": self.frames_trusted, "scans_used": self.scans_used,
                "scans_rejected": self.scans_rejected,
                "totals": {f"{k}_voxels": int(len(getattr(self.voxels, k)))  # distinct voxels (blocks overlap)
                           for k in ("removed", "added", "dynamic")},
                "blocks": self.blocks}


def scan_agreement(points_map: np.ndarray, origin: np.ndarray, up: np.ndarray, map_near: np.ndarray,
                   voxel_m: float, min_points: int = 50) -> float:
    """Share of a scan's above-ground points (N, 3 map frame; more than 0.5 m above the sensor's
    ground, i.e. ``(p - origin) . up > -0.5``) whose voxel is in ``map_near`` (sorted keys: the
    map's voxels and their neighbours). All points when fewer than ``min_points`` are above."""
    h = (points_map - origin) @ up
    sel = points_map[h > -0.5]
    if len(sel) < min_points:
        sel = points_map
    if not len(sel):
        return 0.0
    # a binary search in the sorted table: np.isin sorts the whole table again on every call (the
    # campus's 34 blocks, dilated: 95 % of the detection's CPU went there)
    return float(in_sorted(voxel_keys(sel, voxel_m), map_near).mean())


def sweep_poses(run: RunPoses, k: int, max_gap_s: float = 0.3):
    """The run's trusted poses around its ``k``-th (a :class:`~blockloc.geometry.Trajectory`)
    to deskew that frame's sweep with: its neighbours within ``max_gap_s`` of it (across a gap in
    the trusted frames the pose is held, never interpolated over the gap)."""
    from blockloc.geometry import Trajectory

    lo, hi = k, k + 1
    if k > 0 and run.stamps[k] - run.stamps[k - 1] <= max_gap_s:
        lo = k - 1
    if k + 1 < len(run) and run.stamps[k + 1] - run.stamps[k] <= max_gap_s:
        hi = k + 2
    return Trajectory(run.stamps[lo:hi], run.T_map_body[lo:hi])


def detect_changes(store, sequence, run: RunPoses, *, voxel_m: float = 0.5, max_range_m: float = 40.0,
                   margin_m: float = 1.0, min_agreement: float = 0.6, stride: int = 1,
                   thresholds: Thresholds = Thresholds(), deskew: bool = True,
                   progress: Callable[[int, int], None] | None = None) -> ChangeResult:
    """Detect what changed in ``store`` (a block :class:`~blockloc.maps.store.MapStore` with
    keyframes) from ``run``'s trusted frames of ``sequence`` (a ``Sequence`` whose frame indices
    are the run's). stride: use every stride-th trusted frame. deskew: move each point with the
    run's pose at its own time (:func:`sweep_poses`) when the frames carry per-point times.
    progress: (done, total) scans."""
    from blockloc.maps.mapping import scan_to_map
    from blockloc.voxels import voxel_select

    info = sequence.info
    T_body_lidar = np.asarray(info.T_body_lidar, float)
    up = up_from_gravity(getattr(info, "gravity_map", (0.0, 0.0, -9.81)))
    # the blocks the run came near
    pos = run.T_map_body[:, :3, 3] if len(run) else np.zeros((0, 3))
    blocks, keyframes = {}, {}
    from scipy.spatial import cKDTree

    tree = cKDTree(pos) if len(pos) else None
    for bid in store.ids:
        e = store.entry(bid)
        kf = e.keyframes if e.keyframes is not None else e.centroid[None]
        if tree is None or not np.isfinite(tree.query(kf, distance_upper_bound=max_range_m)[0]).any():
            continue
        blocks[bid] = store.load(bid)[0][:, :3].astype(np.float64)
        keyframes[bid] = np.asarray(kf, float)
    block_keys = {b: np.unique(voxel_keys(p, voxel_m)) for b, p in blocks.items()}
    map_keys = np.unique(np.concatenate(list(block_keys.values()))) if blocks else np.zeros(0, np.int64)
    map_near = dilate_keys(map_keys) if len(map_keys) else map_keys
    fine_m = voxel_m / 2.5
    fine_keys = (np.unique(np.concatenate([voxel_keys(p, fine_m) for p in blocks.values()]))
                 if blocks else np.zeros(0, np.int64))
    # new points are judged against every map cell; free space may cross all but the ground's
    ev = Evidence(voxel_m, margin_m, fine=(map_keys, fine_m, fine_keys),
                  carvable=without_lowest(fine_keys, up),
                  ground=ground_band(fine_keys, up, thresholds.ground_band_cells))
    off_pts, off_int = [], []
    idx = np.arange(0, len(run), max(1, int(stride)))
    for done, k in enumerate(idx, 1):
        frame = sequence.frame(int(run.index[k]))
        T_map_lidar = run.T_map_body[k] @ T_body_lidar
        pts = np.asarray(frame.points, float)[:, :3]
        inten = (np.asarray(frame.intensity, np.float32) if frame.intensity is not None
                 else np.zeros(len(pts), np.float32))
        times = frame.time_offsets
        r = np.linalg.norm(pts, axis=1)
        near = np.isfinite(r) & (r <= max_range_m)
        pts, inten = pts[near], inten[near]
        sel = voxel_select(pts, voxel_m / 2)
        pts, inten = pts[sel], inten[sel]
        if deskew and times is not None:
            pm = scan_to_map(pts, np.asarray(times, np.float64)[near][sel], float(frame.stamp),
                             sweep_poses(run, k), T_body_lidar)
        else:
            pm = pts @ T_map_lidar[:3, :3].T + T_map_lidar[:3, 3]
        origin = T_map_lidar[:3, 3]
        if scan_agreement(pm, origin, up, map_near, voxel_m) < min_agreement:
            ev.rejected += 1
        else:
            off = ev.add_scan(origin, pm, up)  # the new points: off the map's fine cells
            off_pts.append(pm[off].astype(np.float32))
            off_int.append(inten[off])
        if progress is not None:
            progress(done, len(idx))
    ev.flush()
    # the cells of the scans' new points the mapping day had in clear sight from its keyframes:
    # added structure stands where the mapping day saw free space, not merely where it never looked
    cells = ev.new_cells()
    if blocks and len(cells):
        # in sight up to two fine cells short of the cell (a new point has no map cell within one):
        # a wall that hid the ground right behind it hides it (a metre's margin would look past it)
        map_free = seen_by_keyframes(cells, fine_m, np.concatenate(list(keyframes.values())), fine_keys,
                                     2 * fine_m, max_range_m, k=thresholds.seen_keyframes)
    else:
        map_free = np.zeros(0, np.int64)
    vc = classify(ev, map_keys, map_free, thresholds)
    report = block_report(vc, block_keys, keyframes, blocks, thresholds)
    params = {"voxel_m": voxel_m, "max_range_m": max_range_m, "margin_m": margin_m,
              "min_agreement": min_agreement, "stride": int(stride), "deskew": bool(deskew), **vars(thresholds)}
    log.info("changes: %d trusted frames, %d scans used, %d rejected by the consistency gate",
             len(run), ev.scans, ev.rejected)
    return ChangeResult(report, vc, len(run), ev.scans, ev.rejected, params, block_keys, keyframes,
                        np.concatenate(off_pts) if off_pts else np.zeros((0, 3), np.float32),
                        np.concatenate(off_int) if off_int else np.zeros(0, np.float32))
