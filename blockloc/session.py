"""A tracking session: one sequence, one map, one tracker, stepped frame by frame.

``Session.from_config(cfg, seq, store)`` assembles the parts (registration engine, map policy and
provider, global localizer, tracker); then either

    session.run(init="gt")                      # initialize -> every frame -> finish

or, driven from outside (the benchmarks step several sessions in lockstep):

    session.initialize("gt", first_frame)
    for frame in seq.frames():
        session.step(frame)                     # IMU fed up to the sweep's end, then the scan
    result = session.finish()

Initialization: ``gt`` (the first ground-truth pose), ``pose`` (global init around an x, y[, yaw]
hint) or ``global`` (global init over the whole map on the first frames, until one is verified:
the map's place index, see :mod:`blockloc.global_init.place_index`). A tracker that is lost
relocalizes around its last good pose, then over the whole map (:meth:`Session.relocalize`);
only verified poses restart it, and the frames in between are reported lost, never ok.
Every path prepares its scan with :func:`blockloc.tracking.scan_prep.prepare_for_init`, as
``blockloc init`` does.

A run survives bad frames: a scan that cannot be read is skipped (``skipped_frames``), a map
entry that cannot be loaded is treated as unmapped (``map_faults``), IMU and LiDAR gaps are
logged and counted (``imu_gaps``, ``lidar_gaps``); ``run(should_stop=...)`` stops between frames
(Ctrl-C), and ``finish`` always hands the observers what was computed (``interrupted`` in the
metrics).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator, Optional, Sequence

import numpy as np

from blockloc.errors import BlocklocError, GlobalInitError, MapError, RegistrationError, TrackingError
from blockloc.geometry import Trajectory, transform_points
from blockloc.viz.events import FrameEvent, ObserverGroup, RunInfo

log = logging.getLogger(__name__)

INIT_MODES = ("gt", "pose", "global")
IMU_GAP_WARN_S = 0.5  # an IMU gap longer than this is logged and counted (once per gap)
LIDAR_GAP_FACTOR = 3.0  # a gap between scans of more than this many scan periods is logged


@dataclass
class RunResult:
    """What a session produced: the estimate (T_map_body), per-frame diagnostics, metrics, the
    results folder (or None) and, when kept, the tracker's Estimate objects."""

    trajectory: Trajectory
    diagnostics: list[dict]
    metrics: dict
    out_dir: object | None
    estimates: list = field(default_factory=list, repr=False)


