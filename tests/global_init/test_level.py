"""Gravity from the scan (floor plane), synthetic rooms and the real Hilti walk; NDT refinement."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.errors import GlobalInitError
from blockloc.geometry import rpy_to_R
from blockloc.registration.engines import make_engine
from blockloc.global_init.level import (gravity_from_scan, refine_gravity_by_ndt,
                                        up_hint_from_gravity_map)


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def _grid(u, v, origin, du, dv, step=0.1):
    s, t = np.meshgrid(np.arange(0, u, step), np.arange(0, v, step), indexing="ij")
    return origin + s.reshape(-1, 1) * du + t.reshape(-1, 1) * dv


def _corridor(width=2.0, height=4.0, length=30.0, sensor_h=1.2, floor=True, ceiling=True,
              table=False, seed=0):
    """A corridor along x in a level world (z up), as seen from a sensor at the origin,
    ``sensor_h`` above the floor: walls dominate (twice the floor's area each)."""
    x, y, z = np.eye(3)
    o = np.array([-length / 2, -width / 2, -sensor_h])
    parts = [_grid(length, height, o, x, z), _grid(length, height, o + width * y, x, z)]
    if floor:
        parts.append(_grid(length, width, o, x, y))
    if ceiling:
        parts.append(_grid(length, width, o + height * z, x, y))
    if table:  # a 1.5 x 1 m table top 0.75 m above the floor
        parts.append(_grid(1.5, 1.0, np.array([1.0, -0.5, -sensor_h + 0.75]), x, y, step=0.05))
    pts = np.concatenate(parts)
    rng = np.random.default_rng(seed)
    return pts + rng.normal(0.0, 0.01, pts.shape)


def _sensor_view(points_world, roll, pitch, yaw=0.3):
    """Points in a sensor frame rotated by (roll, pitch, yaw) from the level world; returns
    (points_sensor, true gravity direction in the sensor frame)."""
    R_ws = rpy_to_R(roll, pitch, yaw)
    return points_world @ R_ws, R_ws.T @ np.array([0.0, 0.0, -1.0])


@pytest.mark.parametrize("roll_deg,pitch_deg", [(0, 0), (30, -10), (-20, 25), (5, 37)])
def test_wall_dominated_corridor(roll_deg, pitch_deg):
    pts, g_true = _sensor_view(_corridor(), np.radians(roll_deg), np.radians(pitch_deg))
    est = gravity_from_scan(pts)
    assert est.method == "floor"
    assert _angle_deg(est.direction, g_true) < 0.2
    assert est.floor_distance_m == pytest.approx(1.2, abs=0.02)
    assert 0.8 < est.confidence <= 1.0
    np.testing.assert_allclose(est.gravity, 9.81 * est.direction)


def test_table_top_does_not_replace_the_floor():
    pts, g_true = _sensor_view(_corridor(table=True), np.radians(12), np.radians(-8))
    est = gravity_from_scan(pts)
    assert est.floor_distance_m == pytest.approx(1.2, abs=0.02)  # not the table's 0.45 m
    assert _angle_deg(est.direction, g_true) < 0.2


def test_ceiling_only_falls_back_to_the_normal_vote():
    pts, g_true = _sensor_view(_corridor(floor=False), np.radians(15), np.radians(5))
    est = gravity_from_scan(pts)
    assert est.method == "normals" and np.isnan(est.floor_distance_m)
    assert _angle_deg(est.direction, g_true) < 1.0
    floor_est = gravity_from_scan(_sensor_view(_corridor(), np.radians(15), np.radians(5))[0])
    assert est.confidence < 0.5 < floor_est.confidence


def test_z_down_body_frame():
    up = up_hint_from_gravity_map((0.0, 0.0, 9.81))  # NCLT-style map, z down
    np.testing.assert_allclose(up, [0, 0, -1])
    flip = np.diag([1.0, -1.0, -1.0])  # body x fwd, y right, z down
    pts, g_true = _sensor_view(_corridor(), np.radians(10), np.radians(4))
    est = gravity_from_scan(pts @ flip.T, up_hint=up)
    assert _angle_deg(est.direction, flip @ g_true) < 0.2


def test_outside_the_cone_or_no_planes_raise():
    rng = np.random.default_rng(3)
    blob = rng.normal(0.0, 5.0, (20000, 3))
    with pytest.raises(GlobalInitError, match="no planar surface within 45 deg"):
        gravity_from_scan(blob)
    with pytest.raises(GlobalInitError, match="expected at least 50"):
        gravity_from_scan(np.zeros((10, 3)))
    # a sensor lying on its side (90 deg roll): with the default hint the floor is out of the
    # cone; given a hint within 45 deg it is found again
    pts, g_true = _sensor_view(_corridor(ceiling=False), np.radians(90), 0.0)
    est = gravity_from_scan(pts, up_hint=-g_true + [0.3, 0.2, 0.0])
    assert _angle_deg(est.direction, g_true) < 0.2


# ----------------------------------------------------------------------------- the real walk


@pytest.fixture(scope="module")
def walk(shared_data):
    from blockloc.datasets.scanfolder import ScanFolderSequence

    root = shared_data / "balm_hilti_walk"
    return ScanFolderSequence(root / "scans", poses=root / "poses_T_world_lidar.tum")


def test_real_walk_gravity_from_every_scan(walk):
    """All 177 scans: the floor normal, put into the world frame by the reference poses, is the
    same direction in every scan (the floor is one plane) and is the README's 2.8 deg from the
    world frame's -z (the first scan's frame is not level)."""
    gt = walk.ground_truth()
    g_world, err_ref = [], []
    for i in range(len(walk)):
        est = gravity_from_scan(walk.frame(i).points)
        assert est.method == "floor" and est.confidence > 0.5, i
        R_wl = gt.poses[i, :3, :3]
        g_world.append(R_wl @ est.direction)
        err_ref.append(_angle_deg(est.direction, R_wl.T @ [0.0, 0.0, -1.0]))
    g_world = np.array(g_world)
    mean = g_world.mean(axis=0) / np.linalg.norm(g_world.mean(axis=0))
    spread = np.array([_angle_deg(g, mean) for g in g_world])
    assert np.median(spread) < 0.2 and spread.max() < 0.6
    assert 2.3 < _angle_deg(mean, [0, 0, -1]) < 3.3
    assert 2.3 < np.median(err_ref) < 3.3 and max(err_ref) < 3.6


def test_real_walk_ndt_refines_roll_and_pitch(walk):
    """A candidate 3 deg off in roll and 2 deg in pitch is pulled back onto the map's vertical."""
    from blockloc.geometry import transform_points
    from blockloc.global_init.refine import Refiner

    gt = walk.ground_truth()
    i = 60
    neighbours = [j for j in range(i - 8, i + 9, 2) if j != i]
    map_pts = np.concatenate([transform_points(gt.poses[j], walk.frame(j).points) for j in neighbours])
    T_ref = gt.poses[i]
    T_cand = T_ref.copy()
    T_cand[:3, :3] = T_ref[:3, :3] @ rpy_to_R(np.radians(3.0), np.radians(-2.0), 0.0)
    T_cand[:3, 3] += [0.15, -0.1, 0.05]
    g_map = np.array([0.0, 0.0, -9.81])
    T_out, est = refine_gravity_by_ndt(Refiner(make_engine("ndt", resolution_m=1.0), map_pts), walk.frame(i).points,
                                       T_cand, g_map)
    g_true = T_ref[:3, :3].T @ [0.0, 0.0, -1.0]
    assert _angle_deg(T_cand[:3, :3].T @ [0, 0, -1.0], g_true) > 3.0
    assert est.method == "ndt" and est.confidence > 0.5
    assert _angle_deg(est.direction, g_true) < 0.3
    assert np.linalg.norm(T_out[:3, 3] - T_ref[:3, 3]) < 0.05
