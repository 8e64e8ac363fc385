"""NDT engine: accuracy on real and synthetic points, derivatives, tiles, errors."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from blockloc.errors import RegistrationError
from blockloc.geometry import inv_T, rotation_angle, transform_points, xyzrpy_to_T
from blockloc.registration.ndt import (
    NdtRegistration,
    NdtTarget,
    align,
    ndt_constants,
    se3_exp,
)


def pose_error(T_est, T_ref):
    """(translation m, rotation deg) of inv(T_ref) @ T_est."""
    E = inv_T(T_ref) @ T_est
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(rotation_angle(E[:3, :3])))


def random_offset(rng, trans=1.0, yaw_deg=5.0, rp_deg=2.0):
    dx = rng.uniform(-trans, trans, 3)
    roll, pitch = np.radians(rng.uniform(-rp_deg, rp_deg, 2))
    yaw = np.radians(rng.uniform(-yaw_deg, yaw_deg))
    return xyzrpy_to_T(*dx, roll, pitch, yaw)


# ------------------------------------------------------------------------------------------
# real HDL-32E pair


def test_real_pair_from_identity_and_random_starts(hdl_pair):
    target_pts, source, T_ref = hdl_pair
    target = NdtTarget.build(target_pts, resolution=1.0)
    reg = NdtRegistration(neighbors="DIRECT7")
    res = reg.align(target, source, np.eye(4))
    et, er = pose_error(res.T_target_source, T_ref)
    assert res.converged and et < 0.05 and er < 0.5, (et, er)
    assert 0.5 < res.fitness <= 1.0

    rng = np.random.default_rng(2024)
    ok = 0
    for _ in range(50):
        T0 = T_ref @ random_offset(rng)
        r = reg.align(target, source, T0)
        et, er = pose_error(r.T_target_source, T_ref)
        ok += et < 0.05 and er < 0.5
    assert ok >= 48, f"{ok}/50 within 5 cm and 0.5 deg"


def test_real_pair_one_shot_direct1_at_2m(hdl_pair):
    """The block-map paper's setting (DIRECT1, 2 m) converges from a moderate offset."""
    target_pts, source, T_ref = hdl_pair
    T0 = T_ref @ xyzrpy_to_T(0.3, -0.2, 0.05, 0.0, 0.0, np.radians(2.0))
    res = align(target_pts, source, T0, resolution=2.0, neighbors="DIRECT1")
    et, er = pose_error(res.T_target_source, T_ref)
    assert res.converged and et < 0.1 and er < 0.5, (et, er)


def _tracking_starts(T_ref, n, seed):
    """T_ref and n - 1 starts within +-0.2 m and +-1 deg per axis of it (an IMU prediction)."""
    rng = np.random.default_rng(seed)
    return [T_ref] + [T_ref @ xyzrpy_to_T(*rng.uniform(-0.2, 0.2, 3),
                                          *np.radians(rng.uniform(-1.0, 1.0, 3)))
                      for _ in range(n - 1)]


def test_direct1_search_and_direct7_polish_reach_the_direct7_optimum(hdl_pair):
    """The default fine level (DIRECT1 search, DIRECT7 polish) ends where DIRECT7 alone does."""
    target_pts, source, T_ref = hdl_pair
    target = NdtTarget.build(target_pts, resolution=1.0)
    # both converged tightly: the optima themselves are compared, not the stopping residuals
    fast = NdtRegistration(step_epsilon=1e-4)
    plain = NdtRegistration(search_neighbors=None, step_epsilon=1e-4)
    assert (fast.neighbors, fast.search_neighbors) == ("DIRECT7", "DIRECT1")
    for T0 in _tracking_starts(T_ref, 8, seed=5):
        a, b = fast.align(target, source, T0), plain.align(target, source, T0)
        assert a.converged and b.converged
        et, er = pose_error(a.T_target_source, b.T_target_source)
        assert et < 1e-3 and er < 0.01, (et, er)
        assert a.score == pytest.approx(b.score, rel=1e-4)


def test_default_stop_lies_within_step_epsilon_of_the_optimum(hdl_pair):
    """Default settings stop before a Newton step shorter than step_epsilon (1e-3, rad and m
    together): a tight DIRECT7 run from the result moves it by about that at most."""
    target_pts, source, T_ref = hdl_pair
    target = NdtTarget.build(target_pts, resolution=1.0)
    reg = NdtRegistration()
    tight = NdtRegistration(search_neighbors=None, step_epsilon=1e-7, coarse_to_fine=False)
    for T0 in _tracking_starts(T_ref, 8, seed=6):
        res = reg.align(target, source, T0)
        assert res.converged
        again = tight.align(target, source, res.T_target_source)
        et, er = pose_error(res.T_target_source, again.T_target_source)
        assert et < 1.5e-3 and np.radians(er) < 1.5e-3, (et, er)


