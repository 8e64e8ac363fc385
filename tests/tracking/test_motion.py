"""The LiDAR-only motion model: the constant-velocity factor's error and Jacobians, its noise, the
prediction and the rotated guesses."""

import gtsam
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from blockloc.geometry import rotation_angle, xyzrpy_to_T
from blockloc.tracking import motion
from blockloc.tracking.motion import MotionNoise

vec6 = st.lists(st.floats(-1.5, 1.5), min_size=6, max_size=6).map(np.array)


def _pose(xi):
    return gtsam.Pose3.Expmap(np.asarray(xi, dtype=np.float64))


@given(vec6, vec6, vec6, vec6, st.floats(0.05, 1.0))
def test_jacobians_match_finite_differences(a, b, w_i, w_j, dt):
    T_i, T_j = _pose(a), _pose(b)
    e0, Hs = motion.constant_velocity_error(T_i, w_i, T_j, w_j, dt, jacobians=True)
    e_plain, none = motion.constant_velocity_error(T_i, w_i, T_j, w_j, dt)
    assert none is None and np.allclose(e0, e_plain)
    h = 1e-6
    args = [T_i, w_i, T_j, w_j]
    for n in range(4):
        num = np.zeros((12, 6))
        for c in range(6):
            d = np.zeros(6)
            d[c] = h
            plus, minus = list(args), list(args)
            if n in (0, 2):  # poses: right perturbation, the Pose3 retraction
                plus[n], minus[n] = args[n].retract(d), args[n].retract(-d)
            else:  # twists: vectors
                plus[n], minus[n] = args[n] + d, args[n] - d
            num[:, c] = (motion.constant_velocity_error(*plus, dt)[0]
                         - motion.constant_velocity_error(*minus, dt)[0]) / (2 * h)
        assert np.allclose(Hs[n], num, atol=1e-5), (n, np.abs(Hs[n] - num).max())


def test_error_is_zero_on_a_constant_twist_and_grows_with_acceleration():
    T_i = xyzrpy_to_T(1.0, -2.0, 0.5, 0.1, -0.2, 0.7)
    w = np.array([0.1, -0.05, 0.8, 1.2, 0.1, -0.05])
    T_j = motion.predict(T_i, w, 0.5)
    e, _ = motion.constant_velocity_error(gtsam.Pose3(T_i), w, gtsam.Pose3(T_j), w, 0.5)
    assert np.abs(e).max() < 1e-9
    w2 = w + np.r_[0.0, 0.0, 0.3, 0.0, 0.0, 0.0]
    e2, _ = motion.constant_velocity_error(gtsam.Pose3(T_i), w, gtsam.Pose3(T_j), w2, 0.5)
    assert np.allclose(e2[6:], w2 - w) and np.abs(e2[:6]).max() < 1e-9


def test_factor_error_is_the_mahalanobis_norm_under_the_wnoa_covariance():
    from gtsam.symbol_shorthand import V, X

    noise = MotionNoise(sigma_rot=0.7, sigma_trans=0.4)
    dt = 0.5
    f = motion.constant_velocity_factor(X(0), V(0), X(1), V(1), dt, noise)
    vals = gtsam.Values()
    T_i, T_j = _pose([0.1, 0.2, -0.3, 1.0, 2.0, 0.5]), _pose([0.2, 0.1, 0.1, 1.4, 2.2, 0.4])
    w_i, w_j = np.array([0.1, 0, 0.2, 0.5, 0, 0]), np.array([0.0, 0.1, 0.3, 0.7, 0.1, 0])
    vals.insert(X(0), T_i)
    vals.insert(V(0), w_i)
    vals.insert(X(1), T_j)
    vals.insert(V(1), w_j)
    e, _ = motion.constant_velocity_error(T_i, w_i, T_j, w_j, dt)
    Q = motion.wnoa_covariance(dt, noise)
    assert np.allclose(Q, Q.T) and np.all(np.linalg.eigvalsh(Q) > 0)
    assert f.error(vals) == pytest.approx(0.5 * e @ np.linalg.solve(Q, e), rel=1e-9)
    # the pose block of Q(dt) is what prediction_sigma reports
    s_rot, s_trans = noise.prediction_sigma(dt)
    assert s_rot == pytest.approx(np.sqrt(Q[0, 0])) and s_trans == pytest.approx(np.sqrt(Q[3, 3]))
    with pytest.raises(ValueError):
        motion.constant_velocity_factor(X(0), V(0), X(1), V(1), 0.0, noise)


def test_predict_twist_between_and_velocity_round_trip():
    T_a = xyzrpy_to_T(3.0, 1.0, -0.2, 0.05, 0.1, -1.0)
    w = np.array([0.02, -0.1, 0.6, 1.5, -0.2, 0.1])
    T_b = motion.predict(T_a, w, 0.4)
    assert np.allclose(motion.twist_between(T_a, T_b, 0.4), w, atol=1e-9)
    table = motion.predict(T_a, w, np.array([0.0, 0.2, 0.4]))
    assert table.shape == (3, 4, 4) and np.allclose(table[0], T_a) and np.allclose(table[2], T_b)
    v_map = np.array([1.0, -2.0, 0.3])
    tw = motion.body_twist_from_map_velocity(T_a, v_map)
    assert np.allclose(tw[:3], 0) and np.allclose(motion.map_velocity(T_a, tw), v_map)


@pytest.mark.parametrize("gravity", [np.array([0, 0, -9.81]), np.array([0, 0, 9.81])])
def test_rotated_predictions_turn_about_the_vertical_and_the_body_axes(gravity):
    T = xyzrpy_to_T(5.0, -3.0, 1.0, 0.3, -0.2, 0.4)  # tilted: yaw must still be about the vertical
    cands = motion.rotated_predictions(T, gravity, yaw_deg=(30.0, -45.0), tilt_deg=(15.0,))
    assert [c[0] for c in cands] == ["yaw+30", "yaw-45", "roll+15", "pitch+15"]
    up = -gravity / np.linalg.norm(gravity)
    for (label, Tc), angle in zip(cands, (30.0, -45.0, 15.0, 15.0)):
        assert np.allclose(Tc[:3, 3], T[:3, 3])  # turned about the body origin
        dR = Tc[:3, :3] @ T[:3, :3].T
        assert np.rad2deg(rotation_angle(dR)) == pytest.approx(abs(angle))
        if label.startswith("yaw"):
            assert np.allclose(dR @ up, up)  # the vertical is the axis
    roll = cands[2][1]
    assert np.allclose(T[:3, :3].T @ roll[:3, :3] @ [1, 0, 0], [1, 0, 0])  # about body x
    assert motion.rotated_predictions(T, gravity) == []


def test_extrapolation_jacobians_match_finite_differences():
    T = _pose([0.3, -0.2, 0.5, 1.0, -2.0, 0.4])
    w = np.array([0.2, -0.1, 0.9, 1.5, 0.2, -0.1])
    tau = -0.05
    J_x, J_v = motion.extrapolation_jacobians(w, tau)

    def out(Tp, wp):
        return gtsam.Pose3(motion.predict(Tp.matrix(), wp, tau))

    base = out(T, w)
    h = 1e-6
    for c in range(6):
        d = np.zeros(6)
        d[c] = h
        num_x = (base.localCoordinates(out(T.retract(d), w)) - base.localCoordinates(out(T.retract(-d), w))) / (2 * h)
        num_v = (base.localCoordinates(out(T, w + d)) - base.localCoordinates(out(T, w - d))) / (2 * h)
        assert np.allclose(J_x[:, c], num_x, atol=1e-6) and np.allclose(J_v[:, c], num_v, atol=1e-6)
