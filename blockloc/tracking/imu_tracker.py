"""The IMU estimator: keyframes hold pose, velocity and IMU biases, linked by a
CombinedImuFactor (preintegration, Forster et al.); the prediction and the deskew come from the
IMU (rotation from the gyro, eq. 8; translation at constant velocity, eq. 9).
"""

from __future__ import annotations

import numpy as np

from blockloc import deskew as dsk
from blockloc.geometry import inv_T
from blockloc.tracking.estimator import Estimator
from blockloc.tracking.factors import state_priors
from blockloc.tracking.imu import ImuBuffer, ImuNoise, integrate, make_preintegration_params, predict_states
from blockloc.tracking.window import keys_of


class ImuTracker(Estimator):
    """Tracker with IMU preintegration; ``T_body_imu`` (4, 4) places the IMU on the body."""

    lidar_only = False

    def __init__(self, *, T_body_imu: np.ndarray, imu_noise: ImuNoise = ImuNoise(), **kwargs) -> None:
        super().__init__(**kwargs)
        self.T_body_imu = np.asarray(T_body_imu, dtype=np.float64)
        self.imu_params = make_preintegration_params(self.gravity_map, self.T_body_imu, imu_noise,
                                                     self.params.imu_noise_inflation)
        self.imu = ImuBuffer()

    def insert_imu(self, t: float, acc: np.ndarray, gyro: np.ndarray) -> None:
        self.imu.insert(t, acc, gyro)

    def reset(self) -> None:
        """Forget the state and the IMU samples held (their stamps are from before the restart)."""
        super().reset()
        self.imu = ImuBuffer()

    def without_imu(self) -> Estimator:
        """A :class:`LidarOnlyTracker` restarted at the newest keyframe's pose and velocity."""
        from blockloc.tracking.lidar_only import LidarOnlyTracker

        return LidarOnlyTracker.continuing(self)

    def _start_keyframe(self, i, T, stamp, vel, bias, sigma_vel_m_s) -> None:
        import gtsam

        f = self.settings.fixed
        kx, kv, kb = keys_of(i)
        bias = bias if bias is not None else gtsam.imuBias.ConstantBias()
        values = gtsam.Values()
        values.insert(kx, gtsam.Pose3(T))
        values.insert(kv, vel)
        values.insert(kb, constant_bias=bias)
        self.window.add_keyframe(i, stamp, values)
        for factor in state_priors(keys_of(i), T, vel, bias, f.init_sigma_rot_rad, f.init_sigma_trans_m,
                                   sigma_vel_m_s, f.init_sigma_acc_bias, f.init_sigma_gyro_bias):
            self.window.add_factor(factor)

    def _state(self, i: int):
        import gtsam

        kx, kv, kb = keys_of(i)
        v = self.window.values
        return gtsam.NavState(v.atPose3(kx), v.atVector(kv)), v.atConstantBias(kb)

    def _gravity_unknown_pose(self) -> np.ndarray:
        if len(self.imu):
            acc = np.asarray(self.imu._acc[-50:]).mean(axis=0)  # at rest the IMU reads -g
            return -(self.T_body_imu[:3, :3] @ acc)
        return np.array([0.0, 0.0, np.linalg.norm(self.gravity_map)])

    def _predict_and_deskew(self, points, offsets, stamp, t_key, t_prev, last):
        """Predicted T_map_body and velocity at ``stamp`` (= ``t_key``); the points deskewed to it."""
        state_prev, bias_prev = self._state(last)
        if self.settings.scan.deskew and len(offsets) and (offsets.max() - offsets.min()) > 1e-6:
            t_lo, t_hi = stamp + offsets.min(), stamp + offsets.max()
            imu_t = self.imu.arrays()[0]
            inner = imu_t[(imu_t > max(t_lo, t_prev)) & (imu_t < t_hi)]
            table_t = np.unique(np.concatenate([[t_lo, t_hi, stamp], inner]))
        else:
            table_t = np.array([stamp])
        # The first scan after a (re)start stamped at its sweep's end: the sweep lies before the
        # keyframe, and propagating forward from it would leave the scan without its rotation
        # (seen: the first pose 0.13 m off at 5 m/s). Propagated from the sweep's start instead
        # and anchored at the keyframe (the relative motion is the IMU's between the times).
        early = table_t[0] < t_prev - 1e-9 and abs(stamp - t_prev) < 1e-4
        t_from = float(table_t[0]) if early else t_prev
        poses, vels = predict_states(self.imu_params, state_prev, bias_prev, self.imu, t_from,
                                     np.maximum(table_t, t_from))
        ref = int(np.searchsorted(table_t, stamp))
        if early:
            poses = state_prev.pose().matrix() @ inv_T(poses[ref]) @ poses
            vels = np.broadcast_to(np.asarray(state_prev.velocity()), vels.shape)
        T_pred, v_pred = poses[ref], vels[ref]
        if len(table_t) == 1:
            return T_pred, v_pred, points
        # Constant-velocity translation (eq. 9), IMU rotation (eq. 8).
        poses = poses.copy()
        poses[:, :3, 3] = T_pred[:3, 3] + v_pred[None] * (table_t - stamp)[:, None]
        T_ref_table = dsk.lidar_motion_table(poses, self.T_body_lidar, ref)
        return T_pred, v_pred, dsk.deskew_points(points, stamp + offsets, table_t, T_ref_table)

    def _link_keyframe(self, k, last, t_prev, stamp, values, T_pred, v_pred, T_ndt, accepted, diag) -> None:
        import gtsam

        _, bias_prev = self._state(last)
        kx, kv, kb = keys_of(k)
        px, pv, pb = keys_of(last)
        pim = gtsam.PreintegratedCombinedMeasurements(self.imu_params, bias_prev)
        diag.imu_gap_s = integrate(pim, self.imu, t_prev, stamp)
        values.insert(kv, v_pred)
        # by keyword: positionally pybind tries 43 other overloads first (measured 160 us against 55)
        values.insert(kb, constant_bias=bias_prev)
        self.window.add_keyframe(k, stamp, values)
        self.window.add_factor(gtsam.CombinedImuFactor(px, pv, kx, kv, pb, kb, pim))

    def _after_frame(self) -> None:
        self.imu.discard_before(self.window.stamps[self.window.latest] - 1.0)
