"""A tracking session: one sequence, one map, one tracker, stepped frame by frame.

:func:`blockloc.app.assemble.build_session` assembles the parts from a config (registration
engine, map policy and provider, global localizer, tracker); then either

    session.run(init="gt")                      # initialize -> every frame -> finish

or, driven from outside (the benchmarks step several sessions in lockstep):

    session.initialize("gt", first_frame)
    for frame in seq.frames():
        session.step(frame)                     # IMU fed up to the sweep's end, then the scan
    result = session.finish()

Initialization: ``gt`` (the first ground-truth pose), ``pose`` (global init around an x, y[, yaw]
hint) or ``global`` (global init over the whole map on the first frames, until one is verified:
the map's place index, see :mod:`blockloc.global_init.place_index`). A tracker that is lost
relocalizes around its last good pose, then over the whole map (:mod:`blockloc.app.recovery`);
only verified poses restart it, and the frames in between are reported lost, never ok. A scan
that fits several places (ambiguous) leaves its hypotheses to the next scan of either path, which
is registered to it and tests them (``init['second_scan']``, ``relocalizations[i]['second_scan']``).
Every path prepares its scan with :func:`blockloc.global_init.scan_prep.prepare_for_init`, as
``blockloc init`` does.

A run survives bad frames: a scan that cannot be read is skipped (``skipped_frames``), a map
entry that cannot be loaded is treated as unmapped (``map_faults``), IMU and LiDAR gaps are
logged and counted (``imu_gaps``, ``lidar_gaps``: :mod:`blockloc.app.stream_checks`), as are the
points a loader dropped for NaN/inf coordinates (``nonfinite_points``); ``run(should_stop=...)``
stops between frames (Ctrl-C), and ``finish`` always hands the observers what was computed
(``interrupted`` in the metrics). A results file that cannot be written (disk full, its folder
removed: :class:`~blockloc.errors.OutputWriteError`) stops the run; ``run`` raises it after
``finish`` wrote what it could (``output_error``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator, Optional, Sequence

import numpy as np

from blockloc.app.recovery import GlobalInitSettings, Recovery
from blockloc.app.stream_checks import StreamChecks
from blockloc.datasets.base import ImuData
from blockloc.errors import BlocklocError, OutputWriteError, TrackingError
from blockloc.evaluation.results import run_metrics
from blockloc.geometry import Trajectory
from blockloc.maps.summary import entry_footprint
from blockloc.tracking.tracker import Diagnostics, Estimate
from blockloc.viz.events import FrameEvent, ObserverGroup, RunInfo

log = logging.getLogger(__name__)

INIT_MODES = ("gt", "pose", "global")


@dataclass
class RunResult:
    """What a session produced: the estimate (T_map_body), per-frame diagnostics, metrics, the
    results folder (or None) and, when kept, the tracker's Estimate objects."""

    trajectory: Trajectory
    diagnostics: list[dict]
    metrics: dict
    out_dir: object | None
    estimates: list = field(default_factory=list, repr=False)


def iter_frames(seq, start: int, stop: int) -> Iterator[tuple[int, object]]:
    """(index, LidarFrame) for frames start..stop-1, or (index, exception) for a frame that could
    not be read; reading resumes after it (any loader whose ``frames`` yields in order)."""
    i = start
    while i < stop:
        try:
            for frame in seq.frames(i, stop):
                yield i, frame
                i += 1
            return
        except BlocklocError as exc:
            yield i, exc
            i += 1


