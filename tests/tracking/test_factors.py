"""The tracker's factors: the NDT information's frame change (on NCLT's real extrinsic), its
weak-direction and floor shaping, and the GTSAM factors' tangent order and noise."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.datasets.nclt import NCLT_T_BODY_LIDAR
from blockloc.geometry import inv_T, transform_points, xyzrpy_to_T
from blockloc.registration.ndt import NdtRegistration, NdtTarget, se3_exp
from blockloc.tracking.factors import (NdtFactorParams, adjoint, ndt_factor, ndt_information,
                                       odometry_factor, robust, state_priors)
from tests.registration.conftest import synthetic_scene

# No shaping at all: no weak directions (eigenvalues are clamped to >= 0 first), no floor, scale 1,
# so the information is exactly the body-frame Hessian.
EXACT = NdtFactorParams(information_scale=1.0, degeneracy_ratio=0.0, weak_factor=1.0,
                        min_sigma_rot_rad=0.0, min_sigma_trans_m=0.0, huber_k=0.0)


def _fd_hessian(cost, h=1e-5):
    E = np.eye(6) * h
    H = np.zeros((6, 6))
    for i in range(6):
        for j in range(6):
            H[i, j] = (cost(E[i] + E[j]) - cost(E[i] - E[j]) - cost(-E[i] + E[j])
                       + cost(-E[i] - E[j])) / (4 * h * h)
    return 0.5 * (H + H.T)


@pytest.fixture(scope="module")
def ndt_case():
    """An NDT target, a scan in NCLT's velodyne frame and the body pose it was taken at."""
    scene = synthetic_scene(seed=0)
    target = NdtTarget.build(scene, resolution=1.0)
    T_map_body = xyzrpy_to_T(1.5, -2.0, 1.2, 0.02, -0.015, 0.4)
    T_map_lidar = T_map_body @ NCLT_T_BODY_LIDAR
    # scene points >= 0.15 voxel from every voxel face: the finite differences change no voxel
    rng = np.random.default_rng(5)
    pts = scene[rng.choice(len(scene), 6000, replace=False)]
    frac = np.mod(pts, 1.0)
    pts = pts[np.all((frac > 0.15) & (frac < 0.85), axis=1)][:500]
    # a few centimetres off the optimum, as a converged scan is
    T_map_lidar_est = T_map_lidar @ se3_exp(np.array([0.002, -0.001, 0.003, 0.02, -0.01, 0.01]))
    source = transform_points(inv_T(T_map_lidar), pts)
    return target, source, T_map_body @ inv_T(T_map_lidar) @ T_map_lidar_est


def test_ndt_information_is_the_body_frame_hessian_on_the_nclt_extrinsic(ndt_case):
    """H_body from ``ndt_information`` equals the finite-difference Hessian of the NDT cost under a
    right perturbation of T_map_body (GTSAM Pose3 tangent: rotation, translation), with the scan
    in NCLT's velodyne frame (T_body_lidar: 0.96 m lever arm, -90.7 deg yaw)."""
    target, source, T_map_body = ndt_case
    reg = NdtRegistration(neighbors="DIRECT7")
    H_lidar = reg.evaluate(target, source, T_map_body @ NCLT_T_BODY_LIDAR).H

    def cost(xi):
        T = T_map_body @ se3_exp(xi) @ NCLT_T_BODY_LIDAR
        return -reg.evaluate(target, source, T, derivatives=False).score

    H_fd = _fd_hessian(cost)
    assert np.linalg.eigvalsh(H_fd).min() > 0  # near the optimum: positive definite
    info, weak = ndt_information(H_lidar, NCLT_T_BODY_LIDAR, EXACT)
    assert weak == 0
    scale = np.abs(H_fd).max()
    np.testing.assert_allclose(info, H_fd, atol=2e-4 * scale)
    # the test has power: the other side's adjoint misses by far more than the tolerance
    A_wrong = adjoint(NCLT_T_BODY_LIDAR)
    assert np.abs(A_wrong.T @ H_lidar @ A_wrong - H_fd).max() > 0.05 * scale
    # and the lidar-frame Hessian itself is not the body-frame one (the extrinsic matters)
    assert np.abs(H_lidar - H_fd).max() > 0.05 * scale