def test_align_reports_exact_direct7_derivatives_at_its_pose(hdl_pair):
    """score, b, H_exact of the fused level kernel are those evaluate() gives at the result."""
    target_pts, source, T_ref = hdl_pair
    target = NdtTarget.build(target_pts, resolution=1.0)
    reg = NdtRegistration()
    T0 = T_ref @ xyzrpy_to_T(0.15, -0.1, 0.05, 0.01, -0.005, 0.015)
    res = reg.align(target, source, T0)
    ev = reg.evaluate(target, source, res.T_target_source)
    assert res.score == pytest.approx(ev.score, rel=1e-9)
    assert res.num_inliers == ev.num_inliers
    np.testing.assert_allclose(res.b, ev.b, atol=1e-6 * np.abs(ev.H).max())
    np.testing.assert_allclose(res.H_exact, ev.H, rtol=1e-6, atol=1e-9 * np.abs(ev.H).max())
    assert res.eigenvalues[0] > 0


def test_align_makes_one_kernel_call_per_level_and_stage(hdl_pair, monkeypatch):
    """Default: one ndt_level call for the coarse level, one for the DIRECT1 search, one for
    the DIRECT7 polish, and no other alignment kernel call from Python."""
    from blockloc.registration import _ndt_kernels as k

    target_pts, source, T_ref = hdl_pair
    target = NdtTarget.build(target_pts, resolution=1.0)
    calls = []
    for name in ("ndt_level", "ndt_evaluate"):
        real = getattr(k, name)
        monkeypatch.setattr(k, name, lambda *a, _real=real, _name=name: (
            calls.append((_name, a[3][4], a[4])) or _real(*a)))
    res = NdtRegistration().align(target, source, T_ref)
    assert [(c[0], c[2]) for c in calls] == [("ndt_level", 1), ("ndt_level", 1),
                                             ("ndt_level", 7)]
    assert [c[1] for c in calls] == [0.5, 1.0, 1.0]  # 1 / resolution: coarse level first
    assert res.passes >= 3
    calls.clear()
    NdtRegistration(search_neighbors=None).align(target, source, T_ref)
    assert [(c[0], c[2]) for c in calls] == [("ndt_level", 1), ("ndt_level", 7)]


def test_align_from_prediction_near_start_fine_level_only(hdl_pair, monkeypatch):
    """From starts within 1 cm / 0.1 deg of the optimum (an IMU prediction on the simulated
    worlds): the DIRECT7 level alone (one kernel call), in fewer passes than align(), at DIRECT7's
    optimum within the stopping tolerance (step_epsilon 1e-3; align() from these starts ends up
    to 1 cm / 0.4 deg away from it: its coarse level moves the pose first)."""
    from blockloc.registration import _ndt_kernels as k

    target_pts, source, T_ref = hdl_pair
    target = NdtTarget.build(target_pts, resolution=1.0)
    reg = NdtRegistration()
    T_opt = NdtRegistration(search_neighbors=None, coarse_to_fine=False, step_epsilon=1e-7).align(
        target, source, T_ref).T_target_source
    fitness_opt = reg.evaluate(target, source, T_opt).num_inliers / len(source)
    rng = np.random.default_rng(11)
    calls = []
    real = k.ndt_level
    monkeypatch.setattr(k, "ndt_level", lambda *a: calls.append(a[4]) or real(*a))
    for _ in range(6):
        T0 = T_opt @ xyzrpy_to_T(*rng.uniform(-0.01, 0.01, 3), *np.radians(rng.uniform(-0.1, 0.1, 3)))
        calls.clear()
        fast = reg.align_from_prediction(target, source, T0)
        assert calls == [7] and fast.coarse_iterations == 0 and fast.converged
        et, er = pose_error(fast.T_target_source, T_opt)
        # the stop leaves the pose about step_epsilon (1e-3, rad and m together) from the optimum
        assert np.hypot(et, np.radians(er)) < 2e-3, (et, er)
        full = reg.align(target, source, T0)
        assert fast.passes < full.passes
        assert fast.fitness == pytest.approx(fitness_opt, abs=0.01)


@pytest.mark.parametrize("offset", [(0.1, -0.08, 0.05, 0.5), (0.6, -0.4, 0.1, 4.0)])
def test_align_from_prediction_far_start_falls_back_to_align(hdl_pair, offset):
    """From starts 10 cm / 0.5 deg and 0.6 m / 4 deg off (the fine level alone does not converge
    fast there): align()'s result from the same start, the passes spent first counted on top."""
    target_pts, source, T_ref = hdl_pair
    target = NdtTarget.build(target_pts, resolution=1.0)
    reg = NdtRegistration()
    x, y, z, yaw_deg = offset
    T0 = T_ref @ xyzrpy_to_T(x, y, z, 0.0, 0.0, np.radians(yaw_deg))
    fast = reg.align_from_prediction(target, source, T0)
    full = reg.align(target, source, T0)
    np.testing.assert_allclose(fast.T_target_source, full.T_target_source, atol=1e-12)
    assert fast.coarse_iterations == full.coarse_iterations > 0
    assert full.passes < fast.passes <= full.passes + 3
    et, er = pose_error(fast.T_target_source, T_ref)
    assert et < 0.05 and er < 0.5, (et, er)


