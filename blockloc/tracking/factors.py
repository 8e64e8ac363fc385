"""Factors the tracker puts in the window: NDT scan-to-map, LiDAR odometry, priors.

(The LiDAR-only constant-velocity factor lives in ``blockloc.tracking.motion``.)

Tangent order everywhere is GTSAM's Pose3: (rotation rad, translation m), right perturbation.

The NDT factor is a robust Gaussian prior on the keyframe pose ``T_map_body`` at the pose NDT
converged to, whose information comes from NDT's Hessian: moved from the lidar to the body frame
by the adjoint, scaled, with directions whose eigenvalue is small against the strongest one
down-weighted (a corridor's axis), and floored by a minimum standard deviation so thousands of
correlated point residuals do not claim millimetre accuracy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.geometry import inv_T, lever_arm_scaling, skew


def adjoint(T: np.ndarray) -> np.ndarray:
    """(6, 6) adjoint of a (4, 4) transform in (rotation, translation) tangent order."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = skew(t) @ R
    return A


@dataclass(frozen=True)
class NdtFactorParams:
    """How a registration Hessian becomes a factor's information.

    information_scale: multiplies the Hessian (NDT's score is not a log-likelihood).
    degeneracy_ratio: eigenvalues below ratio * max are weak directions (rotation scaled to metres
        by the residuals' lever arm, see :func:`ndt_information`).
    weak_factor: weak eigenvalues are multiplied by this (down-weighted, not dropped).
    min_sigma_rot_rad, min_sigma_trans_m: floor of the factor's standard deviations.
    huber_k: Huber threshold in whitened units (0: no robust loss).
    """

    information_scale: float = 1.0
    degeneracy_ratio: float = 0.01
    weak_factor: float = 1e-3
    min_sigma_rot_rad: float = np.deg2rad(0.1)
    min_sigma_trans_m: float = 0.02
    huber_k: float = 1.345


def ndt_information(H_lidar: np.ndarray, T_body_lidar: np.ndarray,
                    params: NdtFactorParams) -> tuple[np.ndarray, int]:
    """Information (6, 6) on the body pose from NDT's Hessian on the lidar pose; and weak dims.

    H_lidar: (6, 6) Hessian of the registration cost w.r.t. a right perturbation of
    ``T_map_lidar`` (rotation first). With T_map_lidar = T_map_body T_body_lidar, a body
    perturbation xi_b gives xi_l = Ad(T_lidar_body) xi_b, so H_body = A^T H_lidar A.
    """
    A = adjoint(inv_T(T_body_lidar))
    H = A.T @ np.asarray(H_lidar, dtype=np.float64) @ A
    H = 0.5 * (H + H.T) * params.information_scale
    # Weak directions are found in a tangent whose six coordinates share one unit: rotation
    # scaled by the lever arm L of the residuals (xi' = (L rot, trans), H' = D H D). Compared
    # raw, rad^-2 against m^-2, the rotation eigenvalues are L^2 (hundreds of m^2) times the
    # translation ones, so every translation direction counted as weak: on the small simulated
    # world 3 weak dimensions in 296 of 300 scans (NDT and VGICP alike), translation then held
    # at 0.14 m (NDT) / 0.34 m (VGICP) instead of the floor. L^2 = tr(H_rot) / tr(H_trans): a
    # rotation by 1 rad moves the residuals as much as a translation by L metres, on average.
    d = lever_arm_scaling(H)  # xi = D xi'
    w, U = np.linalg.eigh(H * np.outer(d, d))
    w = np.maximum(w, 0.0)
    wmax = float(w.max()) if len(w) else 0.0
    weak = w < params.degeneracy_ratio * wmax
    w = np.where(weak, w * params.weak_factor, w)
    # Floor the standard deviations: cov = inv(info) + diag(floor^2), the inverse taken in the
    # eigenbasis of the (scaled) information so weak directions stay weak.
    floor = np.r_[np.full(3, params.min_sigma_rot_rad**2), np.full(3, params.min_sigma_trans_m**2)]
    eps = 1e-12 * max(wmax, 1.0)
    Ud = U * d[:, None]  # cov = D inv(H') D
    cov = (Ud / np.maximum(w, eps)) @ Ud.T + np.diag(floor)
    cov = 0.5 * (cov + cov.T)
    info = np.linalg.inv(cov)
    return 0.5 * (info + info.T), int(weak.sum())


def robust(noise, huber_k: float):
    """Wrap a gtsam noise model in a Huber loss (huber_k <= 0: unchanged)."""
    import gtsam

    if huber_k <= 0:
        return noise
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), noise)


def ndt_factor(key, T_map_body_ndt: np.ndarray, information: np.ndarray, huber_k: float):
    """PriorFactorPose3 on ``key`` at the registered pose with the given information (6, 6)."""
    import gtsam

    noise = gtsam.noiseModel.Gaussian.Information(information)
    return gtsam.PriorFactorPose3(key, gtsam.Pose3(T_map_body_ndt), robust(noise, huber_k))


def odometry_factor(key_a, key_b, T_a_b: np.ndarray, sigma_rot_rad: float, sigma_trans_m: float,
                    huber_k: float):
    """BetweenFactorPose3 for the relative LiDAR odometry between two keyframes."""
    import gtsam

    noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sigma_rot_rad), np.full(3, sigma_trans_m)])
    return gtsam.BetweenFactorPose3(key_a, key_b, gtsam.Pose3(T_a_b), robust(noise, huber_k))


def pose_prior(key, T_map_body: np.ndarray, sigma_rot_rad: float, sigma_trans_m: float):
    """PriorFactorPose3 with per-axis sigmas (rad, m)."""
    import gtsam

    noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sigma_rot_rad), np.full(3, sigma_trans_m)])
    return gtsam.PriorFactorPose3(key, gtsam.Pose3(np.asarray(T_map_body, dtype=np.float64)), noise)


def state_priors(keys, T_map_body: np.ndarray, velocity_map: np.ndarray, bias,
                 sigma_rot_rad: float, sigma_trans_m: float, sigma_vel_m_s: float,
                 sigma_acc_bias: float, sigma_gyro_bias: float) -> list:
    """Priors on (X, V, B) of a first keyframe."""
    import gtsam

    kx, kv, kb = keys
    vel_noise = gtsam.noiseModel.Isotropic.Sigma(3, sigma_vel_m_s)
    bias_noise = gtsam.noiseModel.Diagonal.Sigmas(
        np.r_[np.full(3, sigma_acc_bias), np.full(3, sigma_gyro_bias)])
    return [
        pose_prior(kx, T_map_body, sigma_rot_rad, sigma_trans_m),
        gtsam.PriorFactorVector(kv, np.asarray(velocity_map, dtype=np.float64), vel_noise),
        gtsam.PriorFactorConstantBias(kb, bias, bias_noise),
    ]
