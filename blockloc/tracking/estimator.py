"""The streaming pose tracker's shared frame step (:class:`Estimator`); the variants differ only in the states, priors
and motion factors they create (as GLIM's estimators do):
:class:`blockloc.tracking.imu_tracker.ImuTracker` (IMU preintegration) and
:class:`blockloc.tracking.lidar_only.LidarOnlyTracker` (a constant-velocity prior on SE(3)).

Per frame (``insert_frame``), in a 20 -> 5 window:
 1. predict the body pose over the sweep from the newest keyframe's estimate (variant),
 2. downsample the scan and deskew it to the keyframe time (variant),
 3. ask the map provider for the local map at the predicted position (it reports switches),
 4. register the scan with the predicted pose as initial guess (a variant may retry),
 5. check health (fitness, innovation against the prediction, gates from the variant),
 6. add a keyframe linked to the previous one by the variant's factor, the NDT factor when
    accepted, optionally a LiDAR odometry factor; optimize the window,
 7. marginalize: down to N_r keyframes on a map switch, else down to N_a,
 8. after ``max_bad_frames`` rejected frames in a row, relocalize around the last good pose.

Collaborators are duck-typed so tests can hand in small fakes:
- ``map_provider.update(position_map (3,), velocity_map (3,) | None, stamp) -> LocalMap`` with
  ``.target`` (what ``registration.align`` takes, None when nothing is mapped), ``.switched``,
  and optionally ``.block_id`` / ``.region_id``; optionally ``map_provider.relocate(position,
  velocity, stamp)``, called after a relocalization (the map where the robot is now, waited for);
- ``registration.align(target, source_points (N, 3), T_init (4, 4)) -> result`` with
  ``T_target_source``, ``converged``, ``fitness``, ``H`` (6, 6, Pose3 tangent order); optionally
  ``registration.align_from_prediction(target, source_points, T_pred)`` (the same result), used
  from the variant's prediction: an engine may save work where the start is already close (NDT
  skips its coarse stages when its fine level alone converges near the prediction);
- ``relocalize(points_lidar (N, 3), hint_T_map_body (4, 4) | None, gravity_body (3,), stamp)
  -> T_map_body (4, 4) | None``.
"""

from __future__ import annotations

import logging
import time
from typing import Callable, Optional

import numpy as np

from blockloc import deskew as dsk
from blockloc.datasets.base import LidarFrame
from blockloc.errors import TrackingError
from blockloc.geometry import inv_T, rotation_angle, so3_log
from blockloc.tracking.factors import ndt_factor, ndt_information, odometry_factor
from blockloc.tracking.params import TrackerSettings
from blockloc.tracking.restart import Restarts
from blockloc.tracking.results import REJECT_REASONS, Diagnostics, Estimate, plain_id, reject_reason
from blockloc.tracking.window import SlidingWindow, keys_of

log = logging.getLogger(__name__)

Relocalizer = Callable[[np.ndarray, Optional[np.ndarray], np.ndarray, float], Optional[np.ndarray]]


def _deferred(compute: Callable[[], np.ndarray]) -> Callable[[], np.ndarray | None]:
    """``compute`` (reading a :meth:`SlidingWindow.frozen` window, not the live one) as the callable
    ``Estimate.covariance`` runs on its first read; an indeterminant system gives None. Why: the
    marginals cost about as much as the smoother's optimization, and a caller that never reads
    them (a benchmark, track without a recording) should not pay for them in the per-scan update."""

    def run() -> np.ndarray | None:
        try:
            return compute()
        except RuntimeError as exc:  # an indeterminant system: report, do not crash
            log.debug("no covariance: %s", exc)
            return None

    return run