# ------------------------------------------------------------------------------------------
# synthetic scene


@pytest.mark.parametrize("neighbors", ["DIRECT1", "DIRECT7", "DIRECT27"])
def test_synthetic_random_transforms_recovered(scene, make_scene, neighbors):
    target = NdtTarget.build(scene, resolution=1.0)
    # An independent sample of the same surfaces as the scan.
    scan = make_scene(seed=7, n_per_m2=4.0)
    rng = np.random.default_rng(11)
    reg = NdtRegistration(neighbors=neighbors)
    offsets = 0.3 if neighbors == "DIRECT1" else 1.0  # DIRECT1 sees only its own voxel
    for _ in range(5):
        T_true = random_offset(rng, trans=offsets)
        source = transform_points(inv_T(T_true), scan)
        res = reg.align(target, source, np.eye(4))
        et, er = pose_error(res.T_target_source, T_true)
        assert res.converged, neighbors
        assert et < 0.02 and er < 0.1, (neighbors, et, er)
        assert res.fitness > 0.9


def test_result_fields_and_degeneracy(scene, make_scene):
    target = NdtTarget.build(scene, resolution=1.0)
    scan = make_scene(seed=3, n_per_m2=4.0)
    res = NdtRegistration().align(target, scan)
    assert res.T_target_source.shape == (4, 4)
    assert res.H.shape == (6, 6) and res.b.shape == (6,)
    assert np.allclose(res.H, res.H.T)
    assert res.error == pytest.approx(-res.score)
    assert res.num_inliers == round(res.fitness * res.num_points)
    # at the optimum of a well-constrained scene: gradient ~ 0 relative to curvature, H PD
    assert np.all(res.eigenvalues > 0)
    assert len(res.degenerate_directions(1e-3)) == 0
    # a single plane (the floor): in-plane translation is held only by the extent of the voxel
    # Gaussians (eigenvalues ~1e-5 of the largest), so exactly v_x and v_y are reported weak
    floor = scene[(np.abs(scene[:, 2]) < 0.05)]
    plane_res = NdtRegistration().align(NdtTarget.build(floor), floor[::10])
    weak = plane_res.degenerate_directions(1e-3)
    assert len(weak) == 2
    span = np.zeros((2, 6))
    span[0, 3] = span[1, 4] = 1.0
    proj = weak @ span.T
    assert np.allclose(np.linalg.svd(proj, compute_uv=False), 1.0, atol=1e-2)
    info = plane_res.information(0.0)
    assert np.linalg.eigvalsh(info).min() >= -1e-9


# ------------------------------------------------------------------------------------------
# derivatives


def _interior_source(scene, T, res, n=400, seed=5):
    """Scene points whose image under T lies >= 0.15 voxel from any voxel face (no voxel changes
    under the small finite-difference perturbations)."""
    rng = np.random.default_rng(seed)
    pts = scene[rng.choice(len(scene), 6000, replace=False)]
    frac = np.mod(transform_points(T, pts) / res, 1.0)
    keep = np.all((frac > 0.15) & (frac < 0.85), axis=1)
    return pts[keep][:n]


@pytest.mark.parametrize("neighbors", ["DIRECT1", "DIRECT7", "DIRECT27"])
def test_gradient_and_hessian_match_finite_differences(scene, neighbors):
    target = NdtTarget.build(scene, resolution=1.0)
    T = xyzrpy_to_T(0.12, -0.08, 0.05, 0.01, -0.02, 0.03)
    source = _interior_source(scene, T, 1.0)
    assert len(source) >= 200
    reg = NdtRegistration(neighbors=neighbors)
    ev = reg.evaluate(target, source, T)

    def cost(xi):
        return -reg.evaluate(target, source, T @ se3_exp(xi), derivatives=False).score

    # central differences; steps small enough that the truncation error (points up to 25 m from
    # the origin, normal sigma of a few cm) stays below the tolerances
    h = 1e-6
    E = np.eye(6) * h
    b_fd = np.array([(cost(E[i]) - cost(-E[i])) / (2 * h) for i in range(6)])
    h = 1e-5
    E = np.eye(6) * h
    H_fd = np.zeros((6, 6))
    for i in range(6):
        for j in range(6):
            H_fd[i, j] = (cost(E[i] + E[j]) - cost(E[i] - E[j]) - cost(-E[i] + E[j])
                          + cost(-E[i] - E[j])) / (4 * h * h)
    scale_b = np.abs(b_fd).max()
    scale_H = np.abs(H_fd).max()
    assert scale_b > 1.0  # not at the optimum: the gradient is substantial
    np.testing.assert_allclose(ev.b, b_fd, atol=1e-5 * scale_b)
    np.testing.assert_allclose(ev.H, H_fd, atol=1e-4 * scale_H)