def test_adjoint_is_gtsam_pose3_adjoint_map():
    import gtsam

    rng = np.random.default_rng(3)
    for _ in range(5):
        T = xyzrpy_to_T(*rng.normal(0, 2, 3), *rng.uniform(-np.pi, np.pi, 3))
        np.testing.assert_allclose(adjoint(T), gtsam.Pose3(T).AdjointMap(), atol=1e-12)
    np.testing.assert_allclose(adjoint(NCLT_T_BODY_LIDAR),
                               gtsam.Pose3(NCLT_T_BODY_LIDAR).AdjointMap(), atol=1e-12)


def test_information_scale_weak_directions_and_floor():
    H = np.diag([4e4, 4e4, 4e4, 1e4, 1e4, 1.0])  # translation z weak (a corridor's axis)
    T_bl = np.eye(4)
    info, weak = ndt_information(H, T_bl, NdtFactorParams(information_scale=0.5, degeneracy_ratio=0.01,
                                                          weak_factor=1e-3, min_sigma_rot_rad=0.0,
                                                          min_sigma_trans_m=0.0))
    assert weak == 1
    np.testing.assert_allclose(np.diag(info), [2e4, 2e4, 2e4, 5e3, 5e3, 0.5e-3], rtol=1e-9)
    # the floor: cov = inv(info) + diag(sigma^2), so no direction is held tighter than the floor
    p = NdtFactorParams(information_scale=1.0, degeneracy_ratio=0.0, min_sigma_rot_rad=0.01,
                        min_sigma_trans_m=0.05)
    info, weak = ndt_information(np.diag([1e8] * 3 + [1e8, 1e8, 100.0]), T_bl, p)
    assert weak == 0
    want = 1.0 / (1.0 / np.array([1e8] * 3 + [1e8, 1e8, 100.0]) + np.r_[[1e-4] * 3, [0.0025] * 3])
    np.testing.assert_allclose(np.diag(info), want, rtol=1e-9)
    np.testing.assert_allclose(info, np.diag(np.diag(info)), atol=1e-9 * want.max())
    # negative eigenvalues (an unconverged Hessian) never give negative information
    info, _ = ndt_information(np.diag([1.0, 1.0, 1.0, 1.0, 1.0, -5.0]), T_bl, NdtFactorParams())
    assert np.linalg.eigvalsh(info).min() > 0


