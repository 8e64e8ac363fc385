import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from blockloc.geometry import (
    R_to_rpy, T_to_xyzrpy, Trajectory, inv_T, rotation_angle, rpy_to_R, so3_exp, so3_log,
    transform_points, xyzrpy_to_T,
)

angles = st.floats(-np.pi + 1e-3, np.pi - 1e-3)
pitches = st.floats(-np.pi / 2 + 1e-2, np.pi / 2 - 1e-2)
coords = st.floats(-1e3, 1e3)


@given(coords, coords, coords, angles, pitches, angles)
def test_xyzrpy_round_trip(x, y, z, r, p, yaw):
    T = xyzrpy_to_T(x, y, z, r, p, yaw)
    np.testing.assert_allclose(T_to_xyzrpy(T), [x, y, z, r, p, yaw], atol=1e-7)


@given(angles, pitches, angles)
def test_rpy_matches_scipy_extrinsic_xyz(r, p, yaw):
    from scipy.spatial.transform import Rotation

    np.testing.assert_allclose(rpy_to_R(r, p, yaw), Rotation.from_euler("xyz", [r, p, yaw]).as_matrix(),
                               atol=1e-12)


@settings(max_examples=50)
@given(st.lists(coords, min_size=3, max_size=3), st.lists(st.floats(-3, 3), min_size=3, max_size=3))
def test_inverse_and_transform(t, w):
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array(w))
    T[:3, 3] = t
    np.testing.assert_allclose(inv_T(T) @ T, np.eye(4), atol=1e-9)
    pts = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_allclose(transform_points(inv_T(T), transform_points(T, pts)), pts, atol=1e-7)


@given(st.lists(st.floats(-3, 3), min_size=3, max_size=3))
def test_so3_exp_log(w):
    w = np.array(w)
    if np.linalg.norm(w) >= np.pi:
        w = w / np.linalg.norm(w) * 3.0
    R = so3_exp(w)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(so3_log(R), w, atol=1e-8)
    np.testing.assert_allclose(rotation_angle(R), np.linalg.norm(w), atol=1e-6)


def test_stacked_rpy_round_trip():
    rng = np.random.default_rng(1)
    rpy = rng.uniform([-3, -1.5, -3], [3, 1.5, 3], size=(20, 3))
    np.testing.assert_allclose(R_to_rpy(rpy_to_R(*rpy.T)), rpy, atol=1e-9)


def test_trajectory_interpolation_is_exact_at_stamps_and_between():
    stamps = np.array([0.0, 1.0, 2.0])
    poses = xyzrpy_to_T(np.array([0.0, 1.0, 2.0]), 0, 0, 0, 0, np.array([0.0, 0.2, 0.4]))
    traj = Trajectory(stamps, poses)
    np.testing.assert_allclose(traj.interpolate(stamps), poses, atol=1e-12)
    mid = traj.interpolate(np.array([0.5]))[0]
    np.testing.assert_allclose(T_to_xyzrpy(mid), [0.5, 0, 0, 0, 0, 0.1], atol=1e-12)
    assert traj.path_length() == 2.0


def test_interpolation_uses_only_the_poses_around_the_times_and_matches_the_whole_trajectory():
    """Interpolating from the poses that bracket the times asked for gives the bytes a Slerp over the
    whole trajectory gives (it did that before: seconds a call on a campus drive's 500k poses), at
    the ends, beyond them (clamped), on stamps and between, for two poses and for many."""
    from scipy.spatial.transform import Rotation, Slerp

    rng = np.random.default_rng(0)
    for n in (2, 3, 500):
        stamps = np.unique(rng.uniform(0.0, 100.0, n))
        poses = np.stack([xyzrpy_to_T(*rng.normal(size=3), *rng.uniform(-3.0, 3.0, 3)) for _ in stamps])
        traj = Trajectory(stamps, poses)
        whole = Slerp(stamps, Rotation.from_matrix(poses[:, :3, :3]))
        for t in (stamps[:1], stamps[-1:], np.array([-5.0]), np.array([200.0]), stamps[1:2],
                  rng.uniform(-1.0, 101.0, 50), np.array([stamps[0] + 1e-9])):
            tc = np.clip(t, stamps[0], stamps[-1])
            got = traj.interpolate(t)
            assert np.allclose(got[:, :3, :3], whole(tc).as_matrix(), atol=1e-12, rtol=0)
            assert np.allclose(got[:, :3, 3], np.stack([np.interp(tc, stamps, poses[:, k, 3]) for k in range(3)], 1),
                               atol=1e-12, rtol=0)