def test_gtsam_hessian_factor_reproduces_newton_step(scene):
    import gtsam

    target = NdtTarget.build(scene, resolution=1.0)
    T = xyzrpy_to_T(0.02, -0.015, 0.01, 0.0, 0.0, 0.002)
    source = _interior_source(scene, T, 1.0, n=600)
    reg = NdtRegistration()
    ev = reg.evaluate(target, source, T)
    error = -ev.score
    assert np.linalg.eigvalsh(ev.H).min() > 0  # near the optimum: H positive definite
    key = gtsam.symbol("x", 0)
    factor = gtsam.HessianFactor(key, ev.H, -ev.b, 2.0 * error)
    graph = gtsam.GaussianFactorGraph()
    graph.push_back(factor)
    delta = graph.optimize().at(key)
    np.testing.assert_allclose(delta, -np.linalg.solve(ev.H, ev.b), rtol=1e-6, atol=1e-9)
    # the factor's error is the quadratic model error + b.x + x^T H x / 2
    x = np.array([0.001, -0.002, 0.0005, 0.01, 0.02, -0.01])
    vv = gtsam.VectorValues()
    vv.insert(key, x)
    assert factor.error(vv) == pytest.approx(error + ev.b @ x + 0.5 * x @ ev.H @ x, rel=1e-9)
    # and the Newton step lowers the true cost
    after = -reg.evaluate(target, source, T @ se3_exp(delta), derivatives=False).score
    assert after < error


def test_result_H_is_psd_projection_of_exact_hessian(scene, make_scene):
    target = NdtTarget.build(scene, resolution=1.0)
    scan = make_scene(seed=7, n_per_m2=4.0)
    T_true = xyzrpy_to_T(0.7, -0.25, 0.1, 0.02, -0.03, 0.08)
    source = transform_points(inv_T(T_true), scan)
    # one iteration from far away: the exact Hessian is indefinite there
    res = NdtRegistration(max_iterations=1, coarse_to_fine=False).align(target, source)
    lam = np.linalg.eigvalsh(res.H_exact)
    assert lam[0] < 0
    np.testing.assert_allclose(res.eigenvalues, lam, rtol=1e-9, atol=1e-9 * abs(lam).max())
    lam_psd = np.linalg.eigvalsh(res.H)
    assert lam_psd.min() > -1e-9 * lam.max()
    np.testing.assert_allclose(np.sort(lam_psd), np.sort(np.maximum(lam, 0)), atol=1e-6 * lam.max())
    # converged: H equals the exact Hessian and is positive definite
    good = NdtRegistration().align(target, source)
    np.testing.assert_array_equal(good.H, 0.5 * (good.H_exact + good.H_exact.T))
    assert good.eigenvalues[0] > 0


NEIGHBOR_OFFSETS = {
    "DIRECT1": [(0, 0, 0)],
    "DIRECT7": [(0, 0, 0), (-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)],
    "DIRECT27": [(i, j, k) for k in (-1, 0, 1) for j in (-1, 0, 1) for i in (-1, 0, 1)],
}


def _numpy_pairs(target, x, neighbors):
    """For each point of x (N, 3) (target frame), the (mean, inverse covariance) of its
    neighbour Gaussians, found with a plain dict (1 m voxels; a Gaussian's voxel is that of its
    mean, which lies inside it)."""
    means, covs = target.gaussians()
    icovs = np.linalg.inv(covs)
    index = {tuple(k): i for i, k in enumerate(np.floor(means).astype(int))}
    out = []
    for p in x:
        v = np.floor(p).astype(int)
        rows = [index.get(tuple(v + o)) for o in NEIGHBOR_OFFSETS[neighbors]]
        out.append([(means[i], icovs[i]) for i in rows if i is not None])
    return out


def _noisy_scene_points(scene, n=300, seed=3):
    rng = np.random.default_rng(seed)
    return scene[rng.choice(len(scene), n, replace=False)] + rng.normal(0, 0.05, (n, 3))


@pytest.mark.parametrize("neighbors", ["DIRECT1", "DIRECT7", "DIRECT27"])
def test_score_and_inliers_match_numpy_reference(scene, neighbors):
    """Kernel score (hash look-ups, DIRECT7 neighbour lists) against a plain numpy version."""
    target = NdtTarget.build(scene, resolution=1.0)
    T = xyzrpy_to_T(0.2, -0.1, 0.05, 0.01, 0.0, 0.02)
    source = _noisy_scene_points(scene)
    x = transform_points(T, source)
    d1, d2 = ndt_constants(1.0, 0.55)
    score, inliers = 0.0, 0
    for p, pairs in zip(x, _numpy_pairs(target, x, neighbors)):
        qs = [(p - mu) @ C @ (p - mu) for mu, C in pairs]
        score += sum(-d1 * np.exp(-d2 * q / 2) for q in qs)
        inliers += bool(qs) and min(qs) <= 11.345
    ev = NdtRegistration(neighbors=neighbors).evaluate(target, source, T, derivatives=False)
    assert ev.score == pytest.approx(score, rel=1e-9)
    assert ev.num_inliers == inliers
    assert 0 < inliers < len(source)