class Estimator(Restarts):
    """Streaming estimator: ``insert_imu`` for every IMU sample, ``insert_frame`` for every scan.

    The base of the two variants; ``lidar_only`` says which one an object is. Build one with
    :func:`blockloc.tracking.tracker.make_tracker`.
    """

    lidar_only: bool

    def __init__(self, *, map_provider, registration, T_body_lidar: np.ndarray, gravity_map: np.ndarray,
                 settings: TrackerSettings = TrackerSettings(), relocalize: Relocalizer | None = None) -> None:
        self.map_provider = map_provider
        self.registration = registration
        self.T_body_lidar = np.asarray(T_body_lidar, dtype=np.float64)
        self.T_lidar_body = inv_T(self.T_body_lidar)
        self.gravity_map = np.asarray(gravity_map, dtype=np.float64).reshape(3)
        self.settings = settings
        self.params = settings.tracking
        self.ndt = settings.tracking.ndt_factor_params()
        self.relocalize = relocalize
        self.window = SlidingWindow(self.params.window_size, self.params.lm_iterations)
        self._next_index = 0
        self._last_ndt: tuple[int, np.ndarray] | None = None  # (keyframe, T_map_body) of the last accepted NDT
        self._last_good: np.ndarray | None = None
        # (velocity (3,) in the body frame, bias) of the last accepted keyframe: what a recovery
        # restarts from (the diverged state's are not to be trusted)
        self._last_good_motion: tuple | None = None
        self._recent_fitness: list[float] = []  # of the last accepted scans
        self._bad_streak = 0
        self._lost_frames = 0
        self.last_scan_lidar: np.ndarray | None = None  # the last deskewed registration input (N, 3)
        # the frames since a start whose velocity was unknown, until the window gives it (_settle)
        self._settling: list[LidarFrame] | None = None
        self.counters = {"frames": 0, "failures": 0, "recoveries": 0, "switches": 0, "rejected": 0,
                         "imu_only": 0, "rotation_retries": 0, "rotation_recoveries": 0}
        # why each rejected scan was rejected (the first test it failed, in this order), to tell an
        # engine that does not converge from one whose fits are poor or land off the prediction
        self.counters.update({f"rejected_{r}": 0 for r in REJECT_REASONS})

    # ----------------------------------------------------------------- what a variant provides
    def insert_imu(self, t: float, acc: np.ndarray, gyro: np.ndarray) -> None:
        """One IMU sample: t seconds, acc (3,) m/s^2 specific force and gyro (3,) rad/s, imu frame."""
        raise NotImplementedError

    def _start_keyframe(self, i: int, T: np.ndarray, stamp: float, vel: np.ndarray, bias,
                        sigma_vel_m_s: float) -> None:
        """Add keyframe ``i``'s first values to the (cleared) window and the priors that hold it."""
        raise NotImplementedError

    def _start_rate(self, i: int, rate_body: np.ndarray) -> None:
        """Keyframe ``i``'s starting angular rate, rad/s in the body frame, where the variant holds
        one as a state (the IMU variant takes it from the gyro: nothing to do)."""

    def _state(self, i: int):
        """(gtsam.NavState, gtsam.imuBias.ConstantBias) of keyframe i."""
        raise NotImplementedError

    def _gravity_unknown_pose(self) -> np.ndarray:
        """Gravity (3,) in the body frame, m/s^2, before any pose is known."""
        raise NotImplementedError

    def _predict_and_deskew(self, points, offsets, stamp, t_key, t_prev, last):
        """(T_map_body (4, 4), velocity_map (3,)) predicted at ``t_key`` from keyframe ``last``
        (at ``t_prev``), and the points (times ``stamp + offsets``) deskewed to ``t_key``."""
        raise NotImplementedError

    def _link_keyframe(self, k, last, t_prev, stamp, values, T_pred, v_pred, T_ndt, accepted, diag) -> None:
        """Insert keyframe ``k``'s remaining values (its pose is in ``values``), add it to the
        window with the factor linking it to keyframe ``last``."""
        raise NotImplementedError

    def _keyframe_time(self, stamp: float, offsets: np.ndarray, t_prev: float) -> float:
        """The time a new keyframe's state refers to: the frame stamp."""
        return stamp

    def _gates(self, dt: float) -> tuple[float, float]:
        """Innovation gates (m, deg) for a prediction ``dt`` seconds ahead."""
        return self.params.max_innovation_m, self.params.max_innovation_deg

    def _retry(self, target, scan_pts, T_pred, gates, diag, res):
        """After registration from the prediction failed its health check: another healthy
        (T_ndt, result), or None (the scan is rejected)."""
        return None

    def _pose_at_stamp(self, k: int, state, tau: float):
        """(NavState, covariance (6, 6) | None) at the frame stamp, ``tau`` s after keyframe k."""
        frozen = self.window.frozen()
        return state, self._covariance(lambda: frozen.covariance(keys_of(k)[0]))

    def _after_frame(self) -> None:
        """Housekeeping at the end of a frame step."""

    # ----------------------------------------------------------------- state
    @property
    def initialized(self) -> bool:
        return len(self.window) > 0

    def initialize(self, T_map_body: np.ndarray, stamp: float, velocity_map: np.ndarray | None = None,
                   bias=None, sigma_vel_m_s: float | None = None) -> None:
        """Start (or restart) the window with one keyframe at ``stamp`` held by priors.

        velocity_map: (3,) m/s if known (e.g. from ground truth), else zero with a loose prior.
        bias: the IMU variant's starting bias (zero by default); the LiDAR-only one has none.
        """
        T = np.asarray(T_map_body, dtype=np.float64)
        vel = np.zeros(3) if velocity_map is None else np.asarray(velocity_map, dtype=np.float64)
        if sigma_vel_m_s is None:
            sigma_vel_m_s = 0.1 if velocity_map is not None else self.settings.fixed.init_sigma_vel_m_s
        self.window.clear()
        i = self._next_index
        self._next_index += 1
        self._start_keyframe(i, T, float(stamp), vel, bias, sigma_vel_m_s)
        self._last_ndt = None
        self._last_good = T.copy()
        self._last_good_motion = None
        self._recent_fitness = []
        self._bad_streak = 0
        self._lost_frames = 0
        self._settling = [] if velocity_map is None else None

    def reset(self) -> None:
        """Forget the state: window, last good pose, recent fitness (a live stream that restarted
        with earlier stamps); :meth:`initialize` starts it again. Counters and the variant stay."""
        self.window.clear()
        self._last_ndt = self._last_good = self._last_good_motion = None
        self._recent_fitness = []
        self._bad_streak = self._lost_frames = 0
        self._settling = None

    def without_imu(self) -> "Estimator":
        """The estimator to go on with when the IMU stops mid-run: the LiDAR-only variant
        continuing from this one's newest state (itself when it uses no IMU)."""
        raise NotImplementedError

    def _gravity_body(self, T_map_body: np.ndarray | None) -> np.ndarray:
        if T_map_body is not None:
            return T_map_body[:3, :3].T @ self.gravity_map
        return self._gravity_unknown_pose()

    # ----------------------------------------------------------------- the frame step
    def insert_frame(self, frame: LidarFrame) -> Estimate:
        """Process one LiDAR sweep; returns the estimate at ``frame.stamp``."""
        est = self._insert_frame(frame)
        if self._settling is not None:
            est = self._settle(frame, est)
        return est

    def _settle(self, frame: LidarFrame, est: Estimate) -> Estimate:
        """After a start whose velocity was unknown (zero, with a loose prior): once the second
        keyframe gives the velocity, the window starts again at the first keyframe with it and the
        scans since the start are deskewed and registered again.

        Why: deskewed with zero velocity, a sweep at speed v lands about v x half a sweep along the
        motion (0.3 m at 5 m/s and 10 Hz), and the window keeps that error for its whole length
        (measured on the tiny circle drive after a global init: 0.29, 0.33 m, then 0.06-0.13 m
        for 8 scans). Two keyframes misplaced alike give the velocity all the same. Costs one
        frame's work twice, once per start; the counters count each frame once."""
        self._settling.append(frame)
        if len(self.window) < 2:
            return est
        frames, self._settling = self._settling, None
        if len(self.window) != 2 or est.diagnostics.status != "ok":
            return est  # a rejected scan or a relocalization: nothing to settle from
        first, latest = min(self.window.stamps), self.window.latest
        t_first, t_latest = self.window.stamps[first], self.window.stamps[latest]
        if t_latest - t_first > 0.3:  # scans far apart: their chord is no velocity to deskew with
            return est
        T_first = self.window.values.atPose3(keys_of(first)[0]).matrix()
        p_latest = self.window.values.atPose3(keys_of(latest)[0]).translation()
        dt = max(t_latest - t_first, 1e-3)  # (the keyframes are distinct: > 1e-4 s apart)
        v_map = (np.asarray(p_latest) - T_first[:3, 3]) / dt
        R_first_latest = T_first[:3, :3].T @ self.window.values.atPose3(keys_of(latest)[0]).rotation().matrix()
        if float(np.linalg.norm(v_map)) < 0.2:  # at rest, zero was right
            return est
        counters = dict(self.counters)
        self.initialize(T_first, t_first, velocity_map=v_map, sigma_vel_m_s=0.5)
        self._start_rate(self.window.latest, so3_log(R_first_latest) / dt)
        for f in frames:
            est = self._insert_frame(f)
        self.counters = counters
        log.debug("frame %d: velocity settled at %.2f m/s, %d scans registered again", frame.index,
                  float(np.linalg.norm(v_map)), len(frames))
        return est

    def _insert_frame(self, frame: LidarFrame) -> Estimate:
        t_start = time.perf_counter()
        p = self.params
        stamp = float(frame.stamp)
        diag = Diagnostics()
        self.counters["frames"] += 1

        points, offsets = self._preprocess(frame)
        diag.num_points = len(points)
        diag.prep_ms = (time.perf_counter() - t_start) * 1e3

        if not self.initialized:
            est = self._start_without_pose(frame, points, stamp, diag)
            if est is not None:
                return est

        last = self.window.latest
        t_prev = self.window.stamps[last]
        t_key = self._keyframe_time(stamp, offsets, t_prev)

        # 1-2. prediction over the sweep, deskew to the keyframe time.
        t0 = time.perf_counter()
        T_pred, v_pred, scan_pts = self._predict_and_deskew(points, offsets, stamp, t_key, t_prev, last)
        diag.deskew_ms = (time.perf_counter() - t0) * 1e3
        self.last_scan_lidar = scan_pts

        # 3. the local map at the predicted position.
        t0 = time.perf_counter()
        local = self.map_provider.update(T_pred[:3, 3].copy(), v_pred.copy(), stamp)
        diag.map_ms = (time.perf_counter() - t0) * 1e3
        diag.switched = bool(getattr(local, "switched", False))
        diag.block_id = plain_id(getattr(local, "block_id", getattr(local, "region_id", None)))
        if diag.switched:
            self.counters["switches"] += 1

        # 4-5. registration and its health.
        t0 = time.perf_counter()
        T_ndt, info, accepted = self._register(local, scan_pts, T_pred, diag, t_key - t_prev)
        diag.registration_ms = (time.perf_counter() - t0) * 1e3

        # 6-7. the window.
        t0 = time.perf_counter()
        k = self._add_keyframe(t_key, t_prev, last, T_pred, v_pred, T_ndt, info, accepted, diag)
        self.window.optimize()
        diag.marginalized = self.window.enforce_size(diag.switched, p.window_size_on_switch)
        diag.window_size = len(self.window)
        diag.smoother_ms = (time.perf_counter() - t0) * 1e3

        # 8. health bookkeeping and recovery.
        if accepted:
            est_T = self.window.values.atPose3(keys_of(k)[0]).matrix()
            self._bad_streak = 0
            self._lost_frames = 0
            self._last_good = est_T.copy()
            state_k, bias_k = self._state(k)
            self._last_good_motion = (est_T[:3, :3].T @ np.asarray(state_k.velocity()), bias_k)
            self._recent_fitness = (self._recent_fitness + [diag.fitness])[-5:]
        elif diag.status == "rejected":  # a dropout (imu_only) is not a sign of divergence
            self._bad_streak += 1
            if self._bad_streak >= p.max_bad_frames:
                if self._bad_streak == p.max_bad_frames:
                    self.counters["failures"] += 1
                    log.warning("frame %d: %d rejected scans in a row, relocalizing", frame.index,
                                self._bad_streak)
                diag.status = "lost"
                if self._try_recover(scan_pts, t_key, k, diag, (points, offsets, stamp)) is not None:
                    k = self.window.latest
        self._after_frame()

        return self._estimate(frame.index, stamp, k, diag, t_start)

    # ----------------------------------------------------------------- steps
    def _preprocess(self, frame: LidarFrame) -> tuple[np.ndarray, np.ndarray]:
        s = self.settings.scan
        pts = np.asarray(frame.points)
        if len(pts) == 0:
            return np.zeros((0, 3)), np.zeros(0)
        # range filter + voxel selection: one pass over the raw cloud; only the points kept are converted
        idx = dsk.voxel_downsample_indices(pts, s.voxel_size_m, s.max_points, seed=frame.index,
                                           range_m=(s.min_range_m, s.max_range_m))
        offsets = (np.zeros(len(idx)) if frame.time_offsets is None
                   else np.asarray(frame.time_offsets, dtype=np.float64)[idx])
        return np.ascontiguousarray(pts[idx, :3], dtype=np.float64), offsets

    def _align(self, target, scan_pts, T_guess, T_pred, gates):
        """One registration from ``T_guess``: (T_ndt, result, fitness, innovation m, deg, reject
        reason: "" when healthy). From the prediction itself (``T_guess is T_pred``) of a window
        that has tracked (two keyframes or more) through the engine's ``align_from_prediction``
        when it has one."""
        align = self.registration.align
        # not from a window of one keyframe (a start or a restart): that prediction is a search's
        # pose, often tenths of a metre off, where NDT's fine level alone can settle short of the
        # optimum (seen: 0.29 m off on the scan after a new initial pose; 0.001 m with every stage)
        if T_guess is T_pred and len(self.window) >= 2:
            align = getattr(self.registration, "align_from_prediction", align)
        res = align(target, scan_pts, T_guess @ self.T_body_lidar)
        T_ndt = np.asarray(res.T_target_source) @ self.T_lidar_body
        fitness = float(res.fitness)
        inn_m = float(np.linalg.norm(T_ndt[:3, 3] - T_pred[:3, 3]))
        inn_deg = float(np.rad2deg(rotation_angle(T_pred[:3, :3].T @ T_ndt[:3, :3])))
        reason = reject_reason(res, fitness, inn_m, inn_deg, gates, self.params.min_fitness, T_ndt)
        return T_ndt, res, fitness, inn_m, inn_deg, reason

    def _count_rejection(self, diag, reason: str) -> None:
        diag.reject_reason = reason
        self.counters["rejected"] += 1
        self.counters[f"rejected_{reason}"] += 1

    def _register(self, local, scan_pts, T_pred, diag, dt: float = 0.0):
        target = getattr(local, "target", None)
        if target is None or len(scan_pts) < self.settings.scan.min_points:
            diag.status = "imu_only"
            self.counters["imu_only"] += 1
            return None, None, False
        gates = self._gates(dt)
        try:
            T_ndt, res, diag.fitness, diag.innovation_m, diag.innovation_deg, reason = self._align(
                target, scan_pts, T_pred, T_pred, gates)
        except Exception as exc:  # a registration failure is a rejected scan, not a crash
            log.warning("registration failed: %s", exc)
            diag.status = "rejected"
            self._count_rejection(diag, "error")
            return None, None, False
        if reason:
            retry = self._retry(target, scan_pts, T_pred, gates, diag, res)
            if retry is None:
                diag.status = "rejected"
                self._count_rejection(diag, reason)
                return T_ndt, None, False
            T_ndt, res = retry
        info, diag.weak_dims = ndt_information(np.asarray(res.H), self.T_body_lidar, self.ndt)
        return T_ndt, info, True

    def _add_keyframe(self, stamp, t_prev, last, T_pred, v_pred, T_ndt, info, accepted, diag) -> int:
        import gtsam

        p, f = self.params, self.settings.fixed
        if stamp - t_prev < 1e-4:
            # Same time as the newest keyframe (the first scan after initialization): the NDT
            # factor goes on that keyframe, no new state.
            k = last
        else:
            k = self._next_index
            self._next_index += 1
            values = gtsam.Values()
            values.insert(keys_of(k)[0], gtsam.Pose3(T_ndt if accepted else T_pred))
            self._link_keyframe(k, last, t_prev, stamp, values, T_pred, v_pred, T_ndt, accepted, diag)
        if accepted:
            kx = keys_of(k)[0]
            self.window.add_factor(ndt_factor(kx, T_ndt, info, self.ndt.huber_k))
            if p.use_odometry_factor and self._last_ndt is not None and self._last_ndt[0] != k \
                    and self._last_ndt[0] in self.window.stamps:
                j, T_j = self._last_ndt
                self.window.add_factor(odometry_factor(keys_of(j)[0], kx, inv_T(T_j) @ T_ndt,
                                                       f.odometry_sigma_rot_rad, f.odometry_sigma_trans_m,
                                                       self.ndt.huber_k))
            self._last_ndt = (k, T_ndt)
        return k

    def _start_without_pose(self, frame, points, stamp, diag) -> Estimate | None:
        """No pose yet: relocalize over the whole map, or report 'uninitialized'."""
        if self.relocalize is None:
            raise TrackingError("tracker has no initial pose: call initialize() or give a relocalizer")
        T = None
        if len(points) >= self.settings.scan.min_points:
            T = self.relocalize(points, None, self._gravity_body(None), stamp)
        if T is None:
            diag.status = "uninitialized"
            diag.update_ms = 0.0
            return Estimate(frame.index, stamp, None, None, np.zeros(3), np.zeros(3), np.zeros(3), diag)
        log.info("frame %d: initialized by global localization at %s", frame.index, np.round(T[:3, 3], 2))
        self.initialize(T, stamp)
        return None

    def _try_recover(self, scan_pts, stamp, k, diag, raw=None) -> np.ndarray | None:
        """Relocalize around the last good pose; on success restart the window there
        (:meth:`restart`, with ``raw`` = (points, offsets, frame stamp) of the scan)."""
        p = self.params
        if self.relocalize is None or len(scan_pts) < self.settings.scan.min_points:
            return None
        if (self._bad_streak - p.max_bad_frames) % max(1, self.settings.fixed.relocalize_every) != 0:
            return None
        state, _ = self._state(k)
        T_cur = state.pose().matrix()
        hint = self._last_good if self._last_good is not None else T_cur
        T = self.relocalize(scan_pts, hint, self._gravity_body(T_cur), stamp)
        if T is None:
            return None
        self.counters["recoveries"] += 1
        log.warning("relocalized at %s (%.2f m from the last good pose)", np.round(T[:3, 3], 2),
                    np.linalg.norm(T[:3, 3] - hint[:3, 3]))
        local = self.restart(T, stamp, raw)
        if local is not None:
            diag.block_id = plain_id(getattr(local, "block_id", getattr(local, "region_id", None)))
        self.window.optimize()
        diag.status = "recovered"
        diag.window_size = len(self.window)
        return T

    def _covariance(self, compute):
        """The estimate's covariance deferred (:func:`_deferred`); None when not computed at all."""
        return _deferred(compute) if self.settings.fixed.compute_covariance else None

    def _estimate(self, index, stamp, k, diag, t_start) -> Estimate:
        state, bias = self._state(k)
        state, cov = self._pose_at_stamp(k, state, stamp - self.window.stamps[k])
        diag.update_ms = (time.perf_counter() - t_start) * 1e3
        return Estimate(index, stamp, state.pose().matrix(), cov, np.asarray(state.velocity()),
                        np.asarray(bias.accelerometer()), np.asarray(bias.gyroscope()), diag)
