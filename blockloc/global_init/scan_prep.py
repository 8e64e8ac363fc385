"""One preparation of a scan for global localization: deskew, body frame, gravity.

``blockloc init``, a tracking start from a hint and a no-hint start all call
:func:`prepare_for_init`, so they see the same points at the same time with the same gravity.

Without a pose the velocity is unknown, so only the rotation during the sweep (integrated from
the gyro, bias neglected: ~0.002 rad/s x 0.1 s) is removed; at a turn in place it moves far points
by metres, while the unknown translation is at most speed x sweep time (~0.15 m). The result is
stamped at the middle of the sweep: the pose a rigid registration finds for a scan taken while
moving is the pose at mid-sweep (NCLT and simulated stamps are the sweep start: ~0.065 m apart at
1.3 m/s). Gravity comes from the accelerometer within +-0.25 s of that time; a sequence without an
IMU levels the scan by its own floor plane (:func:`blockloc.global_init.level.gravity_from_scan`,
assuming the body is within 45 degrees of upright in the map's sense of up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.datasets.base import ImuData, LidarFrame, SequenceInfo
from blockloc.errors import GlobalInitError
from blockloc.geometry import inv_T, so3_exp, so3_log, transform_points

IMU_HALF_WINDOW_S = 0.25


@dataclass
class InitScan:
    """A scan ready for global localization.

    points_body: (N, 3) float64, body frame at ``stamp``, metres. stamp: s (mid-sweep).
    gravity_body: (3,) gravity vector in the body frame, m/s^2.
    """

    points_body: np.ndarray
    stamp: float
    gravity_body: np.ndarray


def gravity_from_imu(imu: ImuData, stamp: float, T_body_imu: np.ndarray) -> np.ndarray:
    """Gravity (3,) in the body frame, m/s^2, from the accelerometer within +-0.25 s of ``stamp``
    (the nearest 50 samples when none lie that close, e.g. before the IMU starts)."""
    from blockloc.global_init.projection import gravity_body_from_imu

    if imu is None or len(imu) == 0:
        raise GlobalInitError("no IMU data to level the scan")
    near = imu.between(stamp - IMU_HALF_WINDOW_S, stamp + IMU_HALF_WINDOW_S)
    if len(near) == 0:
        i = int(np.clip(np.searchsorted(imu.t, stamp), 0, len(imu) - 1))
        near = imu.between(imu.t[max(i - 25, 0)], imu.t[min(i + 25, len(imu) - 1)] + 1e-9)
    return gravity_body_from_imu(near.acc, T_body_imu)


def deskew_rotation(frame: LidarFrame, imu: ImuData, info: SequenceInfo) -> tuple[np.ndarray, float]:
    """Frame points (N, 3) in the BODY frame at mid-sweep, rotation-deskewed with the gyro, and
    that time (s). Frames without per-point times (or without IMU samples over the sweep) are
    only transformed into the body frame."""
    from blockloc.deskew import deskew_points_numpy

    pts = np.asarray(frame.points, dtype=np.float64)
    T_bl = np.asarray(info.T_body_lidar, dtype=np.float64)
    if frame.time_offsets is None or len(pts) == 0:
        return transform_points(T_bl, pts), float(frame.stamp)
    offs = np.asarray(frame.time_offsets, dtype=np.float64)
    t_ref = float(frame.stamp + 0.5 * (offs.min() + offs.max()))
    t0, t1 = frame.stamp + offs.min(), frame.stamp + offs.max()
    near = imu.between(t0 - 0.02, t1 + 0.02) if imu is not None and len(imu) else None
    if near is None or len(near) < 2 or t1 <= t0:
        return transform_points(T_bl, pts), t_ref
    omega_body = near.gyro @ np.asarray(info.T_body_imu, dtype=np.float64)[:3, :3].T
    times = np.concatenate([[t0], near.t[(near.t > t0) & (near.t < t1)], [t1]])
    idx = np.clip(np.searchsorted(near.t, times, side="right") - 1, 0, len(near) - 1)
    R = [np.eye(3)]
    for k in range(1, len(times)):  # zero-order hold of the rate over each interval
        R.append(R[-1] @ so3_exp(omega_body[idx[k - 1]] * (times[k] - times[k - 1])))
    R = np.array(R)
    R_ref = _interp_rotation(times, R, t_ref)
    T_body_table = np.zeros((len(times), 4, 4))
    T_body_table[:, :3, :3] = R_ref.T[None] @ R  # body at each table time, relative to t_ref
    T_body_table[:, 3, 3] = 1.0
    T_lidar_table = inv_T(T_bl)[None] @ T_body_table @ T_bl[None]
    lidar = deskew_points_numpy(pts, frame.stamp + offs, times, T_lidar_table)
    return transform_points(T_bl, lidar), t_ref


def gravity_from_scan_points(points_body: np.ndarray, gravity_map: np.ndarray) -> np.ndarray:
    """Gravity (3,) in the body frame, m/s^2, from the scan's floor plane (no IMU)."""
    from blockloc.global_init.level import gravity_from_scan, up_hint_from_gravity_map

    est = gravity_from_scan(points_body, up_hint=up_hint_from_gravity_map(gravity_map))
    return est.direction * float(np.linalg.norm(gravity_map))


def prepare_for_init(frame: LidarFrame, imu: ImuData, info: SequenceInfo) -> InitScan:
    """The scan of ``frame`` deskewed into the body frame at mid-sweep, with gravity there (from
    the accelerometer, or from the scan's floor when the sequence has no IMU)."""
    points_body, stamp = deskew_rotation(frame, imu, info)
    if imu is None or len(imu) == 0:
        return InitScan(points_body, stamp, gravity_from_scan_points(points_body, info.gravity_map))
    return InitScan(points_body, stamp, gravity_from_imu(imu, stamp, info.T_body_imu))


def _interp_rotation(times: np.ndarray, R: np.ndarray, t: float) -> np.ndarray:
    """Rotation at time t from a table (K,) times and (K, 3, 3) rotations (slerp in one interval)."""
    j = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2))
    span = times[j + 1] - times[j]
    a = (t - times[j]) / span if span > 0 else 0.0
    return R[j] @ so3_exp(a * so3_log(R[j].T @ R[j + 1]))