def _numpy_derivatives(target, source, T, neighbors):
    """score, b (6,), exact H (6, 6) and Gauss-Newton H_gn (6, 6) of error = -score under the
    right perturbation T * Exp(xi), by the chain rule pair by pair (independent of the kernels).

    x(xi) = R Exp(xi) p + t with Exp(xi) p = p + w x p + v + (w x (w x p) + w x v) / 2 + O(3):
    dx/dxi = R [-skew(p), I], d2x/dxi_i dxi_j = R Q_ij(p) (Q the quadratic part's Hessian).
    """
    d1, d2 = ndt_constants(1.0, 0.55)
    R, t = T[:3, :3], T[:3, 3]
    x = transform_points(T, source)
    eye6 = np.eye(6)

    def quad(p, xi):
        w, v = xi[:3], xi[3:]
        return 0.5 * np.cross(w, np.cross(w, p)) + 0.5 * np.cross(w, v)

    score, b, H, H_gn = 0.0, np.zeros(6), np.zeros((6, 6)), np.zeros((6, 6))
    for p, xp, pairs in zip(source, x, _numpy_pairs(target, x, neighbors)):
        skew = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
        J = R @ np.hstack([-skew, np.eye(3)])
        # Q[i, j] (3,): second derivative of Exp(xi) p (a quadratic form: polarization is exact)
        Q = np.array([[quad(p, eye6[i] + eye6[j]) - quad(p, eye6[i]) - quad(p, eye6[j])
                       for j in range(6)] for i in range(6)])
        for mu, C in pairs:
            y = C @ (xp - mu)
            q = (xp - mu) @ y
            if d2 * q / 2 > 30.0:  # the kernels' cut-off (weight < 1e-13)
                continue
            e = np.exp(-d2 * q / 2)
            a = -d1 * d2 * e
            score += -d1 * e
            g = a * y  # gradient of the pair's cost d1 e with respect to x
            b += J.T @ g
            H += J.T @ (a * (C - d2 * np.outer(y, y))) @ J + Q @ (R.T @ g)
            H_gn += a * J.T @ C @ J
    return score, b, H, H_gn


@pytest.mark.parametrize("neighbors", ["DIRECT1", "DIRECT7", "DIRECT27"])
def test_fused_derivatives_match_numpy_chain_rule(scene, neighbors):
    """Every evaluation mode (exact, Gauss-Newton, both from one pass) against the chain rule."""
    from blockloc.registration import _ndt_kernels as k

    target = NdtTarget.build(scene, resolution=1.0)
    level = target.snapshot(0).kernel_level()
    d1, d2 = ndt_constants(1.0, 0.55)
    rng = np.random.default_rng(21)
    source = _noisy_scene_points(scene, 200, seed=4)
    nb = {"DIRECT1": 1, "DIRECT7": 7, "DIRECT27": 27}[neighbors]
    for _ in range(3):
        T = random_offset(rng, trans=0.3, yaw_deg=3.0, rp_deg=1.0)
        score, b, H, H_gn = _numpy_derivatives(target, source, T, neighbors)
        scale_b, scale_H = np.abs(b).max(), np.abs(H).max()
        got = {}
        for mode in (k.MODE_EXACT, k.MODE_GN, k.MODE_BOTH):
            memo = (np.full(len(source), -1, np.int64), np.empty(len(source), np.int64))
            acc = k.ndt_evaluate(source, 1, T, level, nb, d1, d2, 11.345, mode, *memo)
            out = np.empty(6), np.empty((6, 6)), np.empty((6, 6))
            k.right_derivatives(acc, T, *out)
            assert acc[0] == pytest.approx(score, rel=1e-9)
            np.testing.assert_allclose(out[0], b, atol=1e-9 * scale_b)
            got[mode] = out
        np.testing.assert_allclose(got[k.MODE_EXACT][1], H, atol=1e-9 * scale_H)
        np.testing.assert_allclose(got[k.MODE_GN][2], H_gn, atol=1e-9 * scale_H)
        np.testing.assert_allclose(got[k.MODE_BOTH][1], H, atol=1e-9 * scale_H)
        np.testing.assert_allclose(got[k.MODE_BOTH][2], H_gn, atol=1e-9 * scale_H)
        # the public evaluate() is the exact mode
        ev = NdtRegistration(neighbors=neighbors).evaluate(target, source, T)
        np.testing.assert_allclose(ev.H, H, atol=1e-9 * scale_H)


def test_strided_evaluation_equals_subset_copy(scene):
    """The coarse levels read every k-th source point in place; same sums as a copied subset."""
    from blockloc.registration import _ndt_kernels as k

    target = NdtTarget.build(scene, resolution=1.0)
    level = target.snapshot(0).kernel_level()
    d1, d2 = ndt_constants(1.0, 0.55)
    source = _noisy_scene_points(scene, 6000, seed=5)  # > SERIAL_MAX_POINTS: parallel path
    T = xyzrpy_to_T(0.1, 0.05, 0.0, 0.0, 0.01, -0.02)
    for stride in (1, 2, 7):
        sub = np.ascontiguousarray(source[::stride])
        memo_a = (np.full(len(source), -1, np.int64), np.empty(len(source), np.int64))
        memo_b = (np.full(len(sub), -1, np.int64), np.empty(len(sub), np.int64))
        a = k.ndt_evaluate(source, stride, T, level, 7, d1, d2, 11.345, k.MODE_BOTH, *memo_a)
        c = k.ndt_evaluate(sub, 1, T, level, 7, d1, d2, 11.345, k.MODE_BOTH, *memo_b)
        np.testing.assert_allclose(a, c, rtol=1e-12, atol=1e-9 * np.abs(c).max())
        assert a[1] > 0.5 * len(sub)  # inliers: the scene matches itself


