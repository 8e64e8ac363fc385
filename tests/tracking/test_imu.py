import numpy as np
import pytest

from blockloc.geometry import rotation_angle, xyzrpy_to_T
from blockloc.tracking.imu import ImuBuffer, ImuNoise, integrate, make_preintegration_params, predict_states
from tests.tracking.synthetic import CircleTrajectory, imu_from_trajectory


@pytest.mark.parametrize("z_up", [True, False])
@pytest.mark.parametrize("T_body_imu", [np.eye(4), xyzrpy_to_T(0.2, 0.0, -0.1, 0.0, 0.1, 0.5)])
def test_preintegrated_exact_imu_reproduces_the_trajectory(z_up, T_body_imu):
    import gtsam

    traj = CircleTrajectory(z_up=z_up)
    imu = imu_from_trajectory(traj, 0.0, 3.0, rate_hz=200.0, T_body_imu=T_body_imu)
    buf = ImuBuffer()
    for t, a, w in zip(imu.t, imu.acc, imu.gyro):
        buf.insert(t, a, w)
    params = make_preintegration_params(traj.gravity_map, T_body_imu, ImuNoise())
    t0, t1 = 0.5, 2.5
    state = gtsam.NavState(gtsam.Pose3(traj.pose(t0)[0]), traj.velocity(t0)[0])
    poses, vels = predict_states(params, state, gtsam.imuBias.ConstantBias(), buf, t0, np.array([1.5, t1]))
    gt = traj.pose(t1)[0]
    assert np.linalg.norm(poses[-1][:3, 3] - gt[:3, 3]) < 0.02
    assert np.rad2deg(rotation_angle(poses[-1][:3, :3].T @ gt[:3, :3])) < 0.1
    assert np.linalg.norm(vels[-1] - traj.velocity(t1)[0]) < 0.02
    # and without the right gravity the same data drifts by metres: gravity is really used
    flipped = make_preintegration_params(-traj.gravity_map, T_body_imu, ImuNoise())
    bad, _ = predict_states(flipped, state, gtsam.imuBias.ConstantBias(), buf, t0, np.array([t1]))
    assert np.linalg.norm(bad[-1][:3, 3] - gt[:3, 3]) > 5.0


def test_buffer_zero_order_hold_covers_gaps_and_reports_them():
    buf = ImuBuffer()
    ts = np.r_[np.arange(0.0, 1.0, 0.01), np.arange(1.3, 2.0, 0.01)]  # a 0.3 s gap
    for t in ts:
        buf.insert(t, np.array([t, 0, 0]), np.zeros(3))
    assert not buf.insert(0.5, np.zeros(3), np.zeros(3))  # out of order ignored
    acc, gyro, dt, gap = buf.segments(0.95, 1.5)
    assert dt.sum() == pytest.approx(0.55)
    assert gap == pytest.approx(0.31, abs=1e-6)
    held = acc[np.argmax(dt)]
    assert held[0] == pytest.approx(0.99)  # the last sample before the gap holds across it
    _, _, dt2, gap2 = buf.segments(0.2, 0.5)
    assert gap2 == pytest.approx(0.01, abs=1e-6) and dt2.sum() == pytest.approx(0.3)
    # past the newest sample the last one holds
    _, _, dt3, gap3 = buf.segments(1.9, 2.5)
    assert dt3.sum() == pytest.approx(0.6) and gap3 > 0.5
    buf.discard_before(1.5)
    assert buf._t[0] <= 1.5 < buf._t[1]


