"""SE(3) helpers on numpy arrays.

Conventions: a transform ``T_a_b`` (4, 4) maps points in frame b to frame a: ``p_a = T_a_b @ p_b``.
Euler angles are roll, pitch, yaw in radians with R = Rz(yaw) @ Ry(pitch) @ Rx(roll), the
convention of NCLT's ground truth and of ROS's ``rpy``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def up_from_gravity(gravity: np.ndarray) -> np.ndarray:
    """(3,) unit vector against ``gravity`` (3,), in its frame (a z-down map's: -z)."""
    g = np.asarray(gravity, np.float64).reshape(3)
    return -g / np.linalg.norm(g)


def tangent_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (3,) unit vectors e1, e2 spanning the plane normal to the unit vector ``up`` (3,), with
    (e1, e2, up) right-handed."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(3, 3) rotation and (3,) translation -> (4, 4) transform."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of one (4, 4) or a stack (N, 4, 4) of rigid transforms."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (N, 3) points; returns float64 (N, 3)."""
    pts = np.asarray(points, dtype=np.float64)
    return pts @ T[:3, :3].T + T[:3, 3]


def rpy_to_R(roll, pitch, yaw) -> np.ndarray:
    """Roll, pitch, yaw (radians, scalars or (N,) arrays) -> (3, 3) or (N, 3, 3), R = Rz Ry Rx."""
    roll, pitch, yaw = np.broadcast_arrays(np.asarray(roll, float), np.asarray(pitch, float),
                                           np.asarray(yaw, float))
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    R = np.empty(roll.shape + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def R_to_rpy(R: np.ndarray) -> np.ndarray:
    """(3, 3) or (N, 3, 3) rotation -> (3,) or (N, 3) roll, pitch, yaw in radians (R = Rz Ry Rx)."""
    R = np.asarray(R, dtype=np.float64)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def xyzrpy_to_T(x, y, z, roll, pitch, yaw) -> np.ndarray:
    """Position (m) and roll/pitch/yaw (rad) -> (4, 4), or (N, 4, 4) for array inputs."""
    R = rpy_to_R(roll, pitch, yaw)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., 0, 3] = x
    T[..., 1, 3] = y
    T[..., 2, 3] = z
    T[..., 3, 3] = 1.0
    return T


def T_to_xyzrpy(T: np.ndarray) -> np.ndarray:
    """(4, 4) or (N, 4, 4) -> (6,) or (N, 6) as x, y, z (m), roll, pitch, yaw (rad)."""
    return np.concatenate([T[..., :3, 3], R_to_rpy(T[..., :3, :3])], axis=-1)


def skew(v: np.ndarray) -> np.ndarray:
    """(3,) vector -> (3, 3) skew-symmetric matrix with skew(v) @ w = v x w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation vector(s) (3,) or (N, 3), radians -> rotation matrix (3, 3) or (N, 3, 3)."""
    w = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    A = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    B = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + A * K + B * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) or (N, 3, 3) -> rotation vector (3,) or (N, 3), radians."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    return Rotation.from_matrix(R).as_rotvec()


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices (3, 3) or (N, 3, 3)."""
    tr = np.trace(R, axis1=-2, axis2=-1)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def covariance_to_ros(cov_tangent: np.ndarray, R_map_body: np.ndarray) -> np.ndarray:
    """(6, 6) Pose3 tangent covariance (rot, trans; body frame, right perturbation) -> ROS order.

    ROS's ``PoseWithCovariance`` holds (x, y, z, rotation about X, Y, Z) in the header's frame
    (``map``). With ``T = T_hat Exp([w, v])`` the position moves by ``R v`` and the orientation by
    the rotation vector ``R w`` about the map's fixed axes (first order), so the ROS covariance
    is ``J P J^T`` with ``J = [[0, R], [R, 0]]``. Returns (6, 6) float64.
    """
    R = np.asarray(R_map_body, dtype=np.float64)
    J = np.zeros((6, 6))
    J[:3, 3:] = R
    J[3:, :3] = R
    out = J @ np.asarray(cov_tangent, dtype=np.float64) @ J.T
    return 0.5 * (out + out.T)


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    """(3, 3) or (N, 3, 3) rotation -> (4,) or (N, 4) unit quaternion x, y, z, w (w >= 0)."""
    R = np.asarray(R, dtype=np.float64)
    if R.ndim == 3:
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(R).as_quat()
        return q * np.where(q[:, 3:] < 0, -1.0, 1.0)
    return _quat_one(R)


def _quat_one(R: np.ndarray) -> np.ndarray:
    """One (3, 3) rotation -> (4,) x, y, z, w with w >= 0. Shepperd's method on the largest of
    w, x, y, z; numpy scalars because scipy's Rotation costs ~0.3 ms a call, too much per frame."""
    m00, m01, m02 = R[0]
    m10, m11, m12 = R[1]
    m20, m21, m22 = R[2]
    tr = m00 + m11 + m22
    if tr >= max(m00, m11, m22):
        w = 0.5 * math.sqrt(max(1.0 + tr, 0.0))
        x, y, z = (m21 - m12) / (4 * w), (m02 - m20) / (4 * w), (m10 - m01) / (4 * w)
    elif m00 >= m11 and m00 >= m22:
        x = 0.5 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        w, y, z = (m21 - m12) / (4 * x), (m01 + m10) / (4 * x), (m02 + m20) / (4 * x)
    elif m11 >= m22:
        y = 0.5 * math.sqrt(max(1.0 - m00 + m11 - m22, 0.0))
        w, x, z = (m02 - m20) / (4 * y), (m01 + m10) / (4 * y), (m12 + m21) / (4 * y)
    else:
        z = 0.5 * math.sqrt(max(1.0 - m00 - m11 + m22, 0.0))
        w, x, y = (m10 - m01) / (4 * z), (m02 + m20) / (4 * z), (m12 + m21) / (4 * z)
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def lever_arm_scaling(H: np.ndarray) -> np.ndarray:
    """(6,) d with xi = d * xi': the pose tangent (rotation first, rad; translation, m) rescaled so
    its six coordinates share one unit, rotation times the residuals' lever arm L. A rotation by
    1 rad moves the residuals as much as a translation by L metres, on average:
    L^2 = tr(H_rot) / tr(H_trans) of the (6, 6) cost Hessian ``H`` (1 m when either is not positive).
    Compared raw, rad^-2 against m^-2, eigenvalues of H mix units; those of H * outer(d, d) do not."""
    h_rot, h_trans = float(np.trace(H[:3, :3])), float(np.trace(H[3:, 3:]))
    lever_m = np.sqrt(h_rot / h_trans) if h_rot > 0 and h_trans > 0 else 1.0
    return np.r_[np.full(3, 1.0 / lever_m), np.ones(3)]


