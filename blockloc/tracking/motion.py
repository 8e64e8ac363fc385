"""LiDAR-only motion model: constant velocity on SE(3) between keyframes, and rotated predictions.

Without an IMU each keyframe i carries, besides its pose ``X(i)`` = T_map_body, a body-frame twist
``V(i)`` = (omega rad/s, v m/s) (6,), GTSAM Pose3 tangent order (rotation first). The body moves
with a constant twist between keyframes, disturbed by white-noise acceleration (the "white noise
on acceleration" Gaussian-process prior of Barfoot / Anderson, "Full STEAM ahead"), so for
keyframes i, j, dt = t_j - t_i apart the factor's error (12,) is

    e = [ Log(X_i^-1 X_j) - dt V_i ;  V_j - V_i ]

with covariance  Q(dt) = [[dt^3/3 Qc, dt^2/2 Qc], [dt^2/2 Qc, dt Qc]],
Qc = diag(sigma_rot^2 I3, sigma_trans^2 I3): sigma_rot in rad/s^2/sqrt(s) (= rad/s^1.5),
sigma_trans in m/s^2/sqrt(s). The noise grows with the gap, so the same settings serve 10 Hz
sweeps and 2 Hz keyframes. (The exact GP prior puts J_r^-1(Log X_i^-1 X_j) on V_j; the
constant-twist error here is zero for exactly the same trajectories, a constant body twist, and
the difference is second order in the twist change.)

A velocity state was chosen over a three-keyframe factor (Log(X_j^-1 X_k) = (dt_jk/dt_ij)
Log(X_i^-1 X_j)) because it keeps the window's per-keyframe (X, V) structure: marginalization,
the 20 -> 5 shrink and the Estimate's velocity work unchanged, and the prior is defined for the
first two keyframes and across any gap.

gtsam is imported inside functions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MotionNoise:
    """White-noise acceleration densities of the constant-velocity prior.

    sigma_rot: angular acceleration, rad/s^2/sqrt(s). sigma_trans: linear, m/s^2/sqrt(s).
    Body-frame, the same on every axis.
    """

    sigma_rot: float = 1.0
    sigma_trans: float = 1.0

    def qc(self) -> np.ndarray:
        """(6, 6) power spectral density Qc, Pose3 tangent order."""
        return np.diag(np.r_[np.full(3, self.sigma_rot**2), np.full(3, self.sigma_trans**2)])

    def prediction_sigma(self, dt: float) -> tuple[float, float]:
        """Per-axis standard deviation (rad, m) of a pose predicted ``dt`` seconds ahead with a
        known twist: sqrt(dt^3 / 3) sigma (the pose block of Q(dt))."""
        s = np.sqrt(max(dt, 0.0) ** 3 / 3.0)
        return float(self.sigma_rot * s), float(self.sigma_trans * s)


def wnoa_covariance(dt: float, noise: MotionNoise) -> np.ndarray:
    """(12, 12) covariance Q(dt) of the error (pose increment, twist change), dt > 0 seconds."""
    qc = noise.qc()
    return np.block([[dt**3 / 3.0 * qc, dt**2 / 2.0 * qc], [dt**2 / 2.0 * qc, dt * qc]])


def constant_velocity_error(T_i, twist_i: np.ndarray, T_j, twist_j: np.ndarray, dt: float,
                            jacobians: bool = False):
    """The factor's error (12,) and, when asked, its four Jacobians.

    T_i, T_j: gtsam.Pose3 (T_map_body); twist_i, twist_j: (6,) body twists. Jacobians are with
    respect to right perturbations of the poses (Pose3 tangent) and plain increments of the
    twists: (12, 6) each, in the order T_i, twist_i, T_j, twist_j.
    """
    import gtsam

    twist_i = np.asarray(twist_i, dtype=np.float64)
    twist_j = np.asarray(twist_j, dtype=np.float64)
    e = np.empty(12)
    e[6:] = twist_j - twist_i
    if not jacobians:
        e[:6] = gtsam.Pose3.Logmap(T_i.between(T_j)) - dt * twist_i
        return e, None
    H_i = np.zeros((6, 6), order="F")
    H_j = np.zeros((6, 6), order="F")
    T_ij = T_i.between(T_j, H_i, H_j)  # H_i = -Ad(T_ij^-1), H_j = I
    J_log = np.zeros((6, 6), order="F")
    e[:6] = gtsam.Pose3.Logmap(T_ij, J_log) - dt * twist_i  # J_log = J_r^-1(xi)
    H_xi, H_xj = np.zeros((12, 6)), np.zeros((12, 6))
    H_xi[:6] = J_log @ H_i
    H_xj[:6] = J_log @ H_j
    return e, [H_xi, _twist_jacobian(dt, True), H_xj, _twist_jacobian(dt, False)]


def _twist_jacobian(dt: float, first: bool) -> np.ndarray:
    """d e / d twist_i = [-dt I; -I], d e / d twist_j = [0; I] (constant)."""
    H = np.zeros((12, 6))
    if first:
        H[:6] = -dt * np.eye(6)
        H[6:] = -np.eye(6)
    else:
        H[6:] = np.eye(6)
    return H


def constant_velocity_factor(key_xi, key_vi, key_xj, key_vj, dt: float, noise: MotionNoise):
    """A ``gtsam.CustomFactor`` on (X_i, V_i, X_j, V_j) with covariance ``wnoa_covariance``."""
    import gtsam

    if not dt > 0:
        raise ValueError(f"constant-velocity factor over dt={dt!r} s: expected dt > 0")
    model = gtsam.noiseModel.Gaussian.Covariance(wnoa_covariance(float(dt), noise))
    dt = float(dt)

    def error(this, values, H):
        kxi, kvi, kxj, kvj = this.keys()
        e, Hs = constant_velocity_error(values.atPose3(kxi), values.atVector(kvi), values.atPose3(kxj),
                                        values.atVector(kvj), dt, jacobians=H is not None)
        if H is not None:
            for n in range(4):
                H[n] = Hs[n]
        return e

    return gtsam.CustomFactor(model, gtsam.KeyVector([key_xi, key_vi, key_xj, key_vj]), error)


def twist_prior(key_v, twist: np.ndarray, sigma_rate_rad_s: float, sigma_vel_m_s: float):
    """PriorFactorVector on a twist key: (6,) mean, per-axis sigmas (rad/s, m/s)."""
    import gtsam

    noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sigma_rate_rad_s), np.full(3, sigma_vel_m_s)])
    return gtsam.PriorFactorVector(key_v, np.asarray(twist, dtype=np.float64), noise)


def predict(T_map_body: np.ndarray, twist: np.ndarray, dt) -> np.ndarray:
    """T_map_body Exp(dt twist): (4, 4) for a scalar dt (s), (K, 4, 4) for dt (K,)."""
    import gtsam

    T = np.asarray(T_map_body, dtype=np.float64)
    w = np.asarray(twist, dtype=np.float64)
    dts = np.atleast_1d(np.asarray(dt, dtype=np.float64))
    out = np.array([T @ gtsam.Pose3.Expmap(d * w).matrix() for d in dts])
    return out[0] if np.ndim(dt) == 0 else out


def extrapolation_jacobians(twist: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians (6, 6) of T' = T Exp(tau twist) w.r.t. a right perturbation of T and an
    increment of the twist (Pose3 tangent of T'): Ad(Exp(-tau twist)) and tau J_r(tau twist)."""
    import gtsam

    xi = tau * np.asarray(twist, dtype=np.float64)
    return gtsam.Pose3.Expmap(-xi).AdjointMap(), tau * gtsam.Pose3.ExpmapDerivative(xi)