class Session:
    """Track one sequence in one map (see the module docstring).

    seq: a ``Sequence``. tracker: a ``Tracker`` whose relocalizer may be this session's
    :meth:`relocalize`. provider: the map provider the tracker reads (``stats``, ``current``,
    ``close``). localizer: a ``GlobalLocalizer`` or None (no global init, no recovery).
    observers: run observers (results writer, recorders, live views). facts: fixed entries of the
    metrics (sequence, map, backend, ...). config: the config used (plain dict, for observers).
    evaluation: keywords of the accuracy evaluation (align, max_time_diff_s, rpe_deltas_m);
    plots: write its plots into ``out_dir``.
    """

    def __init__(self, seq, tracker, provider, *, localizer=None, store=None,
                 init_settings: GlobalInitSettings = GlobalInitSettings(), observers: Sequence = (),
                 evaluation: dict | None = None, plots: bool = True, facts: dict | None = None,
                 config: dict | None = None, out_dir=None, keep_estimates: bool = False) -> None:
        self.seq = seq
        self.info = seq.info
        self.tracker = tracker
        self.provider = provider
        self.store = store
        self.observers = ObserverGroup(observers)  # a failing viewer is dropped, never stops tracking
        self.output_error: OutputWriteError | None = None  # the results folder could not be finished
        self.evaluation = evaluation or {}
        self.plots = plots
        self.facts = dict(facts or {})
        self.config = config or {}
        self.out_dir = out_dir
        self.keep_estimates = keep_estimates
        self.imu = seq.imu()
        self.ground_truth = seq.ground_truth()
        self.stamps = np.asarray(seq.frame_stamps(), dtype=np.float64)
        self._imu_next = 0
        self._mode = "gt"
        self._started = False
        self._reinitialized = False  # a verified reinitialize: the next step says "recovered"
        self._finished: RunResult | None = None
        self._last_map_version = None
        self.init_info: dict = {}
        self.diagnostics: list[dict] = []
        self.estimates: list = []
        self._poses: list[np.ndarray] = []
        self._pose_stamps: list[float] = []
        self.counters = {"skipped_frames": 0, "map_faults": 0, "imu_gaps": 0, "lidar_gaps": 0,
                         "nonfinite_points": 0}
        self.recovery = Recovery(localizer, init_settings, self.info, self.imu, self.ground_truth, self.counters)
        self.reloc_log = self.recovery.log  # every relocalization attempt (also in the metrics)
        self.stream = StreamChecks(self.info, self.counters)
        self.timings: dict[str, float] = {}
        self._t_start = time.perf_counter()

    @property
    def localizer(self):
        """The GlobalLocalizer (or None) global init and relocalization use."""
        return self.recovery.localizer

    @property
    def init_settings(self) -> GlobalInitSettings:
        """The search windows of global init."""
        return self.recovery.settings

    # ----------------------------------------------------------------- initialization
    def initialize(self, mode: str, first: int = 0, pose_hint: tuple | None = None) -> dict:
        """Start the tracker for frame ``first``. mode: gt | pose (``pose_hint`` = (x, y, yaw or
        None), map frame, m and rad) | global. Returns what init found (also in the metrics)."""
        if mode not in INIT_MODES:
            raise TrackingError(f"init {mode!r}: expected one of {', '.join(INIT_MODES)}")
        self._mode = mode
        self.init_info = {"mode": mode}
        if not 0 <= first < len(self.stamps):
            raise TrackingError(f"frame {first}: expected 0..{len(self.stamps) - 1}")
        stamp = float(self.stamps[first])
        if mode == "gt":
            if self.ground_truth is None:
                raise TrackingError(f"{self.info.name}: --init gt needs ground truth; use --init-pose x,y[,yaw] "
                                    "or no init option (global localization)")
            T0 = self.ground_truth.interpolate(np.array([stamp]))[0]
            h = 0.05
            p = self.ground_truth.interpolate(np.array([stamp - h, stamp + h]))[:, :3, 3]
            self.tracker.initialize(T0, stamp, velocity_map=(p[1] - p[0]) / (2 * h))
        elif mode == "pose":
            if pose_hint is None:
                raise TrackingError("init 'pose' needs an x,y[,yaw] hint")
            x, y, yaw = pose_hint
            T, res, t_ref = self._global_init(self.seq.frame(first), (x, y), yaw)
            if T is None:
                why = res.stats.get("refused") or f"best fitness {res.fitness:.2f}"
                raise TrackingError(f"global init around ({x:.1f}, {y:.1f}) found no verified pose "
                                    f"({why}); try another --init-pose or --window")
            # The pose is the body's at mid-sweep; the first scan's registration refines it at the
            # frame stamp (they differ by at most speed x half a sweep).
            self.tracker.initialize(T, stamp)
        return self.init_info

    def _global_init(self, frame, hint_xy, hint_yaw):
        """Global init of one frame (prepared as ``blockloc init`` does); records it in init_info.
        Returns (T_map_body or None when not verified, InitResult, stamp of the pose)."""
        return self.recovery.global_init(frame, hint_xy, hint_yaw, self.init_info)

    def relocalize(self, points_lidar: np.ndarray, hint: Optional[np.ndarray], gravity_body: np.ndarray,
                   stamp: float) -> Optional[np.ndarray]:
        """The tracker's recovery (:meth:`Recovery.relocalize`): a verified T_map_body or None;
        every attempt is in ``reloc_log``."""
        return self.recovery.relocalize(points_lidar, hint, gravity_body, stamp)

    # ----------------------------------------------------------------- live sources
    def extend_imu(self, t: np.ndarray, acc: np.ndarray, gyro: np.ndarray) -> int:
        """A live source's IMU samples that arrived after the session was made: t (K,) s ascending,
        acc, gyro (K, 3) imu frame; ``step`` feeds them like the sequence's own (and global init
        and relocalization level and deskew scans with them). Samples not after the last one held
        are ignored; those fed more than 2 s ago are let go (a long run keeps no growing buffer).
        Returns how many were appended."""
        t = np.asarray(t, np.float64).reshape(-1)
        last = float(self.imu.t[-1]) if len(self.imu) else -np.inf
        keep = t > last
        if not keep.any():
            return 0
        fed_until = float(self.imu.t[self._imu_next - 1]) if self._imu_next > 0 else -np.inf
        drop = int(np.searchsorted(self.imu.t, fed_until - 2.0, side="left")) if self._imu_next > 0 else 0
        drop = min(drop, self._imu_next)
        self._hold_imu(ImuData(np.concatenate([self.imu.t[drop:], t[keep]]),
                               np.concatenate([np.asarray(self.imu.acc).reshape(-1, 3)[drop:],
                                               np.asarray(acc, np.float64).reshape(-1, 3)[keep]]),
                               np.concatenate([np.asarray(self.imu.gyro).reshape(-1, 3)[drop:],
                                               np.asarray(gyro, np.float64).reshape(-1, 3)[keep]])))
        self._imu_next -= drop
        return int(keep.sum())

    def restart_stream(self) -> None:
        """A live source restarted (its stamps jumped back): the tracker forgets its state and
        the IMU held is let go, the gap checks start over; the next verified
        :meth:`reinitialize` starts it again."""
        self.tracker.reset()
        self.recovery.ambiguity = None  # scans before the restart are no motion away from the next
        self._hold_imu(ImuData(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))))
        self._imu_next = 0
        self.stream.restart()

    def drop_imu(self) -> None:
        """A live source's IMU stopped: the tracker goes on LiDAR-only from its newest state
        (:meth:`blockloc.tracking.estimator.Estimator.without_imu`; no change when it is already)."""
        self.tracker = self.tracker.without_imu()

    def reinitialize(self, frame, pose_hint: tuple | None = None) -> bool:
        """A live source: global init of ``frame`` (a LidarFrame) around ``pose_hint`` = (x, y,
        yaw or None), map frame, m and rad (None: over the whole map). A verified pose restarts
        the tracker there (True; while tracking, with the velocity and biases it had); otherwise
        the tracker is left as it was (False). The next :meth:`step`'s estimate then says
        ``recovered`` (when its registration passed), as the tracker's own relocalization does:
        the frames after it are not trusted for change detection until tracking settles again
        (the rule of :func:`blockloc.maps.changes.runs.trusted_mask`), also when no lost or
        uninitialized frame came between (an /initialpose, a source that restarted)."""
        self.start()
        # (the mode of ``step`` stays: it does not search again on the same frame)
        self.init_info.setdefault("mode", "global" if pose_hint is None else "pose")
        hint_xy = None if pose_hint is None else (float(pose_hint[0]), float(pose_hint[1]))
        T, _, _ = self._global_init(frame, hint_xy, None if pose_hint is None else pose_hint[2])
        if T is None:
            return False
        if self.tracker.initialized:  # while tracking: keep the robot's motion (Estimator.restart)
            self._feed_imu(frame)  # the restart deskews the frame with it
            self.tracker.restart_on(frame, T)
        else:
            self.tracker.initialize(T, float(frame.stamp))
        self.init_info["first_frame"] = int(frame.index)
        self._reinitialized = True
        return True

    def _hold_imu(self, imu: ImuData) -> None:
        """The IMU samples held from now on (the session's and its recovery's: one buffer)."""
        self.imu = imu
        self.recovery.imu = imu

    # ----------------------------------------------------------------- the frame step
    def start(self) -> None:
        """Tell the observers the run starts (``step`` does it on the first frame)."""
        if self._started:
            return
        self._started = True
        self.observers.start(self.run_info())

    def step(self, frame, on_estimate: Callable | None = None):
        """Process one scan: feed the IMU samples up to the end of its sweep, then the scan.
        Returns the tracker's Estimate. ``on_estimate(est)``, when given, is called with it as soon
        as the tracker has it, before the bookkeeping and the observers (a live node publishes
        the pose there: the run folder and recordings are not on its latency path)."""
        self.start()
        t0 = time.perf_counter()
        self.stream.lidar_frame(frame)  # gaps, points dropped for NaN/inf coordinates
        self._feed_imu(frame)
        if self._mode == "global" and not self.tracker.initialized:
            T, _, _ = self._global_init(frame, None, None)
            if T is not None:
                self.tracker.initialize(T, float(frame.stamp))
                self.init_info["first_frame"] = int(frame.index)
        if not self.tracker.initialized:
            est = self._uninitialized(frame, t0)
        else:
            est = self.tracker.insert_frame(frame)
        if self._reinitialized and est.T_map_body is not None:
            self._reinitialized = False
            if est.diagnostics.status == "ok":
                est.diagnostics.status = "recovered"
        if on_estimate is not None:
            on_estimate(est)
        d = est.as_dict()
        d.update(index=int(frame.index), stamp=float(frame.stamp))
        self.stream.imu_gap(frame.index, d.get("imu_gap_s", 0.0))
        self.diagnostics.append(d)
        if est.T_map_body is not None:
            self._poses.append(np.asarray(est.T_map_body))
            self._pose_stamps.append(float(est.stamp))
        if self.keep_estimates:
            self.estimates.append(est)
        self._notify(frame, est, d)
        return est

    def _feed_imu(self, frame) -> None:
        """The tracker gets the IMU samples held up to the end of ``frame``'s sweep (once each)."""
        imu = self.imu
        t_end = frame.stamp + (float(np.max(frame.time_offsets)) if frame.time_offsets is not None
                               and len(frame.time_offsets) else 0.0)
        j = self._imu_next
        while j < len(imu.t) and imu.t[j] <= t_end:
            self.tracker.insert_imu(imu.t[j], imu.acc[j], imu.gyro[j])
            j += 1
        self._imu_next = j

    def skip(self, index: int, stamp: float | None, reason: BaseException | str) -> None:
        """Record a frame that could not be read (logged, counted, the run goes on)."""
        self.start()
        self.counters["skipped_frames"] += 1
        log.warning("frame %d skipped: %s", index, reason)
        if stamp is None and 0 <= index < len(self.stamps):
            stamp = float(self.stamps[index])
        d = {"index": int(index), "stamp": float(stamp if stamp is not None else np.nan), "status": "skipped",
             "error": str(reason)}
        self.diagnostics.append(d)
        self.observers.frame(FrameEvent(int(index), d["stamp"], None, None, np.zeros(3), "skipped", d))

    def _uninitialized(self, frame, t0):
        diag = Diagnostics(status="uninitialized", num_points=len(frame.points),
                           update_ms=(time.perf_counter() - t0) * 1e3)
        return Estimate(frame.index, float(frame.stamp), None, None, np.zeros(3), np.zeros(3), np.zeros(3), diag)

    def _notify(self, frame, est, d: dict) -> None:
        if not self.observers.observers:
            return
        local = self.provider.current() if hasattr(self.provider, "current") else None
        changed = local is not None and local.version != self._last_map_version
        if local is not None:
            self._last_map_version = local.version
        scan = getattr(self.tracker, "last_scan_lidar", None)
        ev = FrameEvent(int(frame.index), float(frame.stamp), est.T_map_body, est.covariance,
                        np.asarray(est.velocity_map), d["status"], d,
                        scan_lidar=None if scan is None or est.T_map_body is None else np.asarray(scan, np.float32),
                        local_map_points=local.points if changed else None,
                        local_map_id=None if local is None else local.region_id,
                        active_entries=() if local is None else tuple(local.entry_ids))
        self.observers.frame(ev)

    def run_info(self) -> RunInfo:
        """What observers are told at the start (the map's entries with their footprints, ...)."""
        entries = []
        kind = "block"
        tile = None
        if self.store is not None:
            kind = self.store.kind
            tile = self.store.params.get("tile_size_m") if kind == "grid" else None
            entries = [{"id": e.id, "bounds_min": e.bounds_min, "bounds_max": e.bounds_max,
                        "centroid": e.centroid, "footprint": entry_footprint(self.store, e)}
                       for e in self.store.entries]
        return RunInfo(str(self.info.name), np.asarray(self.info.T_body_lidar), kind, entries, tile,
                       self.ground_truth, self.config, self.out_dir)

    # ----------------------------------------------------------------- the whole run
    def run(self, start: int = 0, stop: int | None = None, *, init: str = "gt", pose_hint: tuple | None = None,
            progress: Callable[[int, int], None] | None = None,
            should_stop: Callable[[], bool] | None = None) -> RunResult:
        """Initialize at frame ``start``, step frames start..stop-1, finish. ``should_stop`` is
        asked between frames (a True answer ends the run as interrupted)."""
        stop = len(self.stamps) if stop is None else min(int(stop), len(self.stamps))
        interrupted = False
        try:
            self.initialize(init, start, pose_hint)
            t0 = time.perf_counter()
            total = stop - start
            for n, (index, frame) in enumerate(iter_frames(self.seq, start, stop)):
                if should_stop is not None and should_stop():
                    interrupted = True
                    break
                if isinstance(frame, BaseException):
                    self.skip(index, None, frame)
                else:
                    self.step(frame)
                if progress is not None:
                    progress(n + 1, total)
            self.timings["track_s"] = time.perf_counter() - t0
        except BaseException:
            if self._started:  # keep what was computed, then let the error through
                self.finish(interrupted=True)
            else:
                self.close()
            raise
        res = self.finish(interrupted=interrupted)
        if self.output_error is not None:
            raise self.output_error
        return res

    def finish(self, interrupted: bool = False) -> RunResult:
        """Metrics of what was computed; observers finish; the map provider closes. Idempotent."""
        if self._finished is not None:
            return self._finished
        self.close()
        self.timings["total_s"] = time.perf_counter() - self._t_start
        traj = Trajectory(np.asarray(self._pose_stamps), np.asarray(self._poses).reshape(-1, 4, 4))
        stats = self.provider.stats() if hasattr(self.provider, "stats") else {}
        counters = dict(getattr(self.tracker, "counters", {}) if self.tracker is not None else {})
        # the tracker counts the scans it was given; the metrics' "frames" counts every frame of
        # the run, skipped ones included
        counters["tracker_frames"] = counters.pop("frames", 0)
        counters.update(self.counters)
        counters["map_faults"] += int(stats.get("failed_loads", 0)) + int(stats.get("target_failures", 0))
        plot_dir = self.out_dir if (self.out_dir is not None and self.plots) else None
        metrics = run_metrics(diagnostics=self.diagnostics, counters=counters, trajectory=traj,
                              ground_truth=self.ground_truth, evaluation=self.evaluation, plot_dir=plot_dir,
                              sequence=str(self.info.name), **self.facts, init=self.init_info,
                              interrupted=bool(interrupted), relocalizations=self.reloc_log,
                              map_stats=stats, track_s=self.timings.get("track_s"),
                              total_s=self.timings["total_s"])
        try:
            self.observers.finish(metrics)  # every observer finishes, then the first failure is logged
        except Exception as exc:  # noqa: BLE001 - what was computed is returned all the same
            log.error("an observer could not finish: %s", exc)
            if isinstance(exc, OutputWriteError):  # the results folder lacks its metrics: run() raises it
                self.output_error = exc
        self._finished = RunResult(traj, self.diagnostics, metrics, self.out_dir,
                                   self.estimates if self.keep_estimates else [])
        return self._finished

    @property
    def result(self) -> RunResult | None:
        """What ``finish`` returned (None before it ran)."""
        return self._finished

    def close(self) -> None:
        """Stop the map provider's thread (idempotent)."""
        self.provider.close()