def test_se3_exp_is_gtsam_pose3_expmap():
    """The chart of H and b is GTSAM's: xi = (omega, v), T * Exp(xi)."""
    import gtsam

    rng = np.random.default_rng(8)
    for scale in (1e-9, 1e-3, 0.3, 2.5):
        for _ in range(5):
            xi = rng.normal(0, scale, 6)
            np.testing.assert_allclose(se3_exp(xi), gtsam.Pose3.Expmap(xi).matrix(), atol=1e-12)


def test_gradient_direction_matches_gtsam_local_coordinates(scene):
    """Moving by -b (small) in gtsam's retract lowers the cost by ~|b|^2 step: same tangent."""
    import gtsam

    target = NdtTarget.build(scene, resolution=1.0)
    T = xyzrpy_to_T(0.1, 0.05, 0.0, 0.0, 0.0, 0.02)
    source = _interior_source(scene, T, 1.0)
    reg = NdtRegistration()
    ev = reg.evaluate(target, source, T)
    h = 1e-7
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = h
        T_plus = gtsam.Pose3(T).retract(xi).matrix()
        T_minus = gtsam.Pose3(T).retract(-xi).matrix()
        fd = (-reg.evaluate(target, source, T_plus, False).score
              + reg.evaluate(target, source, T_minus, False).score) / (2 * h)
        assert fd == pytest.approx(ev.b[i], rel=1e-4, abs=1e-3)


# PCL's NormalDistributionsTransform::computeTransformation (and ndt_omp, which copies it) set
# (Magnusson 2009, eq. 6.8):
#   c1 = 10 (1 - outlier_ratio), c2 = outlier_ratio / resolution^3, d3 = -log(c2),
#   d1 = -log(c1 + c2) - d3, d2 = -2 log((-log(c1 exp(-0.5) + c2) - d3) / d1).
# The numbers below were evaluated once from that formula by hand (Python's math module in a
# scratch shell, not this package), for outlier ratio 0.55:
PCL_NDT_CONSTANTS = {
    1.0: (-2.217225244042889, 0.43312300470355464),
    2.0: (-4.196518186951408, 0.24847851012449546),
}


@pytest.mark.parametrize("resolution", sorted(PCL_NDT_CONSTANTS))
def test_ndt_constants_match_magnusson(resolution):
    """d1, d2 equal the literal values of PCL / ndt_omp's formula at 1 m and 2 m (ratio 0.55):
    at 2 m every power of the resolution matters (c2 = 0.55 / 8)."""
    d1, d2 = ndt_constants(resolution, 0.55)
    want_d1, want_d2 = PCL_NDT_CONSTANTS[resolution]
    assert d1 == pytest.approx(want_d1, rel=1e-12)
    assert d2 == pytest.approx(want_d2, rel=1e-12)


def test_ndt_constants_fit_the_gaussian_plus_uniform_mixture():
    """The fitted -d1 exp(-d2 x^2 / 2) + d3 equals -log(c1 exp(-x^2 / 2) + c2) at x = 0 and x = 1."""
    for res in (0.5, 1.0, 2.0, 3.0):
        d1, d2 = ndt_constants(res, 0.55)
        c1, c2 = 10 * 0.45, 0.55 / res**3
        d3 = -np.log(c2)
        assert d1 < 0 and d2 > 0
        for x in (0.0, 1.0):
            assert d1 * np.exp(-d2 * x * x / 2) + d3 == pytest.approx(-np.log(c1 * np.exp(-x * x / 2) + c2))


# ------------------------------------------------------------------------------------------
# target construction and tiles


def _snapshot_dict(target, level=0):
    snap = target.snapshot(level)
    order = np.argsort(snap.keys)
    return snap.keys[order], snap.gauss[order], snap.counts[order]


def _tiles(points, size, offset=0.0):
    idx = np.floor((points[:, :2] - offset) / size).astype(int)
    out = {}
    for key in {tuple(k) for k in idx}:
        sel = np.all(idx == key, axis=1)
        out[key] = points[sel]
    return out


