"""The streaming pose tracker: IMU preintegration (or a motion prior) + NDT factors in a 20 -> 5 window.

Per frame (``insert_frame``):
 1. predict the body pose over the sweep from the IMU (from the newest keyframe's estimate),
 2. downsample the scan and deskew it to the scan time (IMU rotation, constant velocity),
 3. ask the map provider for the local map at the predicted position (it reports switches),
 4. register the scan with the predicted pose as initial guess,
 5. check health (fitness, innovation against the prediction),
 6. add a keyframe: CombinedImuFactor from the previous one, the NDT factor when accepted,
    optionally a LiDAR odometry factor; optimize the window,
 7. marginalize: down to N_r keyframes on a map switch, else down to N_a,
 8. after ``max_bad_frames`` rejected frames in a row, relocalize around the last good pose.

LiDAR-only mode (``use_imu=False``, or ``None`` and no IMU sample before the first frame): keyframes hold a
pose and a body twist (``blockloc.tracking.motion``) instead of pose, velocity and biases; step 1
predicts with the last twist (constant velocity on SE(3)), step 2 deskews with the same constant
twist over the sweep, step 6 links keyframes by the constant-velocity factor (noise from
``motion_sigma_*``, scaled by the real gap between stamps). Without a gyro the prediction can be
tens of degrees off (the real walk turns up to 48 deg in 0.5 s), so:
 - the innovation gates become ``max(max_innovation_*, lidar_only_gate_sigmas x sigma)`` with
   sigma the prediction's standard deviation under the motion prior over the gap (at 2 Hz and
   1 rad/s^2/sqrt(s): 58 deg; at 10 Hz the fixed 10 deg gate applies): the prior, not a number
   tuned for an IMU, says how far off a prediction can honestly be;
 - when registration from the prediction fails its health check, rotated predictions (yaw about
   the map's vertical, then roll/pitch, ``rotation_retry_*_deg``; first of all the last estimate
   itself, for a turn that stopped) are registered in turn and the
   first healthy one that also fits at least ``rotation_retry_fitness_ratio`` of the recent scans'
   fitness is accepted (counters ``rotation_retries`` / ``rotation_recoveries``, diagnostics
   ``rotation_retries`` / ``rotation_retry``); only then does the frame count as rejected, and
   relocalization follows as with an IMU (after ``max_bad_frames``).
Gravity for relocalization comes from the map's vertical and the last estimate.

Collaborators are duck-typed so tests can hand in small fakes:
- ``map_provider.update(position_map (3,), velocity_map (3,) | None, stamp) -> LocalMap`` with
  ``.target`` (what ``registration.align`` takes, None when nothing is mapped), ``.switched``,
  and optionally ``.block_id`` / ``.region_id``; optionally ``map_provider.relocate(position,
  velocity, stamp)``, called after a relocalization (the map where the robot is now, waited for);
- ``registration.align(target, source_points (N, 3), T_init (4, 4)) -> result`` with
  ``T_target_source``, ``converged``, ``fitness``, ``H`` (6, 6, Pose3 tangent order);
- ``relocalize(points_lidar (N, 3), hint_T_map_body (4, 4) | None, gravity_body (3,), stamp)
  -> T_map_body (4, 4) | None``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional

import numpy as np

from blockloc.datasets.base import LidarFrame
from blockloc.errors import TrackingError
from blockloc.geometry import inv_T, rotation_angle
from blockloc.tracking import deskew as dsk
from blockloc.tracking import motion
from blockloc.tracking.factors import (
    NdtFactorParams,
    ndt_factor,
    ndt_information,
    odometry_factor,
    pose_prior,
    state_priors,
)
from blockloc.tracking.imu import ImuBuffer, ImuNoise, integrate, make_preintegration_params, predict_states
from blockloc.tracking.motion import MotionNoise
from blockloc.tracking.window import SlidingWindow, keys_of

log = logging.getLogger(__name__)

Relocalizer = Callable[[np.ndarray, Optional[np.ndarray], np.ndarray, float], Optional[np.ndarray]]

# Why a scan's registration was not accepted: ``error`` (the engine raised), ``unconverged``,
# ``fitness`` (inlier ratio below min_fitness), ``innovation`` (farther from the prediction than the
# gates), ``nonfinite``.
REJECT_REASONS = ("error", "unconverged", "fitness", "innovation", "nonfinite")


def reject_reason(res, fitness: float, inn_m: float, inn_deg: float, gates: tuple[float, float],
                  min_fitness: float, T: np.ndarray) -> str:
    """The first acceptance test a registration result fails (one of ``REJECT_REASONS``), or ""
    when it passes them all; gates are (metres, degrees)."""
    if not np.all(np.isfinite(T)):
        return "nonfinite"
    if not bool(getattr(res, "converged", True)):
        return "unconverged"
    if not fitness >= min_fitness:
        return "fitness"
    if inn_m > gates[0] or inn_deg > gates[1]:
        return "innovation"
    return ""


@dataclass(frozen=True)
class TrackerParams:
    """Explicit tracker settings (``from_config`` fills them from the config tree)."""

    window_size: int = 20  # N_a
    window_size_on_switch: int = 5  # N_r
    voxel_size_m: float = 0.5
    max_points: int = 20000
    min_range_m: float = 1.0
    max_range_m: float = 100.0
    deskew: bool = True
    min_points: int = 100
    min_fitness: float = 0.4
    max_innovation_m: float = 1.0
    max_innovation_deg: float = 10.0
    max_bad_frames: int = 3  # rejected frames in a row before relocalization
    relocalize_every: int = 5  # while lost, frames between relocalization attempts
    use_odometry_factor: bool = False
    odometry_sigma_rot_rad: float = np.deg2rad(0.5)
    odometry_sigma_trans_m: float = 0.05
    lm_iterations: int = 6
    compute_covariance: bool = True
    imu_noise_inflation: float = 1.0
    ndt: NdtFactorParams = field(default_factory=NdtFactorParams)
    # first keyframe priors
    init_sigma_rot_rad: float = np.deg2rad(1.0)
    init_sigma_trans_m: float = 0.1
    init_sigma_vel_m_s: float = 1.0
    recover_sigma_vel_m_s: float = 1.5  # velocity prior after a relocalization (around the last good one)
    init_sigma_acc_bias: float = 0.2
    init_sigma_gyro_bias: float = 0.01
    # LiDAR-only tracking (see the module doc). use_imu False: LiDAR-only, IMU samples ignored;
    # True: IMU preintegration (as before LiDAR-only existed); None: decided at the first frame,
    # the IMU when some sample has arrived by then, else LiDAR-only.
    use_imu: bool | None = None
    motion: MotionNoise = field(default_factory=MotionNoise)
    init_sigma_rate_rad_s: float = 1.0  # angular-rate prior of a first keyframe (starts at zero)
    lidar_only_gate_sigmas: float = 5.0
    rotation_retry_yaw_deg: tuple = (15.0, -15.0, 30.0, -30.0, 45.0, -45.0)
    rotation_retry_tilt_deg: tuple = (15.0, -15.0)  # roll and pitch each
    # A rotated prediction is accepted only with at least this fraction of the recent fitness
    # (median of the last accepted scans; min_fitness alone before there are any).
    rotation_retry_fitness_ratio: float = 0.8


@dataclass
class Diagnostics:
    """Per-frame health and cost; every field is plain data for JSON."""

    # ok | rejected | imu_only | lost | recovered | uninitialized; imu_only: no scan factor (no map
    # or too few points), the IMU (LiDAR-only: the motion prior) carried the pose
    status: str = "ok"
    fitness: float = float("nan")
    innovation_m: float = float("nan")
    innovation_deg: float = float("nan")
    window_size: int = 0
    marginalized: int = 0
    switched: bool = False
    block_id: object = None
    num_points: int = 0
    weak_dims: int = 0
    imu_gap_s: float = 0.0
    deskew_ms: float = 0.0
    registration_ms: float = 0.0
    smoother_ms: float = 0.0
    update_ms: float = 0.0
    map_ms: float = 0.0
    rotation_retries: int = 0  # rotated predictions registered after the prediction failed (LiDAR-only)
    rotation_retry: str = ""  # the one accepted, e.g. 'yaw+30' ('' none)
    reject_reason: str = ""  # a rejected scan: the first acceptance test it failed (REJECT_REASONS)


@dataclass
class Estimate:
    """The tracker's answer for one frame.

    T_map_body: (4, 4) or None before the first successful initialization.
    covariance: (6, 6) Pose3 tangent (rotation rad, translation m) of T_map_body, or None.
    (LiDAR-only with per-point times the keyframe sits at the scan's mean point time; pose and
    covariance are carried to ``stamp`` with its twist.)
    velocity_map: (3,) m/s; acc_bias (3,) m/s^2 and gyro_bias (3,) rad/s in the imu frame (zeros
    in LiDAR-only mode, which estimates no biases).
    """

    index: int
    stamp: float
    T_map_body: np.ndarray | None
    covariance: np.ndarray | None
    velocity_map: np.ndarray
    acc_bias: np.ndarray
    gyro_bias: np.ndarray
    diagnostics: Diagnostics

    def as_dict(self) -> dict:
        return asdict(self.diagnostics)


class Tracker:
    """Streaming estimator: ``insert_imu`` for every IMU sample, ``insert_frame`` for every scan."""

    def __init__(self, *, map_provider, registration, T_body_lidar: np.ndarray, T_body_imu: np.ndarray,
                 gravity_map: np.ndarray, imu_noise: ImuNoise = ImuNoise(),
                 params: TrackerParams = TrackerParams(), relocalize: Relocalizer | None = None) -> None:
        self.map_provider = map_provider
        self.registration = registration
        self.T_body_lidar = np.asarray(T_body_lidar, dtype=np.float64)
        self.T_lidar_body = inv_T(self.T_body_lidar)
        self.T_body_imu = np.asarray(T_body_imu, dtype=np.float64)
        self.gravity_map = np.asarray(gravity_map, dtype=np.float64).reshape(3)
        self.params = params
        self.relocalize = relocalize
        self.imu_params = make_preintegration_params(self.gravity_map, self.T_body_imu, imu_noise,
                                                     params.imu_noise_inflation)
        self.imu = ImuBuffer()
        self.window = SlidingWindow(params.window_size, params.lm_iterations)
        # True: LiDAR-only; None: not decided yet (IMU unless no sample arrives before the first frame)
        self.lidar_only: bool | None = {False: True, True: False}.get(params.use_imu)
        self._imu_seen = False
        self._init_args: tuple | None = None  # the last initialize() call, to redo it LiDAR-only
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
        self.counters = {"frames": 0, "failures": 0, "recoveries": 0, "switches": 0, "rejected": 0,
                         "imu_only": 0, "rotation_retries": 0, "rotation_recoveries": 0}
        # why each rejected scan was rejected (the first test it failed, in this order), to tell an
        # engine that does not converge from one whose fits are poor or land off the prediction
        self.counters.update({f"rejected_{r}": 0 for r in REJECT_REASONS})

    # ----------------------------------------------------------------- factories
    @classmethod
    def from_config(cls, cfg, info, *, map_provider, registration, relocalize=None,
                    use_imu: bool | None = None) -> "Tracker":
        """From a ``blockloc.config.Config`` and a ``SequenceInfo``.

        use_imu: True / False when the caller knows whether the sequence has an IMU (e.g.
        ``len(seq.imu()) > 0 and cfg.tracking.use_imu``). None: ``cfg.tracking.use_imu`` false
        means LiDAR-only, true means decided at the first frame (no IMU sample by then: LiDAR-only).
        """
        tc, lc, dc = cfg.tracking, cfg.lidar, cfg.dataset
        ndt = NdtFactorParams(information_scale=tc.ndt_information_scale,
                              degeneracy_ratio=tc.degeneracy_eigenvalue_ratio,
                              min_sigma_rot_rad=np.deg2rad(tc.ndt_min_sigma_rot_deg),
                              min_sigma_trans_m=tc.ndt_min_sigma_trans_m,
                              huber_k=tc.huber_k if tc.robust_loss == "huber" else 0.0)
        params = TrackerParams(window_size=tc.window_size, window_size_on_switch=tc.window_size_on_switch,
                               voxel_size_m=lc.voxel_size_m, max_points=lc.max_points,
                               min_range_m=dc.min_range_m, max_range_m=dc.max_range_m, deskew=lc.deskew,
                               min_fitness=tc.min_fitness, max_innovation_m=tc.max_innovation_m,
                               max_innovation_deg=tc.max_innovation_deg, max_bad_frames=tc.max_bad_frames,
                               use_odometry_factor=tc.use_odometry_factor, lm_iterations=tc.lm_iterations,
                               imu_noise_inflation=tc.imu_noise_inflation, ndt=ndt,
                               use_imu=(None if tc.use_imu else False) if use_imu is None else bool(use_imu),
                               motion=MotionNoise(tc.motion_sigma_acc_rad_s2, tc.motion_sigma_acc_m_s2),
                               init_sigma_rate_rad_s=tc.init_sigma_rate_rad_s,
                               lidar_only_gate_sigmas=tc.lidar_only_gate_sigmas,
                               rotation_retry_yaw_deg=tuple(tc.rotation_retry_yaw_deg),
                               rotation_retry_tilt_deg=tuple(tc.rotation_retry_tilt_deg),
                               rotation_retry_fitness_ratio=tc.rotation_retry_fitness_ratio)
        return cls(map_provider=map_provider, registration=registration, T_body_lidar=info.T_body_lidar,
                   T_body_imu=info.T_body_imu, gravity_map=info.gravity_map,
                   imu_noise=ImuNoise.from_config(cfg.imu), params=params, relocalize=relocalize)

    # ----------------------------------------------------------------- state
    @property
    def initialized(self) -> bool:
        return len(self.window) > 0

    def initialize(self, T_map_body: np.ndarray, stamp: float, velocity_map: np.ndarray | None = None,
                   bias=None, sigma_vel_m_s: float | None = None) -> None:
        """Start (or restart) the window with one keyframe at ``stamp`` held by priors.

        velocity_map: (3,) m/s if known (e.g. from ground truth), else zero with a loose prior.
        In LiDAR-only mode the keyframe's twist starts at that velocity and zero angular rate
        (``init_sigma_rate_rad_s``); ``bias`` is not used.
        """
        import gtsam

        p = self.params
        T = np.asarray(T_map_body, dtype=np.float64)
        self._init_args = (T.copy(), float(stamp), None if velocity_map is None else np.array(velocity_map),
                           bias, sigma_vel_m_s)
        vel = np.zeros(3) if velocity_map is None else np.asarray(velocity_map, dtype=np.float64)
        if sigma_vel_m_s is None:
            sigma_vel_m_s = 0.1 if velocity_map is not None else p.init_sigma_vel_m_s
        self.window.clear()
        i = self._next_index
        self._next_index += 1
        kx, kv, kb = keys_of(i)
        values = gtsam.Values()
        values.insert(kx, gtsam.Pose3(T))
        if self.lidar_only:
            twist = motion.body_twist_from_map_velocity(T, vel)
            values.insert(kv, twist)
            self.window.add_keyframe(i, float(stamp), values)
            self.window.add_factor(pose_prior(kx, T, p.init_sigma_rot_rad, p.init_sigma_trans_m))
            self.window.add_factor(motion.twist_prior(kv, twist, p.init_sigma_rate_rad_s, sigma_vel_m_s))
        else:
            bias = bias if bias is not None else gtsam.imuBias.ConstantBias()
            values.insert(kv, vel)
            values.insert(kb, bias)
            self.window.add_keyframe(i, float(stamp), values)
            for f in state_priors(keys_of(i), T, vel, bias, p.init_sigma_rot_rad, p.init_sigma_trans_m,
                                  sigma_vel_m_s, p.init_sigma_acc_bias, p.init_sigma_gyro_bias):
                self.window.add_factor(f)
        self._last_ndt = None
        self._last_good = T.copy()
        self._last_good_motion = None
        self._recent_fitness = []
        self._bad_streak = 0
        self._lost_frames = 0

    def reset(self) -> None:
        """Forget the state: window, IMU samples, last good pose (a live stream that restarted
        with earlier stamps); ``initialize`` starts it again. Counters and the mode stay."""
        self.window.clear()
        self.imu = ImuBuffer()
        self._last_ndt = None
        self._last_good = None
        self._last_good_motion = None
        self._recent_fitness = []
        self._bad_streak = 0
        self._lost_frames = 0

    def use_lidar_only(self) -> None:
        """Go on LiDAR-only (the IMU stopped): the window restarts at the newest keyframe's pose
        and velocity as a pose + twist keyframe; later IMU samples are ignored. No-op when
        LiDAR-only already."""
        if self.lidar_only:
            return
        latest = self.window.latest
        state = self._state(latest) if latest is not None else None
        self.lidar_only = True
        if state is not None:
            nav, _ = state
            self.initialize(nav.pose().matrix(), self.window.stamps[latest], velocity_map=np.asarray(nav.velocity()))

    def insert_imu(self, t: float, acc: np.ndarray, gyro: np.ndarray) -> None:
        """One IMU sample: t seconds, acc (3,) m/s^2 specific force and gyro (3,) rad/s, imu frame.

        Ignored in LiDAR-only mode."""
        if self.lidar_only:
            return
        if self.imu.insert(t, acc, gyro):
            self._imu_seen = True

    def _decide_mode(self, index: int) -> None:
        """use_imu None, at the first frame: LiDAR-only when no IMU sample has arrived."""
        if self.lidar_only is not None:
            return
        self.lidar_only = not self._imu_seen
        if self.lidar_only:
            log.info("frame %d: no IMU sample before the first frame: LiDAR-only tracking", index)
            if self.initialized and self._init_args is not None:
                self.initialize(*self._init_args)  # the same start, as a pose + twist keyframe

    def _state(self, i: int):
        """(NavState, bias) of keyframe i; LiDAR-only: velocity R v of the twist, zero bias."""
        import gtsam

        kx, kv, kb = keys_of(i)
        v = self.window.values
        pose = v.atPose3(kx)
        if self.lidar_only:
            vel = motion.map_velocity(pose.matrix(), v.atVector(kv))
            return gtsam.NavState(pose, vel), gtsam.imuBias.ConstantBias()
        return gtsam.NavState(pose, v.atVector(kv)), v.atConstantBias(kb)

    def _gravity_body(self, T_map_body: np.ndarray | None) -> np.ndarray:
        if T_map_body is not None:
            return T_map_body[:3, :3].T @ self.gravity_map
        if self.lidar_only:  # no accelerometer: the body is taken as level in the map
            return self.gravity_map.copy()
        if len(self.imu):
            acc = np.asarray(self.imu._acc[-50:]).mean(axis=0)  # at rest the IMU reads -g
            return -(self.T_body_imu[:3, :3] @ acc)
        return np.array([0.0, 0.0, np.linalg.norm(self.gravity_map)])

    # ----------------------------------------------------------------- the frame step
    def insert_frame(self, frame: LidarFrame) -> Estimate:
        """Process one LiDAR sweep; returns the estimate at ``frame.stamp``."""
        t_start = time.perf_counter()
        p = self.params
        stamp = float(frame.stamp)
        diag = Diagnostics()
        self.counters["frames"] += 1
        self._decide_mode(frame.index)

        points, offsets = self._preprocess(frame)
        diag.num_points = len(points)

        if not self.initialized:
            est = self._start_without_pose(frame, points, stamp, diag)
            if est is not None:
                return est

        last = self.window.latest
        t_prev = self.window.stamps[last]
        state_prev, bias_prev = self._state(last)
        t_key = self._keyframe_time(stamp, offsets)
        if self.lidar_only and t_key < t_prev + 1e-4:  # the first scan after initialize(): its time
            t_key = max(t_prev, stamp)

        # 1-2. prediction over the sweep (IMU, or the last twist), deskew to the scan time.
        t0 = time.perf_counter()
        if self.lidar_only:
            T_pred, v_pred, scan_pts = self._predict_and_deskew_cv(points, offsets - (t_key - stamp), t_key,
                                                                   t_prev, last)
        else:
            T_pred, v_pred, scan_pts = self._predict_and_deskew(points, offsets, stamp, t_prev, state_prev,
                                                                bias_prev)
        diag.deskew_ms = (time.perf_counter() - t0) * 1e3
        self.last_scan_lidar = scan_pts

        # 3. the local map at the predicted position.
        t0 = time.perf_counter()
        local = self.map_provider.update(T_pred[:3, 3].copy(), v_pred.copy(), stamp)
        diag.map_ms = (time.perf_counter() - t0) * 1e3
        diag.switched = bool(getattr(local, "switched", False))
        diag.block_id = _plain(getattr(local, "block_id", getattr(local, "region_id", None)))
        if diag.switched:
            self.counters["switches"] += 1

        # 4-5. registration and its health.
        t0 = time.perf_counter()
        T_ndt, info, accepted = self._register(local, scan_pts, T_pred, diag, t_key - t_prev)
        diag.registration_ms = (time.perf_counter() - t0) * 1e3

        # 6-7. the window.
        t0 = time.perf_counter()
        k = self._add_keyframe(t_key, t_prev, last, state_prev, bias_prev, T_pred, v_pred, T_ndt, info,
                               accepted, diag)
        self.window.optimize()
        diag.marginalized = self.window.enforce_size(diag.switched, p.window_size_on_switch)
        diag.window_size = len(self.window)
        diag.smoother_ms = (time.perf_counter() - t0) * 1e3

        est_T = self.window.values.atPose3(keys_of(k)[0]).matrix()
        # 8. health bookkeeping and recovery.
        if accepted:
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
                recovered = self._try_recover(scan_pts, t_key, k, diag)
                if recovered is not None:
                    est_T = recovered
                    k = self.window.latest
        self.imu.discard_before(self.window.stamps[self.window.latest] - 1.0)

        return self._estimate(frame.index, stamp, k, diag, t_start)

    # ----------------------------------------------------------------- steps
    def _preprocess(self, frame: LidarFrame) -> tuple[np.ndarray, np.ndarray]:
        p = self.params
        pts = np.asarray(frame.points, dtype=np.float64)
        if len(pts) == 0:
            return np.zeros((0, 3)), np.zeros(0)
        ok = dsk.range_filter(pts, p.min_range_m, p.max_range_m)
        idx = np.flatnonzero(ok)
        sel = dsk.voxel_downsample_indices(pts[idx], p.voxel_size_m, p.max_points, seed=frame.index)
        idx = idx[sel]
        offsets = (np.zeros(len(idx)) if frame.time_offsets is None
                   else np.asarray(frame.time_offsets, dtype=np.float64)[idx])
        return pts[idx], offsets

    def _predict_and_deskew(self, points, offsets, stamp, t_prev, state_prev, bias_prev):
        """Predicted T_map_body and velocity at ``stamp``; the points deskewed to ``stamp``."""
        p = self.params
        if p.deskew and len(offsets) and (offsets.max() - offsets.min()) > 1e-6:
            t_lo, t_hi = stamp + offsets.min(), stamp + offsets.max()
            imu_t = np.asarray(self.imu._t)
            inner = imu_t[(imu_t > max(t_lo, t_prev)) & (imu_t < t_hi)]
            table_t = np.unique(np.concatenate([[t_lo, t_hi, stamp], inner]))
        else:
            table_t = np.array([stamp])
        poses, vels = predict_states(self.imu_params, state_prev, bias_prev, self.imu, t_prev,
                                     np.maximum(table_t, t_prev))
        ref = int(np.searchsorted(table_t, stamp))
        T_pred, v_pred = poses[ref], vels[ref]
        if len(table_t) == 1:
            return T_pred, v_pred, points
        # Constant-velocity translation (eq. 9), IMU rotation (eq. 8).
        poses = poses.copy()
        poses[:, :3, 3] = T_pred[:3, 3] + v_pred[None] * (table_t - stamp)[:, None]
        T_ref_table = dsk.lidar_motion_table(poses, self.T_body_lidar, ref)
        return T_pred, v_pred, dsk.deskew_points(points, stamp + offsets, table_t, T_ref_table)

    def _keyframe_time(self, stamp: float, offsets: np.ndarray) -> float:
        """The time a keyframe's state refers to: the frame stamp; LiDAR-only, the mean time of
        the scan's points when they have their own times.

        Why: without a gyro the twist used to deskew is estimated from the registered poses
        themselves. Deskewed to the sweep start, a twist error e turns the whole scan by about
        e x (mean point time - start), registration turns the pose back by as much, and the next
        twist estimate inherits it: measured on the small simulated world standing still, the
        rotation error doubled every two frames until the track was lost. Deskewed to the mean
        point time, a twist error only bends the scan symmetrically (no first-order change of the
        registered pose), so the loop is broken. Estimates are still reported at the stamp.
        """
        if self.lidar_only and len(offsets) and (offsets.max() - offsets.min()) > 1e-6:
            return stamp + float(offsets.mean())
        return stamp

    def _predict_and_deskew_cv(self, points, offsets, stamp, t_prev, last):
        """LiDAR-only: T_map_body predicted at ``stamp`` with keyframe ``last``'s twist, its map
        velocity, and the points (times ``stamp + offsets``) deskewed to ``stamp`` with the same
        constant twist over the sweep (when per-point times exist)."""
        v = self.window.values
        kx, kv, _ = keys_of(last)
        T_last, twist = v.atPose3(kx).matrix(), v.atVector(kv)
        T_pred = motion.predict(T_last, twist, stamp - t_prev)
        v_pred = motion.map_velocity(T_pred, twist)
        if not (self.params.deskew and len(offsets) and (offsets.max() - offsets.min()) > 1e-6):
            return T_pred, v_pred, points
        # A constant twist is a smooth curve: 9 knots over the sweep interpolate it to well
        # under a millimetre at walking and driving rates.
        rel_t = np.unique(np.r_[np.linspace(offsets.min(), offsets.max(), 9), 0.0])
        poses = motion.predict(T_pred, twist, rel_t)
        ref = int(np.searchsorted(rel_t, 0.0))
        T_ref_table = dsk.lidar_motion_table(poses, self.T_body_lidar, ref)
        return T_pred, v_pred, dsk.deskew_points(points, stamp + offsets, stamp + rel_t, T_ref_table)

    def _gates(self, dt: float) -> tuple[float, float]:
        """Innovation gates (m, deg); LiDAR-only: widened to the motion prior's uncertainty."""
        p = self.params
        if not self.lidar_only:
            return p.max_innovation_m, p.max_innovation_deg
        s_rot, s_trans = p.motion.prediction_sigma(dt)
        k = p.lidar_only_gate_sigmas
        return max(p.max_innovation_m, k * s_trans), max(p.max_innovation_deg, np.rad2deg(k * s_rot))

    def _align(self, target, scan_pts, T_guess, T_pred, gates):
        """One registration from ``T_guess``: (T_ndt, result, fitness, innovation m, deg, reject
        reason: "" when healthy)."""
        p = self.params
        res = self.registration.align(target, scan_pts, T_guess @ self.T_body_lidar)
        T_ndt = np.asarray(res.T_target_source) @ self.T_lidar_body
        fitness = float(res.fitness)
        inn_m = float(np.linalg.norm(T_ndt[:3, 3] - T_pred[:3, 3]))
        inn_deg = float(np.rad2deg(rotation_angle(T_pred[:3, :3].T @ T_ndt[:3, :3])))
        reason = reject_reason(res, fitness, inn_m, inn_deg, gates, p.min_fitness, T_ndt)
        return T_ndt, res, fitness, inn_m, inn_deg, reason

    def _count_rejection(self, diag, reason: str) -> None:
        diag.reject_reason = reason
        self.counters["rejected"] += 1
        self.counters[f"rejected_{reason}"] += 1

    def _register(self, local, scan_pts, T_pred, diag, dt: float = 0.0):
        p = self.params
        target = getattr(local, "target", None)
        if target is None or len(scan_pts) < p.min_points:
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
        ok = not reason
        if not ok and self.lidar_only:
            log.debug("registration from the prediction failed: converged %s, fitness %.2f, innovation "
                      "%.2f m %.1f deg (gates %.2f m %.1f deg)", bool(getattr(res, "converged", True)),
                      diag.fitness, diag.innovation_m, diag.innovation_deg, *gates)
            retry = self._retry_rotated(target, scan_pts, T_pred, gates, diag)
            if retry is not None:
                T_ndt, res = retry
                ok = True
        if not ok:
            diag.status = "rejected"
            self._count_rejection(diag, reason)
            return T_ndt, None, False
        info, diag.weak_dims = ndt_information(np.asarray(res.H), self.T_body_lidar, p.ndt)
        return T_ndt, info, True

    def _retry_rotated(self, target, scan_pts, T_pred, gates, diag):
        """Register from rotated predictions in turn; the first healthy (T_ndt, result), or None.

        Innovation is still measured against the real prediction, so a retry is held to the
        same gate as the prediction itself (the last estimate, a stop, against itself). A retry explores poses the motion model finds
        unlikely, and each try is one more chance of a wrong local minimum that happens to pass
        ``min_fitness`` (the floor or walls near any guess), so it must also fit about as well as
        the recent scans did (``rotation_retry_fitness_ratio``)."""
        p = self.params
        min_fit = p.min_fitness
        if self._recent_fitness:
            min_fit = max(min_fit, p.rotation_retry_fitness_ratio * float(np.median(self._recent_fitness)))
        candidates = motion.rotated_predictions(T_pred, self.gravity_map, p.rotation_retry_yaw_deg,
                                                p.rotation_retry_tilt_deg)
        if not candidates:
            return None
        # First the last estimate itself: a turn that stopped (the walk turned 43 deg, then 9 deg:
        # constant velocity predicted the second 52 deg wrong, every rotation of that was off too).
        T_last = self.window.values.atPose3(keys_of(self.window.latest)[0]).matrix()
        if np.linalg.norm(T_last[:3, 3] - T_pred[:3, 3]) > 0.05 or rotation_angle(T_last[:3, :3].T @ T_pred[:3, :3]) > np.deg2rad(2.0):
            candidates.insert(0, ("stop", T_last))
        self.counters["rotation_retries"] += 1
        for label, T_guess in candidates:
            diag.rotation_retries += 1
            # a stop is a motion hypothesis of its own: gated against itself, not the prediction
            T_ref = T_guess if label == "stop" else T_pred
            try:
                T_ndt, res, fit, inn_m, inn_deg, reason = self._align(target, scan_pts, T_guess, T_ref, gates)
                ok = not reason
            except Exception as exc:
                log.debug("rotated prediction %s: registration failed: %s", label, exc)
                continue
            if ok and fit >= min_fit:
                self.counters["rotation_recoveries"] += 1
                diag.rotation_retry = label
                diag.fitness, diag.innovation_m, diag.innovation_deg = fit, inn_m, inn_deg
                log.info("registration from the prediction failed; rotated prediction %s fits (%.2f)",
                         label, fit)
                return T_ndt, res
        return None

    def _add_keyframe(self, stamp, t_prev, last, state_prev, bias_prev, T_pred, v_pred, T_ndt, info,
                      accepted, diag) -> int:
        import gtsam

        p = self.params
        dt = stamp - t_prev
        if dt < 1e-4:
            # Same time as the newest keyframe (the first scan after initialization): the NDT
            # factor goes on that keyframe, no new state.
            k = last
        else:
            k = self._next_index
            self._next_index += 1
            kx, kv, kb = keys_of(k)
            px, pv, pb = keys_of(last)
            values = gtsam.Values()
            values.insert(kx, gtsam.Pose3(T_ndt if accepted else T_pred))
            if self.lidar_only:
                # Initial twist: the motion that brings the last keyframe to the registered pose.
                T_last = self.window.values.atPose3(px).matrix()
                values.insert(kv, motion.twist_between(T_last, T_ndt, dt) if accepted
                              else self.window.values.atVector(pv))
                self.window.add_keyframe(k, stamp, values)
                self.window.add_factor(motion.constant_velocity_factor(px, pv, kx, kv, dt, p.motion))
            else:
                pim = gtsam.PreintegratedCombinedMeasurements(self.imu_params, bias_prev)
                diag.imu_gap_s = integrate(pim, self.imu, t_prev, stamp)
                values.insert(kv, v_pred)
                values.insert(kb, bias_prev)
                self.window.add_keyframe(k, stamp, values)
                self.window.add_factor(gtsam.CombinedImuFactor(px, pv, kx, kv, pb, kb, pim))
        if accepted:
            kx = keys_of(k)[0]
            self.window.add_factor(ndt_factor(kx, T_ndt, info, p.ndt.huber_k))
            if p.use_odometry_factor and self._last_ndt is not None and self._last_ndt[0] != k \
                    and self._last_ndt[0] in self.window.stamps:
                j, T_j = self._last_ndt
                self.window.add_factor(odometry_factor(keys_of(j)[0], kx, inv_T(T_j) @ T_ndt,
                                                       p.odometry_sigma_rot_rad, p.odometry_sigma_trans_m,
                                                       p.ndt.huber_k))
            self._last_ndt = (k, T_ndt)
        return k

    def _start_without_pose(self, frame, points, stamp, diag) -> Estimate | None:
        """No pose yet: relocalize over the whole map, or report 'uninitialized'."""
        if self.relocalize is None:
            raise TrackingError("tracker has no initial pose: call initialize() or give a relocalizer")
        T = None
        if len(points) >= self.params.min_points:
            T = self.relocalize(points, None, self._gravity_body(None), stamp)
        if T is None:
            diag.status = "uninitialized"
            diag.update_ms = 0.0
            return Estimate(frame.index, stamp, None, None, np.zeros(3), np.zeros(3), np.zeros(3), diag)
        log.info("frame %d: initialized by global localization at %s", frame.index, np.round(T[:3, 3], 2))
        self.initialize(T, stamp)
        return None

    def _try_recover(self, scan_pts, stamp, k, diag) -> np.ndarray | None:
        """Relocalize around the last good pose; on success restart the window there."""
        p = self.params
        if self.relocalize is None or len(scan_pts) < p.min_points:
            return None
        if (self._bad_streak - p.max_bad_frames) % max(1, p.relocalize_every) != 0:
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
        # The diverged state's velocity and biases are not to be trusted (seen: 6 m/s and 0.9 m/s^2
        # of accelerometer bias after a kidnapped start). Restart from the last accepted keyframe's:
        # its velocity in the body frame turned into the relocalized pose (a robot drives on the
        # way it faces; zero instead made the next scans 0.25-0.35 m off, reported ok: the
        # prediction and the deskew of the first scans a whole speed wrong), held loosely, and its
        # biases (they change slowly); zero velocity and the initial bias prior without one.
        v_body, bias = self._last_good_motion if self._last_good_motion is not None else (np.zeros(3), None)
        self.initialize(T, stamp, velocity_map=T[:3, :3] @ v_body, bias=bias,
                        sigma_vel_m_s=p.recover_sigma_vel_m_s)
        # The next scan registers against the map where the robot is now, not where it was.
        relocate = getattr(self.map_provider, "relocate", None)
        if relocate is not None:
            local = relocate(T[:3, 3].copy(), T[:3, :3] @ v_body, stamp)
            diag.block_id = _plain(getattr(local, "block_id", getattr(local, "region_id", None)))
        self.window.optimize()
        diag.status = "recovered"
        diag.window_size = len(self.window)
        return T

    def _estimate(self, index, stamp, k, diag, t_start) -> Estimate:
        state, bias = self._state(k)
        kx, kv, _ = keys_of(k)
        tau = stamp - self.window.stamps[k]
        moved = self.lidar_only and abs(tau) > 1e-9  # keyframe at the scan's mean point time
        if moved:
            import gtsam

            twist = self.window.values.atVector(kv)
            T = motion.predict(state.pose().matrix(), twist, tau)
            state = gtsam.NavState(gtsam.Pose3(T), motion.map_velocity(T, twist))
        cov = None
        if self.params.compute_covariance:
            try:
                if moved:  # first-order propagation of (pose, twist) to the stamp
                    J = np.hstack(motion.extrapolation_jacobians(twist, tau))
                    cov = J @ self.window.joint_covariance([kx, kv]) @ J.T
                else:
                    cov = self.window.covariance(kx)
            except RuntimeError as exc:  # an indeterminant system: report, do not crash
                log.debug("no covariance: %s", exc)
        diag.update_ms = (time.perf_counter() - t_start) * 1e3
        return Estimate(index, stamp, state.pose().matrix(), cov, np.asarray(state.velocity()),
                        np.asarray(bias.accelerometer()), np.asarray(bias.gyroscope()), diag)


def _plain(x):
    """A JSON-friendly copy of a block / region id."""
    if x is None or isinstance(x, (int, str, float)):
        return x
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (tuple, list)):
        return [_plain(v) for v in x]
    return str(x)
