"""The LiDAR-only estimator: keyframes hold a pose and a body twist (``blockloc.tracking.motion``)
instead of pose, velocity and biases; IMU samples are ignored.

The prediction uses the last twist (constant velocity on SE(3)), the deskew the same constant
twist over the sweep, and keyframes are linked by the constant-velocity factor (noise from
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
"""

from __future__ import annotations

import logging

import numpy as np

from blockloc import deskew as dsk
from blockloc.geometry import rotation_angle
from blockloc.tracking import motion
from blockloc.tracking.estimator import Estimator
from blockloc.tracking.factors import pose_prior
from blockloc.tracking.window import keys_of

log = logging.getLogger(__name__)


def _has_point_times(offsets: np.ndarray) -> bool:
    return bool(len(offsets) and (offsets.max() - offsets.min()) > 1e-6)


class LidarOnlyTracker(Estimator):
    """Tracker with a constant-velocity motion prior in place of an IMU."""

    lidar_only = True

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.motion_noise = self.params.motion_noise()

    @classmethod
    def continuing(cls, other: Estimator) -> "LidarOnlyTracker":
        """A LiDAR-only tracker going on from ``other`` (an estimator whose IMU stopped): the
        same collaborators, settings and counters, its window restarted at ``other``'s newest
        keyframe as a pose + twist keyframe (pose and map velocity of that state, at its stamp);
        uninitialized when ``other`` was."""
        new = cls(map_provider=other.map_provider, registration=other.registration,
                  T_body_lidar=other.T_body_lidar, gravity_map=other.gravity_map, settings=other.settings,
                  relocalize=other.relocalize)
        new.counters = other.counters
        new._next_index = other._next_index
        new.last_scan_lidar = other.last_scan_lidar
        latest = other.window.latest
        if latest is not None:
            nav, _ = other._state(latest)
            new.initialize(nav.pose().matrix(), other.window.stamps[latest], velocity_map=np.asarray(nav.velocity()))
        return new

    def without_imu(self) -> "LidarOnlyTracker":
        return self

    def insert_imu(self, t: float, acc: np.ndarray, gyro: np.ndarray) -> None:
        """Ignored: this estimator uses no IMU."""

    def _start_keyframe(self, i, T, stamp, vel, bias, sigma_vel_m_s) -> None:
        """The twist starts at ``vel`` and zero angular rate (``init_sigma_rate_rad_s``); ``bias``
        is not used."""
        import gtsam

        f = self.settings.fixed
        kx, kv, _ = keys_of(i)
        twist = motion.body_twist_from_map_velocity(T, vel)
        values = gtsam.Values()
        values.insert(kx, gtsam.Pose3(T))
        values.insert(kv, twist)
        self.window.add_keyframe(i, stamp, values)
        self.window.add_factor(pose_prior(kx, T, f.init_sigma_rot_rad, f.init_sigma_trans_m))
        self.window.add_factor(motion.twist_prior(kv, twist, self.params.init_sigma_rate_rad_s, sigma_vel_m_s))

    def _start_rate(self, i: int, rate_body: np.ndarray) -> None:
        kv = keys_of(i)[1]
        twist = np.array(self.window.values.atVector(kv), dtype=np.float64)
        twist[:3] = rate_body
        self.window.values.update(kv, twist)

    def _state(self, i: int):
        """(NavState with velocity R v of the twist, zero bias)."""
        import gtsam

        kx, kv, _ = keys_of(i)
        v = self.window.values
        pose = v.atPose3(kx)
        vel = motion.map_velocity(pose.matrix(), v.atVector(kv))
        return gtsam.NavState(pose, vel), gtsam.imuBias.ConstantBias()

    def _gravity_unknown_pose(self) -> np.ndarray:
        return self.gravity_map.copy()  # no accelerometer: the body is taken as level in the map

    def _keyframe_time(self, stamp: float, offsets: np.ndarray, t_prev: float) -> float:
        """The mean time of the scan's points when they have their own times, else the stamp.

        Why: without a gyro the twist used to deskew is estimated from the registered poses
        themselves. Deskewed to the sweep start, a twist error e turns the whole scan by about
        e x (mean point time - start), registration turns the pose back by as much, and the next
        twist estimate inherits it: measured on the small simulated world standing still, the
        rotation error doubled every two frames until the track was lost. Deskewed to the mean
        point time, a twist error only bends the scan symmetrically (no first-order change of the
        registered pose), so the loop is broken. Estimates are still reported at the stamp.
        """
        t_key = stamp + float(offsets.mean()) if _has_point_times(offsets) else stamp
        if t_key < t_prev + 1e-4:  # the first scan after initialize(): its time
            t_key = max(t_prev, stamp)
        return t_key

    def _predict_and_deskew(self, points, offsets, stamp, t_key, t_prev, last):
        """T_map_body predicted at ``t_key`` with keyframe ``last``'s twist, its map velocity, and
        the points deskewed to ``t_key`` with the same constant twist over the sweep (when
        per-point times exist)."""
        offsets = offsets - (t_key - stamp)  # relative to the keyframe time
        v = self.window.values
        kx, kv, _ = keys_of(last)
        T_last, twist = v.atPose3(kx).matrix(), v.atVector(kv)
        T_pred = motion.predict(T_last, twist, t_key - t_prev)
        v_pred = motion.map_velocity(T_pred, twist)
        if not (self.settings.scan.deskew and _has_point_times(offsets)):
            return T_pred, v_pred, points
        # A constant twist is a smooth curve: 9 knots over the sweep interpolate it to well
        # under a millimetre at walking and driving rates.
        rel_t = np.unique(np.r_[np.linspace(offsets.min(), offsets.max(), 9), 0.0])
        poses = motion.predict(T_pred, twist, rel_t)
        ref = int(np.searchsorted(rel_t, 0.0))
        T_ref_table = dsk.lidar_motion_table(poses, self.T_body_lidar, ref)
        return T_pred, v_pred, dsk.deskew_points(points, t_key + offsets, t_key + rel_t, T_ref_table)

    def _gates(self, dt: float) -> tuple[float, float]:
        """Widened to the motion prior's uncertainty over ``dt``."""
        p = self.params
        s_rot, s_trans = self.motion_noise.prediction_sigma(dt)
        k = p.lidar_only_gate_sigmas
        return max(p.max_innovation_m, k * s_trans), max(p.max_innovation_deg, np.rad2deg(k * s_rot))

    def _retry(self, target, scan_pts, T_pred, gates, diag, res):
        """Register from rotated predictions in turn; the first healthy (T_ndt, result), or None.

        Innovation is still measured against the real prediction, so a retry is held to the
        same gate as the prediction itself (the last estimate, a stop, against itself). A retry
        explores poses the motion model finds unlikely, and each try is one more chance of a wrong
        local minimum that happens to pass ``min_fitness`` (the floor or walls near any guess), so
        it must also fit about as well as the recent scans did (``rotation_retry_fitness_ratio``)."""
        p = self.params
        log.debug("registration from the prediction failed: converged %s, fitness %.2f, innovation "
                  "%.2f m %.1f deg (gates %.2f m %.1f deg)", bool(getattr(res, "converged", True)),
                  diag.fitness, diag.innovation_m, diag.innovation_deg, *gates)
        min_fit = p.min_fitness
        if self._recent_fitness:
            min_fit = max(min_fit, p.rotation_retry_fitness_ratio * float(np.median(self._recent_fitness)))
        candidates = motion.rotated_predictions(T_pred, self.gravity_map, tuple(p.rotation_retry_yaw_deg),
                                                tuple(p.rotation_retry_tilt_deg))
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

    def _link_keyframe(self, k, last, t_prev, stamp, values, T_pred, v_pred, T_ndt, accepted, diag) -> None:
        kx, kv, _ = keys_of(k)
        px, pv, _ = keys_of(last)
        dt = stamp - t_prev
        # Initial twist: the motion that brings the last keyframe to the registered pose.
        T_last = self.window.values.atPose3(px).matrix()
        values.insert(kv, motion.twist_between(T_last, T_ndt, dt) if accepted
                      else self.window.values.atVector(pv))
        self.window.add_keyframe(k, stamp, values)
        self.window.add_factor(motion.constant_velocity_factor(px, pv, kx, kv, dt, self.motion_noise))

    def _pose_at_stamp(self, k: int, state, tau: float):
        """The keyframe sits at the scan's mean point time: pose carried to the stamp with its
        twist, covariance by first-order propagation of (pose, twist)."""
        if abs(tau) <= 1e-9:
            return super()._pose_at_stamp(k, state, tau)
        import gtsam

        kx, kv, _ = keys_of(k)
        twist = self.window.values.atVector(kv)
        T = motion.predict(state.pose().matrix(), twist, tau)
        state = gtsam.NavState(gtsam.Pose3(T), motion.map_velocity(T, twist))

        frozen = self.window.frozen()

        def propagated():
            J = np.hstack(motion.extrapolation_jacobians(twist, tau))
            return J @ frozen.joint_covariance([kx, kv]) @ J.T

        return state, self._covariance(propagated)