def test_coarse_level_equals_direct_build_at_double_resolution(scene):
    """Level 1 (from the 1 m voxel sums) is the 2 m grid built from the points."""
    k1, g1, c1 = _snapshot_dict(NdtTarget.build(scene, resolution=1.0, coarse_levels=2), 1)
    k2, g2, c2 = _snapshot_dict(NdtTarget.build(scene, resolution=2.0, coarse_levels=0), 0)
    np.testing.assert_array_equal(k1, k2)
    np.testing.assert_array_equal(c1, c2)
    np.testing.assert_allclose(g1, g2, rtol=1e-8, atol=1e-8)
    k4, g4, _ = _snapshot_dict(NdtTarget.build(scene - 0.37, resolution=1.0, coarse_levels=2), 2)
    k5, g5, _ = _snapshot_dict(NdtTarget.build(scene - 0.37, resolution=4.0, coarse_levels=0), 0)
    np.testing.assert_array_equal(k4, k5)
    np.testing.assert_allclose(g4, g5, rtol=1e-8, atol=1e-8)


def test_gaussians_regularized_and_match_numpy(scene):
    target = NdtTarget.build(scene, resolution=2.0, min_points_per_voxel=6)
    means, covs = target.gaussians()
    counts = target.voxel_counts()
    assert np.all(counts >= 6)
    lam = np.linalg.eigvalsh(covs)
    assert np.all(lam[:, 0] >= 0.01 * lam[:, 2] * (1 - 1e-9))
    # one voxel against numpy
    vox = np.floor(scene / 2.0).astype(int)
    key = vox[0]
    sel = np.all(vox == key, axis=1)
    pts = scene[sel]
    i = np.argmin(np.linalg.norm(means - pts.mean(axis=0), axis=1))
    np.testing.assert_allclose(means[i], pts.mean(axis=0), atol=1e-9)
    w, V = np.linalg.eigh(np.cov(pts.T))
    w = np.maximum(w, 0.01 * w[-1])
    np.testing.assert_allclose(covs[i], (V * w) @ V.T, atol=1e-9)


@pytest.mark.parametrize("tile_size,offset", [(10.0, 0.0), (7.3, 0.4)])
def test_tiles_equal_full_build(scene, tile_size, offset):
    """Aligned tiles and tiles whose edges cut through voxels both equal the one-shot build."""
    full = _snapshot_dict(NdtTarget.build(scene, resolution=1.0))
    tiles = _tiles(scene, tile_size, offset)
    tiled = NdtTarget.from_tiles(tiles, resolution=1.0)
    k1, g1, c1 = full
    k2, g2, c2 = _snapshot_dict(tiled)
    np.testing.assert_array_equal(k1, k2)
    np.testing.assert_array_equal(c1, c2)
    np.testing.assert_allclose(g1, g2, rtol=1e-9, atol=1e-9)
    # the coarse level (derived from the voxel sums) matches too
    full_target = NdtTarget.build(scene, resolution=1.0)
    for level in (1,):
        kc1, gc1, cc1 = _snapshot_dict(full_target, level)
        kc2, gc2, cc2 = _snapshot_dict(tiled, level)
        np.testing.assert_array_equal(kc1, kc2)
        np.testing.assert_array_equal(cc1, cc2)
        np.testing.assert_allclose(gc1, gc2, rtol=1e-8, atol=1e-8)

    # remove and re-add one tile
    key = sorted(tiles)[0]
    tiled.remove_tile(key)
    rest = np.concatenate([p for k, p in tiles.items() if k != key])
    kr, gr, cr = _snapshot_dict(NdtTarget.build(rest, resolution=1.0))
    k3, g3, c3 = _snapshot_dict(tiled)
    np.testing.assert_array_equal(kr, k3)
    np.testing.assert_allclose(gr, g3, rtol=1e-9, atol=1e-9)
    tiled.add_tile(key, tiles[key])
    k4, g4, _ = _snapshot_dict(tiled)
    np.testing.assert_array_equal(k1, k4)
    np.testing.assert_allclose(g1, g4, rtol=1e-9, atol=1e-9)
    assert tiled.num_points == len(scene)


def test_tile_updates_while_aligning(scene, make_scene):
    tiles = _tiles(scene, 10.0)
    target = NdtTarget.from_tiles(tiles)
    scan = make_scene(seed=9, n_per_m2=3.0)
    T_true = xyzrpy_to_T(0.3, -0.2, 0.0, 0.0, 0.0, 0.02)
    source = transform_points(inv_T(T_true), scan)
    far_key = max(tiles)
    stop = threading.Event()
    errors = []

    def churn():
        try:
            while not stop.is_set():
                target.remove_tile(far_key)
                target.add_tile(far_key, tiles[far_key])
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    th = threading.Thread(target=churn)
    th.start()
    try:
        reg = NdtRegistration()
        for _ in range(5):
            res = reg.align(target, source)
            et, er = pose_error(res.T_target_source, T_true)
            assert et < 0.05 and er < 0.2
    finally:
        stop.set()
        th.join()
    assert not errors


