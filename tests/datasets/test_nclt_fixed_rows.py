"""NCLT files parsed from fixed rows in the devkit's layout, with the values they must give.

Round trips (write, then read) cannot catch a reader and a writer that agree on a wrong column
order; these rows are written by hand.

- ``groundtruth_<date>.csv``: utime (us), x, y, z (m), roll, pitch, yaw (rad); the devkit's
  ``read_ground_truth.py`` reads columns 1..6 as x, y, z, r, p, h and its ``ssc_to_homo`` builds
  R = Rz(yaw) Ry(pitch) Rx(roll).
- ``ms25.csv``: utime, mag x y z (Gauss), accel x y z (m/s^2), rotation rate x y z (rad/s)
  (the NCLT paper's sensor table; public NCLT loaders read accel from columns 4..6 and the gyro
  from 7..9, e.g. the ORB-SLAM3 NCLT scripts' ``IMU(:, [1 8:10 5:7])`` in 1-based MATLAB indexing).
- ``velodyne_sync/<utime>.bin``: uint16 x, y, z (m = raw * 0.005 - 100), uint8 intensity, uint8
  laser id (the devkit's ``read_vel_sync.py``).
"""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.datasets.base import ImuData
from blockloc.datasets.nclt import (NCLT_POINT_DTYPE, decode_points, read_groundtruth_csv, read_ms25_csv,
                                    write_groundtruth_csv, write_ms25_csv)
from blockloc.geometry import Trajectory, xyzrpy_to_T

# roll 0.1, pitch -0.2, yaw 0.3 rad: R = Rz(0.3) Ry(-0.2) Rx(0.1), multiplied out by hand
# (Python's math module on the three elementary matrices, in a scratch shell).
ROLL, PITCH, YAW = 0.1, -0.2, 0.3
R_EXPECTED = np.array([
    [0.936293363584, -0.312991825785, -0.159345079308],
    [0.289629477626, 0.944702485995, -0.153791997989],
    [0.198669330795, 0.097843395007, 0.975170327202],
])
GT_ROWS = (
    "1326030000000000,10.5,-3.25,0.75,0.1,-0.2,0.3\n"
    "1326030000100000,11.0,-3.0,0.5,0,0,1.5707963267948966\n"
)


def test_groundtruth_row_gives_devkit_rotation(tmp_path):
    path = tmp_path / "groundtruth_2012-01-22.csv"
    path.write_text(GT_ROWS)
    traj = read_groundtruth_csv(path)
    np.testing.assert_allclose(traj.stamps, [1326030000.0, 1326030000.1], rtol=0, atol=1e-6)
    T = traj.poses[0]
    np.testing.assert_allclose(T[:3, 3], [10.5, -3.25, 0.75])
    np.testing.assert_allclose(T[:3, :3], R_EXPECTED, atol=1e-11)
    # pure yaw of 90 deg: body x along map y
    np.testing.assert_allclose(traj.poses[1][:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(traj.poses[1][:3, 3], [11.0, -3.0, 0.5])


def test_groundtruth_writer_puts_roll_pitch_yaw_in_their_columns(tmp_path):
    T = np.eye(4)
    T[:3, :3] = R_EXPECTED
    T[:3, 3] = [10.5, -3.25, 0.75]
    path = tmp_path / "gt.csv"
    write_groundtruth_csv(path, Trajectory(np.array([1326030000.0]), T[None]))
    cols = [float(v) for v in path.read_text().strip().split(",")]
    assert cols[0] == 1326030000000000
    np.testing.assert_allclose(cols[1:], [10.5, -3.25, 0.75, ROLL, PITCH, YAW], atol=1e-9)


def test_ms25_row_columns(tmp_path):
    path = tmp_path / "ms25.csv"
    # utime, mag x y z, accel x y z, gyro x y z: every value distinct
    path.write_text("1326030000000000,0.11,0.12,0.13,1.1,2.2,-9.7,0.01,0.02,0.03\n"
                    "1326030000010000,0.21,0.22,0.23,1.2,2.3,-9.8,0.04,0.05,0.06\n")
    imu = read_ms25_csv(path)
    np.testing.assert_allclose(imu.t, [1326030000.0, 1326030000.01], rtol=0, atol=1e-6)
    np.testing.assert_allclose(imu.acc, [[1.1, 2.2, -9.7], [1.2, 2.3, -9.8]])
    np.testing.assert_allclose(imu.gyro, [[0.01, 0.02, 0.03], [0.04, 0.05, 0.06]])


def test_ms25_writer_columns(tmp_path):
    path = tmp_path / "ms25.csv"
    write_ms25_csv(path, ImuData(np.array([1326030000.0]), np.array([[1.1, 2.2, -9.7]]),
                                 np.array([[0.01, 0.02, 0.03]])))
    cols = [float(v) for v in path.read_text().strip().split(",")]
    assert cols[0] == 1326030000000000
    np.testing.assert_allclose(cols[1:], [0, 0, 0, 1.1, 2.2, -9.7, 0.01, 0.02, 0.03])


def test_velodyne_sync_point_bytes():
    # raw (x, y, z) = (20200, 19000, 20001): (1.0, -5.0, 0.005) m; intensity 77, laser 12
    raw = np.frombuffer(bytes([0xE8, 0x4E, 0x38, 0x4A, 0x21, 0x4E, 77, 12]), dtype=NCLT_POINT_DTYPE)
    assert int(raw["x"][0]) == 20200 and int(raw["y"][0]) == 19000 and int(raw["z"][0]) == 20001
    xyz, intensity, laser = decode_points(raw)
    np.testing.assert_allclose(xyz, [[1.0, -5.0, 0.005]], atol=1e-6)
    assert intensity.tolist() == [77.0] and laser.tolist() == [12]


@pytest.mark.parametrize("roll, pitch, yaw", [(0.1, -0.2, 0.3), (0.5, 0.05, -2.0)])
def test_roll_and_pitch_are_not_interchangeable(tmp_path, roll, pitch, yaw):
    """A row with roll != pitch must not give the pose of the swapped row."""
    path = tmp_path / "gt.csv"
    path.write_text(f"1,0,0,0,{roll!r},{pitch!r},{yaw!r}\n")
    R = read_groundtruth_csv(path).poses[0][:3, :3]
    np.testing.assert_allclose(R, xyzrpy_to_T(0, 0, 0, roll, pitch, yaw)[:3, :3], atol=1e-12)
    assert np.abs(R - xyzrpy_to_T(0, 0, 0, pitch, roll, yaw)[:3, :3]).max() > 0.05
    # x axis of the body: (cos p cos y, cos p sin y, -sin p) in the map frame
    np.testing.assert_allclose(R[:, 0], [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw),
                                         -np.sin(pitch)], atol=1e-12)
