"""A map store + a run's trusted scans -> what changed, per block (``changes.json``).

Steps, a frame at a time (:class:`ChangeDetector`: fed by the tracking loop, or by
:func:`detect_changes` from a finished run): load the blocks the run comes near, voxelizing
their points (the map's occupied voxels and fine cells); for every used trusted frame of the run
(an ``ok`` pose after ``settle_frames`` ``ok`` ones, :mod:`.runs`), check the scan agrees with
the map (the consistency gate below), then add its hits and free rays to the evidence; at the
end keep the scans' new points in cells the mapping day had in sight from its keyframes
(:func:`.detect.seen_by_keyframes`), classify the voxels and report per block. Each scan is
deskewed with the run's poses around it (points moved with
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
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from blockloc.geometry import up_from_gravity
from blockloc.maps.changes.detect import (Evidence, Thresholds, VoxelChanges, block_report, classify,
                                          ground_band, in_sorted, near_sorted, seen_by_keyframes, unique_keys,
                                          voxel_keys, without_lowest)
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


def scan_agreement(points_map: np.ndarray, origin: np.ndarray, up: np.ndarray, map_keys: np.ndarray,
                   voxel_m: float, min_points: int = 50) -> float:
    """Share of a scan's above-ground points (N, 3 map frame; more than 0.5 m above the sensor's
    ground, i.e. ``(p - origin) . up > -0.5``) whose voxel is a map voxel or next to one
    (``map_keys``: the map's sorted voxel keys). All points when fewer than ``min_points`` are above."""
    h = (points_map - origin) @ up
    sel = points_map[h > -0.5]
    if len(sel) < min_points:
        sel = points_map
    if not len(sel):
        return 0.0
    # binary searches in the sorted table, once per distinct voxel (np.isin sorts the whole table
    # again on every call: on the campus's 34 blocks 95 % of the detection's CPU went there), the
    # 26 neighbours only for the voxels not on the map: no dilated table to build as blocks join
    every = voxel_keys(sel, voxel_m)
    keys = unique_keys(every)
    inverse = np.searchsorted(keys, every)
    near = in_sorted(keys, map_keys)
    if not near.all():
        rest = np.flatnonzero(~near)
        near[rest] = near_sorted(keys[rest], map_keys)
    return float(near[inverse].mean())


def _sweep(before, at, after, max_gap_s: float):
    """The poses to deskew the sweep ``at`` with: ``before`` and ``after`` (stamp, T_map_body) or
    None, each kept only within ``max_gap_s`` of ``at`` (a :class:`~blockloc.geometry.Trajectory`)."""
    from blockloc.geometry import Trajectory

    near = [p for p in (before,) if p is not None and at[0] - p[0] <= max_gap_s] + [at]
    near += [p for p in (after,) if p is not None and p[0] - at[0] <= max_gap_s]
    return Trajectory(np.array([p[0] for p in near], float), np.stack([p[1] for p in near]))


def sweep_poses(run: RunPoses, k: int, max_gap_s: float = 0.3):
    """The run's trusted poses around its ``k``-th (a :class:`~blockloc.geometry.Trajectory`)
    to deskew that frame's sweep with: its neighbours within ``max_gap_s`` of it (across a gap in
    the trusted frames the pose is held, never interpolated over the gap)."""
    pose = lambda j: (float(run.stamps[j]), run.T_map_body[j])  # noqa: E731
    return _sweep(pose(k - 1) if k > 0 else None, pose(k), pose(k + 1) if k + 1 < len(run) else None, max_gap_s)


class ChangeDetector:
    """What changed in a block map store, fed a tracking run one frame at a time (what
    :func:`detect_changes` does with a finished run, and ``track --detect-changes`` while tracking).

    ``add(stamp, T_map_body, trusted, frame)`` with every frame of the run in order (``trusted``:
    :class:`.runs.TrustedFrames`, the rule a run folder is read with); every ``stride``-th trusted frame
    is used. A used frame is processed one trusted frame later, when the pose after it is known
    (its sweep is deskewed with the poses on both sides, :func:`sweep_poses`), or as soon as a
    frame comes more than ``max_gap_s`` after it (then no later pose can be its neighbour), or in
    :meth:`result`. So a frame waits one frame period (0.1 s at 10 Hz) in the normal case.

    Blocks are loaded when they are needed, never the whole map: a block joins when a trusted
    pose comes within ``max_range_m`` of one of its keyframes (the blocks the run came near), or
    when a used scan's footprint (its points and origin, 1 m around, in the horizontal plane
    along the map's axes) overlaps the block's bounds (so every map cell a scan's points and rays
    can meet is there when it is judged). The map's voxels, fine cells, carvable cells and
    ground band grow as blocks join. What one scan adds depends only on the map cells in its
    footprint, so the result does not depend on when a block came: fed the same frames and poses,
    it is the after-the-fact result.

    store: a block :class:`~blockloc.maps.store.MapStore` with keyframes. T_body_lidar: (4, 4);
    gravity_map: (3,) m/s^2 in the map frame (the sequence's). The other arguments:
    :func:`detect_changes`. ``costs``: per :meth:`add` call, (wall s, this thread's CPU s,
    scans processed, blocks loaded)."""

    def __init__(self, store, T_body_lidar: np.ndarray, gravity_map, *, voxel_m: float = 0.5,
                 max_range_m: float = 40.0, margin_m: float = 1.0, min_agreement: float = 0.6, stride: int = 1,
                 thresholds: Thresholds = Thresholds(), deskew: bool = True, max_gap_s: float = 0.3) -> None:
        from scipy.spatial import cKDTree

        self.store = store
        self.T_body_lidar = np.asarray(T_body_lidar, float)
        self.up = up_from_gravity(gravity_map)
        self.voxel_m, self.fine_m = float(voxel_m), float(voxel_m) / 2.5
        self.max_range_m, self.margin_m, self.min_agreement = float(max_range_m), float(margin_m), float(min_agreement)
        self.stride, self.thresholds, self.deskew, self.max_gap_s = max(1, int(stride)), thresholds, bool(deskew), max_gap_s
        # every block's keyframes (the manifest's: no points read) and bounds, to see which come in range
        self._ids = list(store.ids)
        kf, owner = [], []
        for i, bid in enumerate(self._ids):
            e = store.entry(bid)
            k = np.asarray(e.keyframes if e.keyframes is not None else e.centroid[None], float).reshape(-1, 3)
            kf.append(k)
            owner += [i] * len(k)
        self._kf_tree = cKDTree(np.concatenate(kf)) if kf else None
        self._kf_owner = np.asarray(owner, np.int64)
        self._lo = np.array([store.entry(b).bounds_min for b in self._ids], float).reshape(-1, 3)
        self._hi = np.array([store.entry(b).bounds_max for b in self._ids], float).reshape(-1, 3)
        self._loaded = np.zeros(len(self._ids), bool)
        self.blocks: dict = {}  # block id -> (N, 3+) its points as the store gives them (float32)
        self.keyframes: dict = {}
        self.block_keys: dict = {}
        self.map_keys = self.fine_keys = np.zeros(0, np.int64)
        self.ev = Evidence(self.voxel_m, self.margin_m, fine=(self.map_keys, self.fine_m, self.fine_keys),
                           carvable=self.fine_keys, ground=self.fine_keys)
        self.frames_trusted = 0
        self.costs: list[tuple[float, float, int, int]] = []
        self._off_pts: list = []
        self._off_int: list = []
        self._prev = None  # (stamp, T_map_body) of the trusted frame before the pending one
        self._pending = None  # (stamp, T_map_body, frame or a callable giving it, trusted index)
        self._last = None  # (stamp, T_map_body) of the last trusted frame
        self.restarts = 0  # times the run's source restarted (:meth:`restart`)
        self.scans_flushed_on_restart = 0  # used scans processed without the pose after them then
        #: (wall s, CPU s) of :meth:`warm_up` (imports, the compiled kernels loaded), or None
        self.startup: tuple[float, float] | None = None

    def warm_up(self) -> None:
        """Import what a scan needs and load (or compile) every compiled kernel, on a made-up
        scan, so the first real scan pays only for itself (else it pays ~0.5-1 s CPU; the node's
        queue and the bench's p99 see it). Nothing of this object's state changes."""
        t0, c0 = time.perf_counter(), time.thread_time()
        from blockloc.geometry import Trajectory
        from blockloc.maps._raycast_kernels import union_sorted
        from blockloc.maps.mapping import scan_to_map
        from blockloc.voxels import voxel_select

        rng = np.random.default_rng(0)
        pts = rng.uniform(-5.0, 5.0, (64, 3))
        pts = pts[voxel_select(pts, self.voxel_m / 2)]
        T = np.eye(4)
        pm = scan_to_map(pts, np.linspace(0.0, 0.1, len(pts)), 1.0, Trajectory(np.array([0.95, 1.05]),
                         np.stack([T, T])), self.T_body_lidar)
        keys = union_sorted(unique_keys(voxel_keys(pm, self.voxel_m)), np.zeros(0, np.int64))
        # a block as the store gives it: float32, x y z and intensity
        fine = unique_keys(voxel_keys(np.c_[pm, np.zeros(len(pm))].astype(np.float32), self.fine_m))
        scan_agreement(pm, np.zeros(3), self.up, keys, self.voxel_m)
        ev = Evidence(self.voxel_m, self.margin_m, fine=(keys, self.fine_m, fine),
                      carvable=without_lowest(fine, self.up), ground=ground_band(fine, self.up, 1))
        ev.add_scan(np.zeros(3), pm, self.up)
        ev.flush()
        ev.add_scan(np.zeros(3), pm, self.up)
        ev.flush()
        self.startup = (time.perf_counter() - t0, time.thread_time() - c0)

    # ------------------------------------------------------------------ blocks
    def _load(self, which: np.ndarray) -> int:
        """Load the blocks of the indices ``which`` not loaded yet; the map's sets grow."""
        new = [int(i) for i in np.unique(which) if not self._loaded[i]]
        if not new:
            return 0
        from blockloc.maps._raycast_kernels import union_sorted

        for i in new:
            self._loaded[i] = True
            bid = self._ids[i]
            e = self.store.entry(bid)
            # kept as the store gives them (float32, its columns): voxel_keys widens them exactly,
            # and result() hands block_report the float64 points (no 2x copy on the joining frame)
            pts = self.store.load(bid)[0]
            self.blocks[bid] = pts
            self.keyframes[bid] = np.asarray(e.keyframes if e.keyframes is not None else e.centroid[None], float)
            self.block_keys[bid] = unique_keys(voxel_keys(pts, self.voxel_m))
            # the map's sets: sorted unions, merged linearly (no sort of the whole map's keys)
            self.map_keys = union_sorted(self.map_keys, self.block_keys[bid])
            self.fine_keys = union_sorted(self.fine_keys, unique_keys(voxel_keys(pts, self.fine_m)))
        # new points are judged against every map cell; free space may cross all but the ground's
        # (the lowest cell of a column can change when a block joins: recomputed over all)
        self.ev.fine = (self.map_keys, self.fine_m, self.fine_keys)
        self.ev.carvable = without_lowest(self.fine_keys, self.up)
        self.ev.ground = ground_band(self.fine_keys, self.up, self.thresholds.ground_band_cells)
        return len(new)

    def _near_pose(self, position: np.ndarray) -> np.ndarray:
        if self._kf_tree is None:
            return np.zeros(0, np.int64)
        return self._kf_owner[self._kf_tree.query_ball_point(position, self.max_range_m)]

    def _under(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Indices of the blocks whose bounds overlap the box lo..hi (3,) in the horizontal plane
        (every axis but the one along gravity: a column's lowest cell may lie far below a scan)."""
        axes = [a for a in range(3) if a != int(np.argmax(np.abs(self.up)))]
        ok = np.all((self._lo[:, axes] <= hi[axes]) & (self._hi[:, axes] >= lo[axes]), axis=1)
        return np.flatnonzero(ok)

    # ------------------------------------------------------------------ frames
    def add(self, stamp: float, T_map_body: np.ndarray | None, trusted: bool, frame=None) -> int:
        """One frame of the run, in order. T_map_body: (4, 4) or None (not localized); trusted:
        the frame passes :class:`.runs.TrustedFrames`; frame: its ``LidarFrame`` (lidar frame points,
        per-point times), or a callable returning it (read only when the frame is used), or None
        for a frame that is not trusted. Returns the number of scans processed by this call."""
        t0, c0 = time.perf_counter(), time.thread_time()
        stamp = float(stamp)
        done = loaded = 0
        if trusted and self._last is not None and stamp <= self._last[0]:
            # stamps went back with no restart said (:meth:`restart`): the same, or the sweeps of
            # the two streams would be deskewed with each other's poses
            done, loaded = self._restart()
        if self._pending is not None and (trusted or stamp - self._pending[0] > self.max_gap_s):
            after = (stamp, np.asarray(T_map_body, float)) if trusted else None
            loaded += self._process(after)
            done += 1
        if trusted:
            T = np.asarray(T_map_body, float)
            loaded += self._load(self._near_pose(T[:3, 3]))
            if self.frames_trusted % self.stride == 0:
                if frame is None:
                    raise ValueError("a used trusted frame needs its frame")
                self._prev = self._last
                self._pending = (stamp, T, frame)
            self._last = (stamp, T)
            self.frames_trusted += 1
        self.costs.append((time.perf_counter() - t0, time.thread_time() - c0, done, loaded))
        return done

    def restart(self) -> int:
        """The run's source restarted (a live stream whose stamps jumped back): no pose before
        the restart is a neighbour of a scan after it, nor the other way round. The used scan
        waiting for the pose after it is processed now, deskewed with the poses it has (as across
        a gap of more than ``max_gap_s``; counted in ``scans_flushed_on_restart``), and the poses
        held are let go. Returns the number of scans processed (0 or 1)."""
        t0, c0 = time.perf_counter(), time.thread_time()
        done, loaded = self._restart()
        self.costs.append((time.perf_counter() - t0, time.thread_time() - c0, done, loaded))
        return done

    def _restart(self) -> tuple[int, int]:
        done = loaded = 0
        if self._pending is not None:
            loaded = self._process(None)
            done = 1
            self.scans_flushed_on_restart += 1
        self._prev = self._last = None
        self.restarts += 1
        return done, loaded

    def _process(self, after) -> int:
        """Use the pending frame (``after``: the next trusted pose or None). Returns blocks loaded."""
        from blockloc.maps.mapping import scan_to_map
        from blockloc.voxels import voxel_select

        stamp, T_map_body, frame = self._pending
        self._pending = None
        if callable(frame):
            frame = frame()
        T_map_lidar = T_map_body @ self.T_body_lidar
        pts = np.asarray(frame.points, float)[:, :3]
        inten = (np.asarray(frame.intensity, np.float32) if frame.intensity is not None
                 else np.zeros(len(pts), np.float32))
        times = frame.time_offsets
        r = np.linalg.norm(pts, axis=1)
        near = np.isfinite(r) & (r <= self.max_range_m)
        pts, inten = pts[near], inten[near]
        sel = voxel_select(pts, self.voxel_m / 2)
        pts, inten = pts[sel], inten[sel]
        # the previous trusted frame is the neighbour before only when it is the frame just before
        # this one among the trusted (with a stride it is, as the run's list of trusted frames has it)
        before = self._prev
        if self.deskew and times is not None:
            pm = scan_to_map(pts, np.asarray(times, np.float64)[near][sel], float(frame.stamp),
                             _sweep(before, (stamp, T_map_body), after, self.max_gap_s), self.T_body_lidar)
        else:
            pm = pts @ T_map_lidar[:3, :3].T + T_map_lidar[:3, 3]
        origin = T_map_lidar[:3, 3]
        box = np.vstack([pm, origin[None]]) if len(pm) else origin[None]
        loaded = self._load(self._under(box.min(axis=0) - 1.0, box.max(axis=0) + 1.0))
        if scan_agreement(pm, origin, self.up, self.map_keys, self.voxel_m) < self.min_agreement:
            self.ev.rejected += 1
        else:
            off = self.ev.add_scan(origin, pm, self.up)  # the new points: off the map's fine cells
            self._off_pts.append(pm[off].astype(np.float32))
            self._off_int.append(inten[off])
        return loaded

    @property
    def scans(self) -> int:
        """Scans processed so far (used + rejected by the consistency gate)."""
        return self.ev.scans + self.ev.rejected

    def result(self, **notes) -> ChangeResult:
        """What changed by the frames added so far (the pending frame processed first, with the
        poses it has). notes: extra entries of ``params`` (e.g. that the run was interrupted)."""
        if self._pending is not None:
            self._process(None)
        ev, th = self.ev, self.thresholds
        ev.flush()
        # the cells of the scans' new points the mapping day had in clear sight from its keyframes:
        # added structure stands where the mapping day saw free space, not merely where it never looked
        # in the store's order, whatever order the blocks came in (the nearest keyframe's ties)
        order = [b for b in self._ids if b in self.blocks]
        block_keys = {b: self.block_keys[b] for b in order}
        keyframes = {b: self.keyframes[b] for b in order}
        cells = ev.new_cells()
        if self.blocks and len(cells):
            # in sight up to two fine cells short of the cell (a new point has no map cell within one):
            # a wall that hid the ground right behind it hides it (a metre's margin would look past it)
            map_free = seen_by_keyframes(cells, self.fine_m, np.concatenate(list(keyframes.values())),
                                         self.fine_keys, 2 * self.fine_m, self.max_range_m, k=th.seen_keyframes,
                                         sectors=th.seen_sectors, pool=th.seen_pool, up=self.up)
        else:
            map_free = np.zeros(0, np.int64)
        vc = classify(ev, self.map_keys, map_free, th)
        report = block_report(vc, block_keys, keyframes,
                              {b: np.asarray(self.blocks[b][:, :3], np.float64) for b in order}, th)
        restarts = ({"source_restarts": self.restarts, "scans_flushed_on_restart": self.scans_flushed_on_restart}
                    if self.restarts else {})
        params = {"voxel_m": self.voxel_m, "max_range_m": self.max_range_m, "margin_m": self.margin_m,
                  "min_agreement": self.min_agreement, "stride": self.stride, "deskew": self.deskew,
                  **vars(th), **restarts, **notes}
        log.info("changes: %d trusted frames, %d scans used, %d rejected by the consistency gate",
                 self.frames_trusted, ev.scans, ev.rejected)
        return ChangeResult(report, vc, self.frames_trusted, ev.scans, ev.rejected, params, block_keys, keyframes,
                            np.concatenate(self._off_pts) if self._off_pts else np.zeros((0, 3), np.float32),
                            np.concatenate(self._off_int) if self._off_int else np.zeros(0, np.float32))


def detect_changes(store, sequence, run: RunPoses, *, voxel_m: float = 0.5, max_range_m: float = 40.0,
                   margin_m: float = 1.0, min_agreement: float = 0.6, stride: int = 1,
                   thresholds: Thresholds = Thresholds(), deskew: bool = True,
                   progress: Callable[[int, int], None] | None = None) -> ChangeResult:
    """Detect what changed in ``store`` (a block :class:`~blockloc.maps.store.MapStore` with
    keyframes) from ``run``'s trusted frames of ``sequence`` (a ``Sequence`` whose frame indices
    are the run's). stride: use every stride-th trusted frame. deskew: move each point with the
    run's pose at its own time (:func:`sweep_poses`) when the frames carry per-point times.
    progress: (done, total) scans. A loop of :class:`ChangeDetector` over the run's trusted
    frames (only the used ones are read)."""
    info = sequence.info
    det = ChangeDetector(store, info.T_body_lidar, getattr(info, "gravity_map", (0.0, 0.0, -9.81)),
                         voxel_m=voxel_m, max_range_m=max_range_m, margin_m=margin_m,
                         min_agreement=min_agreement, stride=stride, thresholds=thresholds, deskew=deskew)
    total = len(range(0, len(run), det.stride))
    for k in range(len(run)):
        index = int(run.index[k])
        if det.add(run.stamps[k], run.T_map_body[k], True, lambda i=index: sequence.frame(i)) and progress:
            progress(det.scans, total)
    res = det.result()
    if progress is not None and total:
        progress(total, total)
    return res