def test_align_during_tile_swaps_sees_one_whole_map(scene, make_scene):
    """While a background thread swaps a tile in view between two versions, every alignment
    returns exactly the result against one version: never a mix of the two."""
    tiles = _tiles(scene, 10.0)
    key = max(tiles, key=lambda k: len(tiles[k]))
    version_a = tiles[key]
    version_b = version_a + np.array([0.05, 0.0, 0.0])  # moves the optimum measurably
    target = NdtTarget.from_tiles(tiles)
    scan = make_scene(seed=9, n_per_m2=3.0)
    T_true = xyzrpy_to_T(0.3, -0.2, 0.0, 0.0, 0.0, 0.02)
    source = transform_points(inv_T(T_true), scan)
    reg = NdtRegistration()
    results = {}
    for name, pts in (("b", version_b), ("a", version_a)):
        target.add_tile(key, pts)
        results[name] = reg.align(target, source).T_target_source
    assert not np.array_equal(results["a"], results["b"])
    stop = threading.Event()
    swaps = []
    errors = []

    def churn():
        try:
            while not stop.is_set():
                for pts in (version_b, version_a):
                    target.add_tile(key, pts)
                    swaps.append(1)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    th = threading.Thread(target=churn)
    th.start()
    try:
        seen = []
        for _ in range(20):
            T = reg.align(target, source).T_target_source
            seen.append([name for name, ref in results.items() if np.array_equal(T, ref)])
    finally:
        stop.set()
        th.join()
    assert not errors
    assert len(swaps) > 2
    assert all(len(s) == 1 for s in seen), seen


def test_gauss_newton_steps_reach_the_same_optimum(scene, make_scene):
    target = NdtTarget.build(scene, resolution=1.0)
    scan = make_scene(seed=7, n_per_m2=4.0)
    T_true = xyzrpy_to_T(0.4, -0.25, 0.05, 0.01, -0.02, 0.05)
    source = transform_points(inv_T(T_true), scan)
    newton = NdtRegistration(step_epsilon=1e-5).align(target, source)
    gn_reg = NdtRegistration(step="gauss_newton", step_epsilon=1e-5)
    gn = gn_reg.align(target, source)
    assert newton.converged and gn.converged
    et, er = pose_error(gn.T_target_source, newton.T_target_source)
    assert et < 1e-4 and er < 1e-3, (et, er)
    # the result's H is the exact Hessian at its pose, not the Gauss-Newton matrix
    ev = gn_reg.evaluate(target, source, gn.T_target_source)
    np.testing.assert_allclose(gn.H_exact, ev.H, rtol=1e-9, atol=1e-9 * np.abs(ev.H).max())


# ------------------------------------------------------------------------------------------
# bad input


def test_bad_inputs_raise_one_line_errors(scene):
    target = NdtTarget.build(scene)
    reg = NdtRegistration()
    cases = [
        (lambda: NdtTarget.build(np.empty((0, 3))), "target points"),
        (lambda: NdtTarget.build(np.zeros((10, 2))), "(N, 3)"),
        (lambda: reg.align(target, np.empty((0, 3))), "source points"),
        (lambda: reg.align(target, scene[:5]), "at least"),
        (lambda: reg.align(target, np.vstack([scene[:100], [[np.nan, 0, 0]]])), "NaN"),
        (lambda: reg.align(target, np.vstack([scene[:100], [[np.inf, 0, 0]]])), "NaN or inf"),
        (lambda: NdtTarget.build(np.array([[0, 0, np.nan]] * 20)), "NaN"),
        (lambda: reg.align(target, scene[:100], np.eye(3)), "T_init"),
        (lambda: reg.align(NdtTarget.build(scene[:5]), scene[:100]), "no voxel"),
        (lambda: NdtRegistration(neighbors="DIRECT5"), "DIRECT5"),
        (lambda: NdtTarget.build(scene, resolution=0.0), "resolution"),
        (lambda: target.remove_tile("nope"), "nope"),
    ]
    for fn, text in cases:
        with pytest.raises(RegistrationError) as info:
            fn()
        msg = str(info.value)
        assert text in msg and "\n" not in msg, msg


def test_from_config(hdl_pair):
    from blockloc.app.assemble import ndt_registration, ndt_target_options
    from blockloc.config import RegistrationConfig

    cfg = RegistrationConfig(resolution_m=2.0, neighbors="DIRECT1", coarse_levels=0,
                             coarse_to_fine=False, max_iterations=12)
    reg = ndt_registration(cfg)
    assert (reg.neighbors, reg.max_iterations, reg.coarse_to_fine) == ("DIRECT1", 12, False)
    target_pts, source, T_ref = hdl_pair
    target = NdtTarget.build(target_pts, **ndt_target_options(cfg))
    assert target.resolution == 2.0 and len(target.levels()) == 1
    res = reg.align(target, source, T_ref @ xyzrpy_to_T(0.2, 0.1, 0.0, 0.0, 0.0, 0.01))
    et, er = pose_error(res.T_target_source, T_ref)
    assert et < 0.1 and er < 0.5


def test_no_overlap_is_not_converged(scene):
    target = NdtTarget.build(scene)
    far = scene[:2000] + np.array([500.0, 0.0, 0.0])
    res = NdtRegistration().align(target, far)
    assert res.num_inliers == 0 and res.fitness == 0.0 and res.score == 0.0
    assert not res.converged
    np.testing.assert_array_equal(res.T_target_source, np.eye(4))