@dataclass
class Trajectory:
    """Time-stamped poses.

    stamps: (N,) float64 seconds, strictly increasing.
    poses: (N, 4, 4) float64, ``T_map_frame`` for whatever frame the producer states
    (ground truth: the dataset's body frame).
    """

    stamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.stamps) != len(self.poses):
            raise ValueError(f"{len(self.stamps)} stamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) translations."""
        return self.poses[:, :3, 3]

    def interpolate(self, t: np.ndarray) -> np.ndarray:
        """Poses at times t (M,) -> (M, 4, 4): linear in translation, slerp in rotation.

        Times outside [stamps[0], stamps[-1]] are clamped to the ends.
        """
        from scipy.spatial.transform import Rotation, Slerp

        t = np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), self.stamps[0], self.stamps[-1])
        if len(self) == 1:
            return np.repeat(self.poses[:1], len(t), axis=0)
        # only the poses around the times asked for: a whole drive's ground truth at 100 Hz has
        # ~500k poses, and a Slerp over all of them cost seconds per call (a player publishing the
        # truth with every scan fell minutes behind on a campus session)
        lo = max(int(np.searchsorted(self.stamps, t.min(), side="right")) - 1, 0)
        hi = min(int(np.searchsorted(self.stamps, t.max(), side="left")) + 1, len(self))
        hi = min(max(hi, lo + 2), len(self))  # Slerp wants two poses at least
        lo = max(min(lo, hi - 2), 0)
        stamps, poses = self.stamps[lo:hi], self.poses[lo:hi]
        slerp = Slerp(stamps, Rotation.from_matrix(poses[:, :3, :3]))
        out = np.zeros((len(t), 4, 4))
        out[:, :3, :3] = slerp(t).as_matrix()
        for k in range(3):
            out[:, k, 3] = np.interp(t, stamps, poses[:, k, 3])
        out[:, 3, 3] = 1.0
        return out

    def path_length(self) -> float:
        """Length (m) of the polyline through the positions."""
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())
