"""Scan preparation for init: gyro deskew to mid-sweep, gravity from the accelerometer, levelling."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from blockloc.errors import BlocklocError
from blockloc.datasets.base import ImuData, LidarFrame, SequenceInfo
from blockloc.geometry import rpy_to_R
from blockloc.commands.common import parse_pose_hint
from blockloc.global_init.scan_prep import deskew_rotation, gravity_from_imu
from blockloc.global_init.projection import R_level_from_gravity, heading_offset, rotation_aligning, unique_cells


def _fake_seq(omega_z, acc=(0.0, 0.0, -9.81)):
    t = np.arange(0.0, 2.0, 0.01)
    imu = ImuData(t, np.tile(acc, (len(t), 1)), np.tile([0.0, 0.0, omega_z], (len(t), 1)))
    return SimpleNamespace(info=SequenceInfo("fake"), imu=lambda: imu)


def test_gyro_deskew_undoes_a_turn_in_place_during_the_sweep():
    omega = 1.0  # rad/s: 5.7 deg over a 0.1 s sweep, 5 m of smear at 50 m
    rng = np.random.default_rng(0)
    world = rng.uniform(-50, 50, (2000, 3))  # body frame at the reference (mid-sweep) time
    offs = np.sort(rng.uniform(0.0, 0.1, len(world)))
    stamp = 1.0
    t_ref = stamp + 0.5 * (offs.min() + offs.max())
    # the sensor turned by omega * (t - t_ref); it measured each point in its frame at its time
    R_i = rpy_to_R(0.0, 0.0, omega * (stamp + offs - t_ref))
    measured = np.einsum("nji,nj->ni", R_i, world)
    frame = LidarFrame(0, stamp, measured.astype(np.float64), time_offsets=offs.astype(np.float32))
    seq = _fake_seq(omega)
    out, t_out = deskew_rotation(frame, seq.imu(), seq.info)
    assert abs(t_out - t_ref) < 1e-6
    err = np.linalg.norm(out - world, axis=1)
    raw = np.linalg.norm(measured - world, axis=1)
    assert raw.max() > 2.0  # the smear is real
    assert err.max() < 0.05, err.max()


def test_gravity_from_the_accelerometer_and_levelling():
    # body rolled 5 deg, pitched -3 deg in a z-down world: the accelerometer reads -g in the body frame
    R_map_body = rpy_to_R(math.radians(5), math.radians(-3), 0.7)
    g_body = R_map_body.T @ np.array([0.0, 0.0, 9.81])
    seq = _fake_seq(0.0, acc=-g_body)
    g = gravity_from_imu(seq.imu(), 1.0, seq.info.T_body_imu)
    np.testing.assert_allclose(g, g_body, atol=1e-9)
    R_tilt = R_level_from_gravity(g)
    np.testing.assert_allclose(R_tilt @ (g / np.linalg.norm(g)), [0, 0, -1], atol=1e-12)
    assert abs(heading_offset(R_tilt)) < math.radians(10)  # levelling keeps the heading
    # rotation_aligning handles opposite vectors (z-down to z-up) with a proper rotation
    R = rotation_aligning(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
    np.testing.assert_allclose(R @ [0, 0, 1.0], [0, 0, -1.0], atol=1e-12)
    assert abs(np.linalg.det(R) - 1) < 1e-12


def test_parse_pose_hint():
    assert parse_pose_hint("1.5,-2") == (1.5, -2.0, None)
    assert parse_pose_hint("1,2,0.5") == (1.0, 2.0, 0.5)
    for bad in ("1", "1,2,3,4", "a,b", "nan,1"):
        with pytest.raises(BlocklocError, match="--init-pose .* expected x,y or x,y,yaw"):
            parse_pose_hint(bad, "--init-pose")


@pytest.mark.parametrize("n, span", [(0, 5), (1, 5), (7, 2), (5000, 300), (3, 2**40)])
def test_unique_cells_are_numpys_unique_rows(n, span):
    # sorted by x then y, with the inverse; a span too wide for one code falls back to numpy's
    cells = np.random.default_rng(n).integers(-span, span, (n, 2))
    want, want_inv = np.unique(cells.reshape(-1, 2), axis=0, return_inverse=True)
    got, inv = unique_cells(cells, return_inverse=True)
    assert np.array_equal(got, want) and got.dtype == want.dtype
    assert np.array_equal(inv, want_inv.reshape(-1))
    assert np.array_equal(unique_cells(cells), want)
