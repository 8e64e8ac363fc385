import numpy as np

from blockloc.geometry import inv_T, transform_points
from blockloc import deskew as dsk
from tests.tracking.synthetic import T_BODY_LIDAR, CircleTrajectory, make_scan, make_scene


def test_deskew_with_true_motion_recovers_the_undistorted_scan():
    traj = CircleTrajectory(speed=6.0, radius=8.0)  # fast turn: strong distortion
    scene = make_scene(seed=3)
    stamp = 2.0
    frame = make_scan(scene, traj, stamp, T_BODY_LIDAR, max_points=5000, noise_m=0.0)
    # where the points really are in the lidar frame at the stamp
    T_map_lidar = traj.pose(stamp)[0] @ T_BODY_LIDAR
    T_at = traj.pose(stamp + frame.time_offsets.astype(np.float64)) @ T_BODY_LIDAR
    world = np.einsum("nij,nj->ni", T_at[:, :3, :3], frame.points.astype(np.float64)) + T_at[:, :3, 3]
    truth = transform_points(inv_T(T_map_lidar), world)
    raw_err = np.linalg.norm(frame.points - truth, axis=1).max()
    assert raw_err > 0.3  # the distortion is real

    table_t = np.linspace(stamp - 0.1, stamp, 11)
    table = dsk.lidar_motion_table(traj.pose(table_t), T_BODY_LIDAR, 10)
    out = dsk.deskew_points(frame.points, stamp + frame.time_offsets, table_t, table)
    assert np.linalg.norm(out - truth, axis=1).max() < 0.01
    ref = dsk.deskew_points_numpy(frame.points, stamp + frame.time_offsets, table_t, table)
    np.testing.assert_allclose(out, ref, atol=1e-9)


def test_single_pose_table_is_a_rigid_transform():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(100, 3))
    T = CircleTrajectory().pose(1.0)[0]
    out = dsk.deskew_points(pts, np.zeros(100), np.array([0.0]), T[None])
    np.testing.assert_allclose(out, transform_points(T, pts))


def test_voxel_downsample_keeps_one_real_point_per_voxel():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-5, 5, size=(20000, 3))
    idx = dsk.voxel_downsample_indices(pts, 1.0)
    keys = np.floor(pts[idx] / 1.0).astype(int)
    assert len(np.unique(keys, axis=0)) == len(idx) == 1000  # every voxel once
    assert np.all(np.diff(idx) > 0)
    capped = dsk.voxel_downsample_indices(pts, 1.0, max_points=300, seed=2)
    assert len(capped) == 300 and set(capped) <= set(idx)
    np.testing.assert_array_equal(capped, dsk.voxel_downsample_indices(pts, 1.0, max_points=300, seed=2))


def test_range_filter():
    pts = np.array([[0.5, 0, 0], [2, 0, 0], [200, 0, 0], [np.nan, 0, 0]])
    np.testing.assert_array_equal(dsk.range_filter(pts, 1.0, 100.0), [False, True, False, False])


def test_interval_rotation_vectors_equal_the_scipy_log():
    from blockloc._deskew_kernels import interval_rotvecs
    from blockloc.geometry import so3_log

    rng = np.random.default_rng(5)
    # tiny (a sweep's IMU steps), moderate, zero, and near-pi turns between table entries
    angles = np.r_[1e-9, 1e-6, 1e-4, 3e-3, 0.05, 0.4, 1.5, 0.0, 2.9, 3.1]
    axes = rng.normal(size=(len(angles), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    from scipy.spatial.transform import Rotation

    steps = Rotation.from_rotvec(axes * angles[:, None]).as_matrix()
    R = [Rotation.from_rotvec(rng.normal(size=3)).as_matrix()]
    for S in steps:
        R.append(R[-1] @ S)
    R = np.ascontiguousarray(R)
    w, ok = interval_rotvecs(R[:-1])  # up to 2.9 rad: the kernel's own log
    assert ok
    np.testing.assert_allclose(w, so3_log(np.swapaxes(R[:-2], 1, 2) @ R[1:-1]), atol=1e-9, rtol=1e-7)
    _, ok = interval_rotvecs(R)  # 3.1 rad: the caller's exact log instead
    assert not ok
    pts = rng.uniform(-10, 10, (500, 3))
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = rng.normal(size=(len(R), 3))
    table_t = np.arange(len(R)) * 0.01
    times = rng.uniform(-0.01, table_t[-1] + 0.01, len(pts))
    np.testing.assert_allclose(dsk.deskew_points(pts, times, table_t, T),
                               dsk.deskew_points_numpy(pts, times, table_t, T), atol=1e-9)