def _plane_hessian(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Gauss-Newton Hessian (6, 6, rotation first, right perturbation at identity) of the
    point-to-plane residuals n . (R p + t - q): J = [(p x n)^T, n^T] per point."""
    J = np.hstack([np.cross(points, normals), normals])
    return J.T @ J


def _walls(rng, x_half: float, y_half: float, n: int = 4000, with_x_walls: bool = True):
    """Points (N, 3) and normals of a ground plane at z = -1.8 m and walls at y = +-y_half (and
    x = +-x_half), metres, as a LiDAR 1.8 m above ground sees a street or a yard."""
    pts, nrm = [], []
    planes = [(2, -1.8), (1, y_half), (1, -y_half)] + ([(0, x_half), (0, -x_half)] if with_x_walls else [])
    for axis, at in planes:
        p = np.c_[rng.uniform(-x_half, x_half, n), rng.uniform(-y_half, y_half, n), rng.uniform(-1.8, 4.0, n)]
        p[:, axis] = at
        pts.append(p)
        nrm.append(np.tile(np.eye(3)[axis], (n, 1)))
    return np.concatenate(pts), np.concatenate(nrm)


def test_weak_directions_compare_rotation_and_translation_in_one_unit():
    """A yard seen from its middle (walls 25 m away all round) constrains every direction, yet
    its rotation eigenvalues are ~L^2 = hundreds of times its translation ones (rad^-2 against
    m^-2): compared raw, all three translations counted as weak and the factor held translation
    at decimetres (as NDT and VGICP scans of the simulated world did). A street (no wall across
    it) has exactly one weak direction, translation along it. The count does not depend on the
    unit of length."""
    rng = np.random.default_rng(0)
    p = NdtFactorParams(information_scale=1.0, degeneracy_ratio=0.01, weak_factor=1e-3,
                        min_sigma_rot_rad=np.deg2rad(0.1), min_sigma_trans_m=0.02)
    yard = _plane_hessian(*_walls(rng, 25.0, 25.0))
    w_raw = np.linalg.eigvalsh(yard)
    assert (w_raw < 0.01 * w_raw.max()).sum() >= 3  # the raw comparison's mistake is there to make
    info, weak = ndt_information(yard, np.eye(4), p)
    assert weak == 0
    sigma = np.sqrt(np.diag(np.linalg.inv(info)))
    assert sigma[3:].max() < 0.05  # translation near its 2 cm floor, not decimetres
    # the same yard in centimetres (H_rot x 1e4): same directions, same count
    pts, nrm = _walls(rng, 25.0, 25.0)
    assert ndt_information(_plane_hessian(100.0 * pts, nrm), np.eye(4), p)[1] == 0
    info, weak = ndt_information(_plane_hessian(*_walls(rng, 40.0, 6.0, with_x_walls=False)), np.eye(4), p)
    assert weak == 1
    sigma = np.sqrt(np.diag(np.linalg.inv(info)))
    assert sigma[3] > 10 * sigma[4:].max()  # along the street (x) weak, across and up held


def test_ndt_factor_error_is_the_information_quadratic_in_gtsam_tangent_order():
    import gtsam

    key = gtsam.symbol("x", 0)
    T = xyzrpy_to_T(3.0, -1.0, 0.5, 0.1, -0.05, 1.0)
    info = np.diag([100.0, 200.0, 300.0, 1.0, 2.0, 3.0])  # rotation first
    f = ndt_factor(key, T, info, huber_k=0.0)
    xi = np.array([0.01, -0.02, 0.005, 0.3, -0.1, 0.2])
    v = gtsam.Values()
    v.insert(key, gtsam.Pose3(T @ se3_exp(xi)))
    assert f.error(v) == pytest.approx(0.5 * xi @ info @ xi, rel=1e-6)
    # with a Huber loss a large error grows linearly, not quadratically
    fr = ndt_factor(key, T, info, huber_k=1.345)
    big = np.array([0.0, 0.0, 0.0, 10.0, 0.0, 0.0])
    v2 = gtsam.Values()
    v2.insert(key, gtsam.Pose3(T @ se3_exp(big)))
    assert f.error(v2) == pytest.approx(50.0, rel=1e-6)  # whitened error 10: 10^2 / 2
    assert fr.error(v2) == pytest.approx(1.345 * 10.0 - 1.345**2 / 2, rel=1e-6)
    assert robust(gtsam.noiseModel.Unit.Create(6), 0.0).__class__.__name__ == "Unit"


def test_odometry_factor_and_state_priors():
    import gtsam
    from gtsam.symbol_shorthand import B, V, X

    Ta = xyzrpy_to_T(1.0, 2.0, 0.0, 0.0, 0.0, 0.3)
    Tb = xyzrpy_to_T(2.0, 2.5, 0.1, 0.01, 0.0, 0.5)
    f = odometry_factor(X(0), X(1), inv_T(Ta) @ Tb, 0.01, 0.1, huber_k=0.0)
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(Ta))
    v.insert(X(1), gtsam.Pose3(Tb))
    assert f.error(v) == pytest.approx(0.0, abs=1e-12)
    xi = np.array([0.01, 0.0, 0.0, 0.0, 0.1, 0.0])
    v.update(X(1), gtsam.Pose3(Tb @ se3_exp(xi)))
    assert f.error(v) == pytest.approx(0.5 * (1.0 + 1.0), rel=1e-6)  # one sigma in each
    bias = gtsam.imuBias.ConstantBias(np.array([0.1, 0.0, 0.0]), np.zeros(3))
    priors = state_priors((X(2), V(2), B(2)), Ta, np.array([1.0, 0.0, 0.0]), bias, 0.02, 0.1, 0.5,
                          0.2, 0.01)
    assert [list(p.keys()) for p in priors] == [[X(2)], [V(2)], [B(2)]]
    v = gtsam.Values()
    v.insert(X(2), gtsam.Pose3(Ta @ se3_exp(np.array([0.02, 0, 0, 0, 0, 0.1]))))
    v.insert(V(2), np.array([1.5, 0.0, 0.0]))
    v.insert(B(2), gtsam.imuBias.ConstantBias(np.array([0.3, 0.0, 0.0]), np.array([0.0, 0.0, 0.01])))
    errs = [p.error(v) for p in priors]
    np.testing.assert_allclose(errs, [0.5 * 2, 0.5 * 1, 0.5 * 2], rtol=1e-6)