@dataclass(frozen=True)
class GlobalInitSettings:
    """Search windows of global init: window_m (side, m) and yaw_window_deg around a hint."""

    window_m: float = 40.0
    yaw_window_deg: float = 360.0


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
        self.localizer = localizer
        self.store = store
        self.init_settings = init_settings
        self.observers = ObserverGroup(observers)  # a failing viewer is dropped, never stops tracking
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
        self._finished: RunResult | None = None
        self._last_map_version = None
        self._last_stamp: float | None = None
        self._imu_gap_s = 0.0  # the longest gap of the IMU gap in progress, or 0
        self.init_info: dict = {}
        self.reloc_log: list[dict] = []
        self.diagnostics: list[dict] = []
        self.estimates: list = []
        self._poses: list[np.ndarray] = []
        self._pose_stamps: list[float] = []
        self.counters = {"skipped_frames": 0, "map_faults": 0, "imu_gaps": 0, "lidar_gaps": 0}
        self.timings: dict[str, float] = {}
        self._t_start = time.perf_counter()

    # ----------------------------------------------------------------- assembly
    @classmethod
    def from_config(cls, cfg, seq, store, *, backend: str | None = None, observers: Sequence = (),
                    out_dir=None, keep_estimates: bool = False, facts: dict | None = None) -> "Session":
        """All parts from a ``blockloc.config.Config``: the engine ``registration.method``, the
        map policy ``backend`` (default ``map.backend``) and its provider, the global localizer
        (refining with the same engine at ``global_init.ndt_resolution_m``) and the tracker."""
        import dataclasses

        from blockloc.global_init.relocalize import GlobalLocalizer, InitParams
        from blockloc.maps.policies import make_policy
        from blockloc.maps.provider import MapProvider
        from blockloc.registration.engines import engine_from_settings
        from blockloc.tracking.tracker import Tracker

        backend = backend or cfg.map.backend
        rc, mc, gi = cfg.registration, cfg.map, cfg.global_init
        seq = _with_map_mounting(seq, store, mc.use_map_mounting)
        engine = engine_from_settings(dataclasses.asdict(rc))
        policy = make_policy(backend, store, **dataclasses.asdict(mc))
        provider = MapProvider(store, policy, engine=engine, prefetch=mc.prefetch,
                               lookahead_s=mc.prefetch_lookahead_s, cache_mb=mc.cache_mb,
                               retry_missing_s=mc.retry_missing_s)
        try:
            init_engine = engine_from_settings(dataclasses.asdict(rc), resolution_m=gi.ndt_resolution_m)
            localizer = GlobalLocalizer.for_store(store, seq.info.gravity_map, InitParams.from_config(gi, rc),
                                                  engine=init_engine)
            ev = cfg.evaluation
            session = cls(seq, None, provider, localizer=localizer, store=store,
                          init_settings=GlobalInitSettings(gi.window_m, gi.yaw_window_deg),
                          observers=observers, out_dir=out_dir, keep_estimates=keep_estimates,
                          evaluation={"align": ev.align, "max_time_diff_s": ev.max_time_diff_s,
                                      "rpe_deltas_m": ev.rpe_deltas_m}, plots=ev.plots,
                          facts={"backend": backend, "registration": rc.method, **(facts or {})},
                          config=cfg.to_dict())
            session.tracker = Tracker.from_config(cfg, seq.info, map_provider=provider, registration=engine,
                                                  relocalize=session.relocalize,
                                                  use_imu=len(session.imu) > 0 and cfg.tracking.use_imu)
        except BaseException:
            provider.close()
            raise
        return session

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
                raise TrackingError(f"global init around ({x:.1f}, {y:.1f}) found no verified pose "
                                    f"(best fitness {res.fitness:.2f}); try another --init-pose or --window")
            # The pose is the body's at mid-sweep; the first scan's registration refines it at the
            # frame stamp (they differ by at most speed x half a sweep).
            self.tracker.initialize(T, stamp)
        return self.init_info

    def _global_init(self, frame, hint_xy, hint_yaw):
        """Global init of one frame (prepared as ``blockloc init`` does); records it in init_info.
        Returns (T_map_body or None when not verified, InitResult, stamp of the pose)."""
        from blockloc.jit import CompileClock
        from blockloc.tracking.scan_prep import prepare_for_init

        if self.localizer is None:
            raise TrackingError("no global localizer: cannot initialize without a pose")
        s = self.init_settings
        scan = prepare_for_init(frame, self.imu, self.info)
        yaw_window = s.yaw_window_deg if hint_yaw is not None else 360.0
        t0 = time.perf_counter()
        with CompileClock() as jit:
            res = self.localizer.localize(scan.points_body, scan.gravity_body, hint_xy, hint_yaw, s.window_m,
                                          yaw_window if hint_xy is not None else 360.0)
        # a first run after install compiles the kernels inside the search: reported apart
        self.init_info.update(time_s=time.perf_counter() - t0 - jit.seconds, compile_s=jit.seconds,
                              verified=bool(res.verified),
                              fitness=float(res.fitness), score=float(res.score), ambiguous=bool(res.ambiguous),
                              frame=int(frame.index), stamp=scan.stamp)
        ok = res.T_map_body is not None and res.verified
        if ok and self.ground_truth is not None:
            from blockloc.global_init.relocalize import pose_error

            Tg = self.ground_truth.interpolate(np.array([scan.stamp]))[0]
            self.init_info["error_m"], self.init_info["error_deg"] = pose_error(np.asarray(res.T_map_body), Tg)
        return (np.asarray(res.T_map_body) if ok else None), res, scan.stamp

    def relocalize(self, points_lidar: np.ndarray, hint: Optional[np.ndarray], gravity_body: np.ndarray,
                   stamp: float) -> Optional[np.ndarray]:
        """The tracker's recovery: global init of a scan (lidar frame) around ``hint``
        (T_map_body), and, when nothing there is verified, over the whole map (the place index:
        a kidnapped robot is outside any window around its last pose). Only a verified pose is
        returned; a failed or impossible attempt returns None. Every attempt is in ``reloc_log``."""
        if self.localizer is None:
            return None
        pts_body = transform_points(self.info.T_body_lidar, points_lidar)
        T, searched = self._relocalize_once(pts_body, hint, gravity_body, stamp)
        if T is None and searched and hint is not None:
            # The hint's attitude comes from a state that has diverged: level the scan by the
            # accelerometer when there is one.
            T, _ = self._relocalize_once(pts_body, None, self._gravity_at(stamp, gravity_body), stamp)
        return T

    def _gravity_at(self, stamp: float, fallback: np.ndarray) -> np.ndarray:
        """Gravity (3,) in the body frame at ``stamp`` from the accelerometer, else ``fallback``."""
        if self.imu is None or len(self.imu) == 0:
            return np.asarray(fallback, float)
        from blockloc.tracking.scan_prep import gravity_from_imu

        try:
            return gravity_from_imu(self.imu, float(stamp), self.info.T_body_imu)
        except GlobalInitError:
            return np.asarray(fallback, float)

    def _relocalize_once(self, pts_body: np.ndarray, hint: Optional[np.ndarray], gravity_body: np.ndarray,
                         stamp: float) -> tuple[Optional[np.ndarray], bool]:
        """(verified T_map_body or None, whether the search ran: False when global init could not
        start, e.g. a scan too sparse to project, which another search would not change)."""
        s = self.init_settings
        entry = {"stamp": float(stamp), "hint": hint is not None}
        try:
            if hint is None:
                res = self.localizer.localize(pts_body, gravity_body, None, None, s.window_m, 360.0)
            else:
                yaw = float(np.arctan2(hint[1, 0], hint[0, 0]))
                res = self.localizer.localize(pts_body, gravity_body, (float(hint[0, 3]), float(hint[1, 3])),
                                              yaw, s.window_m, s.yaw_window_deg)
        except (GlobalInitError, RegistrationError, MapError) as exc:
            # e.g. a scan too sparse to project, or a map entry that cannot be read: this attempt
            # failed, tracking goes on
            if isinstance(exc, MapError):
                self.counters["map_faults"] += 1
            log.warning("relocalization at t=%.2f failed: %s", stamp, exc)
            self.reloc_log.append({**entry, "verified": False, "fitness": 0.0, "time_s": 0.0, "error": str(exc)})
            return None, False
        self.reloc_log.append({**entry, "verified": bool(res.verified), "ambiguous": bool(res.ambiguous),
                               "fitness": float(res.fitness), "time_s": float(res.time_s)})
        if not res.verified or res.T_map_body is None:
            log.info("relocalization at t=%.2f%s: no verified match (best fitness %.2f)", stamp,
                     "" if hint is not None else " over the whole map", res.fitness)
            return None, True
        return np.asarray(res.T_map_body), True

    # ----------------------------------------------------------------- the frame step
    def start(self) -> None:
        """Tell the observers the run starts (``step`` does it on the first frame)."""
        if self._started:
            return
        self._started = True
        self.observers.start(self.run_info())

    def step(self, frame):
        """Process one scan: feed the IMU samples up to the end of its sweep, then the scan.
        Returns the tracker's Estimate."""
        self.start()
        t0 = time.perf_counter()
        self._check_lidar_gap(frame)
        imu = self.imu
        t_end = frame.stamp + (float(np.max(frame.time_offsets)) if frame.time_offsets is not None
                               and len(frame.time_offsets) else 0.0)
        j = self._imu_next
        while j < len(imu.t) and imu.t[j] <= t_end:
            self.tracker.insert_imu(imu.t[j], imu.acc[j], imu.gyro[j])
            j += 1
        self._imu_next = j
        if self._mode == "global" and not self.tracker.initialized:
            T, _, _ = self._global_init(frame, None, None)
            if T is not None:
                self.tracker.initialize(T, float(frame.stamp))
                self.init_info["first_frame"] = int(frame.index)
        if not self.tracker.initialized:
            est = self._uninitialized(frame, t0)
        else:
            est = self.tracker.insert_frame(frame)
        d = est.as_dict()
        d.update(index=int(frame.index), stamp=float(frame.stamp))
        self._check_imu_gap(frame.index, d.get("imu_gap_s", 0.0))
        self.diagnostics.append(d)
        if est.T_map_body is not None:
            self._poses.append(np.asarray(est.T_map_body))
            self._pose_stamps.append(float(est.stamp))
        if self.keep_estimates:
            self.estimates.append(est)
        self._notify(frame, est, d)
        return est

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
        from blockloc.tracking.tracker import Diagnostics, Estimate

        diag = Diagnostics(status="uninitialized", num_points=len(frame.points),
                           update_ms=(time.perf_counter() - t0) * 1e3)
        return Estimate(frame.index, float(frame.stamp), None, None, np.zeros(3), np.zeros(3), np.zeros(3), diag)

    def _check_imu_gap(self, index: int, gap_s: float) -> None:
        """Count a gap of the IMU stream once, logged on the first frame it spans and on the
        frame where samples are back (the frames between see the same gap, growing)."""
        if gap_s > IMU_GAP_WARN_S:
            if self._imu_gap_s == 0.0:
                self.counters["imu_gaps"] += 1
                log.warning("frame %d: an IMU gap: no samples for the last %.2f s", index, gap_s)
            self._imu_gap_s = max(self._imu_gap_s, gap_s)
        elif self._imu_gap_s > 0.0:
            log.warning("frame %d: IMU samples again, after a gap of %.2f s", index, self._imu_gap_s)
            self._imu_gap_s = 0.0

    def _check_lidar_gap(self, frame) -> None:
        stamp = float(frame.stamp)
        period = 1.0 / max(float(getattr(self.info, "lidar_rate_hz", 10.0) or 10.0), 1e-6)
        if self._last_stamp is not None and stamp - self._last_stamp > LIDAR_GAP_FACTOR * period:
            self.counters["lidar_gaps"] += 1
            log.warning("frame %d: no LiDAR scan for %.2f s before it", frame.index, stamp - self._last_stamp)
        self._last_stamp = stamp

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
            from blockloc.maps.summary import entry_footprint

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
        return self.finish(interrupted=interrupted)

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
        from blockloc.evaluation.results import run_metrics

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


def _with_map_mounting(seq, store, use: bool):
    """:func:`blockloc.maps.mounting.with_map_mounting` (the session's and ``init``'s)."""
    from blockloc.maps.mounting import with_map_mounting

    return with_map_mounting(seq, store, use)
    deg, m = mounting_difference(X_map, np.asarray(seq.info.T_body_lidar, np.float64))
    if use:
        from blockloc.datasets.base import RemountedSequence

        log.info("%s: tracking with the map's estimated LiDAR mounting (%.2f deg, %.3f m from the "
                 "sequence's)", seq.info.name, deg, m)
        return RemountedSequence(seq, X_map)
    if deg > 0.05 or m > 0.005:
        log.warning("the map was built with a LiDAR mounting estimated from its drive that differs "
                    "from %s's by %.2f deg / %.3f m; if the same robot recorded both, "
                    "--set map.use_map_mounting=true tracks with it", seq.info.name, deg, m)
    return seq
