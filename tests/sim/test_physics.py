"""Physical consistency of the simulator: IMU vs ground truth, scans vs the world, distortion."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.geometry import inv_T, so3_exp
from blockloc.sim.stream import open_sim_sequence
from blockloc.sim.trajectory import D4

G_MAP = np.array([0.0, 0.0, 9.81])  # NCLT map frame, z down


@pytest.fixture(scope="module")
def tiny_map():
    """Every error source off: the exact checks below hold to numerical precision (the errors
    have their own tests in test_realism_switches.py)."""
    return open_sim_sequence("tiny", "map", 3, ideal=True)


@pytest.fixture(scope="module")
def tiny_loc():
    return open_sim_sequence("tiny", "loc", 3, ideal=True)


def _integrate(T0, v0, t, acc, gyro):
    """Trapezoidal strapdown integration in the map frame (z down, gravity +z)."""
    R, p, v = T0[:3, :3].copy(), T0[:3, 3].copy(), v0.copy()
    out = [p.copy()]
    for k in range(len(t) - 1):
        dt = t[k + 1] - t[k]
        R1 = R @ so3_exp(0.5 * (gyro[k] + gyro[k + 1]) * dt)
        a0 = R @ acc[k] + G_MAP
        a1 = R1 @ acc[k + 1] + G_MAP
        p = p + v * dt + (2 * a0 + a1) / 6 * dt * dt
        v = v + 0.5 * (a0 + a1) * dt
        R = R1
        out.append(p.copy())
    return np.array(out), R


def test_noise_free_imu_reproduces_ground_truth(tiny_map):
    traj = tiny_map.trajectory
    # a 10 s window with motion: speed-ups, curves or turns in place
    speed = np.hypot(traj._sx(np.arange(0, traj.duration, 0.5), 1), traj._sy(np.arange(0, traj.duration, 0.5), 1))
    t0 = float(np.arange(0, traj.duration, 0.5)[np.argmax(speed > 0.5)])
    t = t0 + np.arange(0, 1001) * 0.01
    acc, gyro = traj.imu_ideal(t)
    T = traj.T_map_body(t)
    h = 1e-3
    v0 = (traj.T_map_body(t0 + h)[0, :3, 3] - traj.T_map_body(t0 - h)[0, :3, 3]) / (2 * h)
    pos, R_end = _integrate(T[0], v0, t, acc, gyro)
    err = np.linalg.norm(pos - T[:, :3, 3], axis=1)
    assert np.linalg.norm(T[-1, :3, 3] - T[0, :3, 3]) > 5.0  # the window really moves
    assert err.max() < 0.01, err.max()  # measured: ~3e-5 m
    rot_err = np.linalg.norm(so3_exp(np.zeros(3)) - R_end.T @ T[-1, :3, :3])
    assert rot_err < 2e-3


def test_imu_at_rest_reads_minus_gravity_plus_bias(tiny_map):
    imu = tiny_map.imu()
    rest = imu.t < imu.t[0] + 1.5  # the drive starts with 2 s standing still
    mean_acc = imu.acc[rest].mean(axis=0)
    # body z down and nearly level: specific force ~ (0, 0, -9.81) with tilt from the terrain
    assert abs(np.linalg.norm(mean_acc) - 9.81) < 0.1
    assert mean_acc[2] < -9.5
    ba, bg = tiny_map.imu_bias
    assert np.linalg.norm(ba[0]) > 1e-4 and np.linalg.norm(bg[0]) > 1e-5  # non-zero initial bias
    gyro_rest = imu.gyro[rest].mean(axis=0)
    # at rest the gyro reads its bias (+ white noise 0.005 rad/s a sample, ~0.0004 on the mean)
    assert np.allclose(gyro_rest, bg[rest].mean(axis=0), atol=1.5e-3)
    assert imu.acc[rest].std(axis=0).max() > 0.005  # white noise present


def test_trajectory_is_c2_and_on_the_terrain(tiny_map):
    traj = tiny_map.trajectory
    t = np.arange(0.0, traj.duration, 0.005)
    a = np.stack([traj._sx(t, 2), traj._sy(t, 2)], axis=1)
    jumps = np.linalg.norm(np.diff(a, axis=0), axis=1)
    assert jumps.max() < 0.05  # continuous acceleration (no polyline corners)
    p = traj.position(t)
    ground = tiny_map.world.terrain.height(p[:, 0], p[:, 1])
    assert np.allclose(p[:, 2] - ground, traj.body_height_m)
    T = traj.T_map_body(t[::200])
    # lidar about 1 m above ground: body z down, lidar 0.957 m above the body origin
    T_ml = T @ tiny_map.info.T_body_lidar
    lidar_up = -(T_ml[:, 2, 3]) - (-(T[:, 2, 3]) - traj.body_height_m)
    assert np.all(np.abs(lidar_up - 1.05) < 0.05)
    v = np.hypot(traj._sx(t, 1), traj._sy(t, 1))
    assert 1.0 <= v.max() <= 1.5 + 1e-6
    assert (v < 0.01).mean() > 0.02  # stops and turns in place exist


def _world_points(seq, frame, per_point_time=True, shift_s=0.0):
    t_rel = frame.stamp - seq.epoch_us * 1e-6 + shift_s
    times = t_rel + (frame.time_offsets.astype(np.float64) if per_point_time else np.zeros(len(frame)))
    # map-frame ground truth at each point's time, through the extrinsic, back to the z-up world
    uniq, inv = np.unique(np.round(times, 7), return_inverse=True)
    T_map_lidar = seq.trajectory.T_map_body(uniq) @ seq.info.T_body_lidar
    T_world_lidar = D4 @ T_map_lidar
    P = np.einsum("nij,nj->ni", T_world_lidar[inv][:, :3, :3], frame.points) + T_world_lidar[inv][:, :3, 3]
    return P


def test_scan_points_lie_on_world_surfaces(tiny_map):
    frame, cat = tiny_map.frame_with_labels(200)
    static = ~np.isin(np.array(tiny_map.scene.categories)[cat], ["pedestrian", "vehicle"])
    assert len(frame) > 5000 and static.mean() > 0.8
    P = _world_points(tiny_map, frame)[static]
    d = tiny_map.scene.distance(P)
    # range noise sigma 2 cm: 99% within 3 sigma-ish along the ray, none far off
    assert np.quantile(d, 0.5) < 0.02
    assert np.quantile(d, 0.99) < 0.07
    # ground truth of another time does not fit: the check can fail
    T_a, T_b = tiny_map.trajectory.T_map_body(np.array([20.0, 21.0]) + frame.stamp - tiny_map.epoch_us * 1e-6 - 20.0)
    assert np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]) > 0.3  # the robot moves in that second
    wrong = _world_points(tiny_map, frame, shift_s=1.0)[static]
    # (most points are ground, which still fits a pose moved along it: compare the tail)
    assert np.quantile(tiny_map.scene.distance(wrong), 0.9) > 5 * np.quantile(d, 0.9)
    # per-point fields
    assert frame.ring.max() == 31 and frame.ring.min() == 0
    assert 0 <= frame.time_offsets.min() and frame.time_offsets.max() < 0.1
    assert 0 <= frame.intensity.min() and frame.intensity.max() <= 255
    r = np.linalg.norm(frame.points, axis=1)
    assert r.max() <= 100.1 and r.min() >= 0.85


def test_elevations_are_hdl32e(tiny_map):
    frame = tiny_map.frame(50)
    el = np.rad2deg(np.arcsin(-frame.points[:, 2] / np.linalg.norm(frame.points, axis=1)))  # z down
    from blockloc.sim.lidar import HDL32E_ELEVATION_DEG

    assert np.allclose(el, HDL32E_ELEVATION_DEG[frame.ring], atol=1e-3)
    assert el.min() == pytest.approx(-30.67, abs=1e-3)


def test_fast_turn_shows_motion_distortion(tiny_map):
    traj = tiny_map.trajectory
    stamps = tiny_map.frame_stamps() - tiny_map.epoch_us * 1e-6
    yaw_rate = np.abs(traj._sp(stamps + 0.05, 1))
    i = int(np.argmax(yaw_rate))
    assert yaw_rate[i] > 0.4  # a turn in place at ~0.6 rad/s peak
    frame, cat = tiny_map.frame_with_labels(i)
    from blockloc.sim.lidar import HDL32E_ELEVATION_DEG

    static = ~np.isin(np.array(tiny_map.scene.categories)[cat], ["pedestrian", "vehicle"])
    # beams near horizontal hit structures; ground points rotated about the vertical stay on the
    # ground and would hide the effect
    sel = static & (HDL32E_ELEVATION_DEG[frame.ring] > -8)
    d_true = tiny_map.scene.distance(_world_points(tiny_map, frame)[sel])
    d_skew = tiny_map.scene.distance(_world_points(tiny_map, frame, per_point_time=False)[sel])
    # read without deskewing, points land off the surfaces by up to yaw_rate * 0.1 s * range
    assert np.quantile(d_true, 0.9) < 0.04
    assert np.quantile(d_skew, 0.9) > 0.3
    assert np.median(d_skew) > 10 * np.median(d_true)
    # the same check on a frame at rest shows no distortion
    still = int(np.argmin(np.abs(traj._sp(stamps + 0.05, 1)) + np.hypot(traj._sx(stamps + 0.05, 1), traj._sy(stamps + 0.05, 1))))
    f2, c2 = tiny_map.frame_with_labels(still)
    s2 = ~np.isin(np.array(tiny_map.scene.categories)[c2], ["pedestrian", "vehicle"])
    s2 &= HDL32E_ELEVATION_DEG[f2.ring] > -8
    d2 = tiny_map.scene.distance(_world_points(tiny_map, f2, per_point_time=False)[s2])
    assert np.quantile(d2, 0.9) < 0.04


def test_moving_actors_are_cast_exactly(tiny_loc):
    """The per-scan actor scene (only rays aimed near an actor are cast) finds every actor hit a
    brute-force cast of all rays finds; and actors do appear in scans."""
    from blockloc.open3d_loader import open3d
    from blockloc.sim.lidar import beam_directions

    o3d = open3d()
    tiny_map = tiny_loc
    scene = tiny_map.scene
    total = 0
    for t0 in np.arange(5.0, tiny_map.trajectory.duration - 1, 7.0):
        A = 180
        T = tiny_map.T_world_lidar(t0 + np.arange(A) * 0.1 / A)
        d, _ = beam_directions(A)
        dirs = np.matmul(d, T[:, :3, :3].transpose(0, 2, 1)).reshape(-1, 3)
        org = np.repeat(T[:, :3, 3], 32, axis=0)
        _, _, _, cat = scene.cast(org, dirs, t0, 100.0)
        static_r, _, _, _ = scene.cast(org, dirs, None, 100.0)
        V, F, _ = scene.actor_mesh(t0, org[0], 110.0)
        if not len(F):
            continue
        dyn = o3d.t.geometry.RaycastingScene()
        dyn.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
        r_dyn = dyn.cast_rays(o3d.core.Tensor(np.c_[org, dirs].astype(np.float32)))["t_hit"].numpy()
        brute = r_dyn < static_r
        names = np.array(scene.categories + ["none"])[cat]
        ours = np.isin(names, ["pedestrian", "vehicle"])
        assert np.array_equal(brute, ours)
        total += int(ours.sum())
    assert total > 20