def twist_between(T_a: np.ndarray, T_b: np.ndarray, dt: float) -> np.ndarray:
    """The constant body twist (6,) that moves T_a to T_b in dt > 0 seconds: Log(T_a^-1 T_b) / dt."""
    import gtsam

    from blockloc.geometry import inv_T

    return gtsam.Pose3.Logmap(gtsam.Pose3(inv_T(T_a) @ T_b)) / dt


def body_twist_from_map_velocity(T_map_body: np.ndarray, velocity_map: np.ndarray) -> np.ndarray:
    """(6,) twist with zero angular rate and the body-frame linear velocity R^T v (m/s)."""
    return np.r_[np.zeros(3), np.asarray(T_map_body)[:3, :3].T @ np.asarray(velocity_map, dtype=np.float64)]


def map_velocity(T_map_body: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """(3,) velocity of the body origin in the map frame, m/s (R v of the twist)."""
    return np.asarray(T_map_body)[:3, :3] @ np.asarray(twist, dtype=np.float64)[3:]


def _axis_rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    from blockloc.geometry import so3_exp

    a = np.asarray(axis, dtype=np.float64)
    return so3_exp(a / np.linalg.norm(a) * angle_rad)


def rotated_predictions(T_pred: np.ndarray, gravity_map: np.ndarray, yaw_deg=(), tilt_deg=()
                        ) -> list[tuple[str, np.ndarray]]:
    """Alternative initial guesses around a prediction (4, 4) T_map_body, in the order given.

    yaw_deg: turns about the map's vertical (the gravity axis, so a tilted sensor is turned as a
    person turns) through the body origin. tilt_deg: roll and pitch, turns about the body's own x
    and y axes. Returns (label, T_map_body) pairs, e.g. ('yaw+30', T).
    """
    out = []
    up = -np.asarray(gravity_map, dtype=np.float64)
    for a in yaw_deg:
        T = np.array(T_pred, dtype=np.float64)
        T[:3, :3] = _axis_rotation(up, np.deg2rad(a)) @ T[:3, :3]
        out.append((f"yaw{a:+g}", T))
    for a in tilt_deg:
        for name, axis in (("roll", (1.0, 0.0, 0.0)), ("pitch", (0.0, 1.0, 0.0))):
            T = np.array(T_pred, dtype=np.float64)
            T[:3, :3] = T[:3, :3] @ _axis_rotation(np.array(axis), np.deg2rad(a))
            out.append((f"{name}{a:+g}", T))
    return out