def test_integrate_through_a_gap_stays_close_for_smooth_motion():
    import gtsam

    traj = CircleTrajectory()
    imu = imu_from_trajectory(traj, 0.0, 3.0)
    keep = (imu.t < 1.2) | (imu.t > 1.5)
    buf = ImuBuffer()
    for t, a, w in zip(imu.t[keep], imu.acc[keep], imu.gyro[keep]):
        buf.insert(t, a, w)
    params = make_preintegration_params(traj.gravity_map, np.eye(4), ImuNoise())
    pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
    gap = integrate(pim, buf, 1.0, 2.0)
    assert gap > 0.29
    state = gtsam.NavState(gtsam.Pose3(traj.pose(1.0)[0]), traj.velocity(1.0)[0])
    pred = pim.predict(state, gtsam.imuBias.ConstantBias()).pose().matrix()
    assert np.linalg.norm(pred[:3, 3] - traj.pose(2.0)[0][:3, 3]) < 0.05


def test_per_axis_noise_densities_reach_the_preintegration_covariances():
    from blockloc.errors import TrackingError

    axes = ImuNoise(acc_noise_axes=(0.03, 0.03, 0.35), gyro_noise_axes=(0.001, 0.002, 0.003))
    p = make_preintegration_params(np.array([0.0, 0.0, -9.81]), np.eye(4), axes, noise_inflation=2.0)
    np.testing.assert_allclose(np.diag(p.getAccelerometerCovariance()), (2 * np.array([0.03, 0.03, 0.35])) ** 2)
    np.testing.assert_allclose(np.diag(p.getGyroscopeCovariance()), (2 * np.array([0.001, 0.002, 0.003])) ** 2)
    scalar = make_preintegration_params(np.array([0.0, 0.0, -9.81]), np.eye(4), ImuNoise(acc_noise_density=0.01))
    np.testing.assert_allclose(scalar.getAccelerometerCovariance(), np.eye(3) * 1e-4)
    with pytest.raises(TrackingError, match="acc_noise_axes"):
        ImuNoise(acc_noise_axes=(0.1, 0.2))


def _predict_stepwise(params, state_i, bias, buffer, t_i, times):
    """The reference: integrate from one time to the next (buffer.segments per interval)."""
    import gtsam

    pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
    poses, vels, t_prev = [], [], t_i
    for t in times:
        if t > t_prev:
            integrate(pim, buffer, t_prev, t)
            t_prev = t
        s = pim.predict(state_i, bias) if pim.deltaTij() > 0 else state_i
        poses.append(s.pose().matrix())
        vels.append(s.velocity())
    return np.array(poses), np.array(vels)


def test_predict_states_in_one_pass_equals_integrating_interval_by_interval():
    import gtsam

    traj = CircleTrajectory()
    imu = imu_from_trajectory(traj, 0.0, 3.0, rate_hz=100.0)
    keep = (imu.t < 1.2) | (imu.t > 1.45)  # a gap inside the sweep
    buf = ImuBuffer()
    for t, a, w in zip(imu.t[keep], imu.acc[keep], imu.gyro[keep]):
        buf.insert(t, a, w)
    params = make_preintegration_params(traj.gravity_map, np.eye(4), ImuNoise())
    bias = gtsam.imuBias.ConstantBias(np.array([0.05, -0.02, 0.01]), np.array([0.001, 0.002, -0.001]))
    t_i = 1.003
    state = gtsam.NavState(gtsam.Pose3(traj.pose(t_i)[0]), traj.velocity(t_i)[0])
    rng = np.random.default_rng(3)
    # times on IMU samples, between them, repeated, before t_i, and past the newest sample
    times = np.sort(np.r_[0.9, t_i, imu.t[(imu.t > 1.0) & (imu.t < 1.6)][::3], rng.uniform(1.0, 1.6, 7), 1.3, 1.3, 3.2])
    times = np.maximum(times, t_i)
    got_T, got_v = predict_states(params, state, bias, buf, t_i, times)
    want_T, want_v = _predict_stepwise(params, state, bias, buf, t_i, times)
    np.testing.assert_allclose(got_T, want_T, atol=1e-9)
    np.testing.assert_allclose(got_v, want_v, atol=1e-9)
    assert np.linalg.norm(got_T[-1][:3, 3] - got_T[0][:3, 3]) > 1.0  # it moved
