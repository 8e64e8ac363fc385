"""with_trajectory: a ROS bag or a scan folder with poses from a TUM/KITTI file."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from blockloc.datasets.base import Sequence
from blockloc.datasets.rosbag import RosbagSequence, write_rosbag
from blockloc.datasets.scanfolder import ScanFolderSequence
from blockloc.datasets.with_poses import (TrajectorySequence, covered_mask, match_trajectory,
                                          with_trajectory)
from blockloc.errors import DatasetError
from blockloc.trajectory_io import read_trajectory_file, write_kitti, write_tum
from blockloc.geometry import Trajectory, xyzrpy_to_T


def _traj(stamps) -> Trajectory:
    t = np.asarray(stamps, float)
    s = t - t[0]
    return Trajectory(t, xyzrpy_to_T(2.0 * s, -s, 0.1 * s, 0.01 * s, 0.0, 0.3 * s))


@pytest.fixture
def bag(tmp_path, session_data):
    path = write_rosbag(tmp_path / "rec.bag", iter(session_data["frames"]), session_data["imu"])
    seq = RosbagSequence(path, lidar_topic="/velodyne_points", imu_topic="/imu")
    yield seq
    seq.close()


def test_bag_with_fastlio_tum(tmp_path, bag):
    stamps = bag.frame_stamps()
    traj = _traj(np.arange(stamps[0] - 0.2, stamps[-1] + 0.2, 0.01))  # a 100 Hz odometry file
    write_tum(tmp_path / "fastlio.tum", traj)
    seq = with_trajectory(bag, tmp_path / "fastlio.tum", frame_name="camera_init")
    assert isinstance(seq, TrajectorySequence) and isinstance(seq, Sequence)
    assert seq.info.map_frame == "camera_init"
    assert seq.info.trajectory_source.endswith("fastlio.tum")
    assert seq.info.name == bag.info.name and seq.info.imu_rate_hz == bag.info.imu_rate_hz
    assert len(seq) == len(bag) and len(seq.imu()) == len(bag.imu())
    np.testing.assert_array_equal(seq.frame_stamps(), stamps)
    np.testing.assert_array_equal(seq.frame(1).points, bag.frame(1).points)
    assert seq.path == bag.path  # passed through
    gt = seq.mapping_poses()
    assert seq.ground_truth() is gt and bag.ground_truth() is None
    # interpolated by time at the frame stamps: the file's motion, not the bag's
    np.testing.assert_allclose(gt.interpolate(stamps), traj.interpolate(stamps), atol=1e-6)
    assert len(seq.uncovered_frames()) == 0


def test_map_built_from_wrapped_bag_uses_file_poses(tmp_path, bag):
    from blockloc.maps.mapping import mapping_keyframes

    stamps = bag.frame_stamps()
    traj = _traj(np.arange(stamps[0] - 0.2, stamps[-1] + 0.2, 0.01))
    seq = with_trajectory(bag, traj)
    assert seq.info.map_frame == "map"
    kfs = list(mapping_keyframes(seq, keyframe_distance_m=0.0, keyframe_angle_deg=0.0, deskew=False))
    assert [k.index for k in kfs] == list(range(len(bag)))
    for k in kfs:
        np.testing.assert_allclose(k.T_map_lidar, traj.interpolate([stamps[k.index]])[0], atol=1e-6)


def test_partial_trajectory_names_uncovered_frames(tmp_path, bag, caplog):
    stamps = bag.frame_stamps()  # 4 frames, 0.1 s apart
    traj = _traj(np.arange(stamps[0], stamps[1] + 0.001, 0.01))
    with caplog.at_level(logging.WARNING):
        seq = with_trajectory(bag, traj)
    np.testing.assert_array_equal(seq.uncovered_frames(), [2, 3])
    assert "does not cover 2 scan(s): frame 2, frame 3" in caplog.text


def test_untimed_kitti_pairs_by_index(tmp_path, bag):
    traj = _traj(np.arange(len(bag)))
    write_kitti(tmp_path / "poses.kitti", traj, write_times=False)
    seq = with_trajectory(bag, tmp_path / "poses.kitti")
    np.testing.assert_array_equal(seq.ground_truth().stamps, bag.frame_stamps())
    np.testing.assert_allclose(seq.ground_truth().poses, traj.poses, atol=1e-6)
    write_kitti(tmp_path / "short.kitti", Trajectory(traj.stamps[:3], traj.poses[:3]), write_times=False)
    with pytest.raises(DatasetError, match=r"short.kitti: 3 poses \(no stamps\) cannot be matched "
                                           r"to the 4 scans of .*counts differ"):
        with_trajectory(bag, tmp_path / "short.kitti")


def test_no_overlap_one_line(tmp_path, bag):
    write_tum(tmp_path / "late.tum", _traj(bag.frame_stamps()[-1] + 10 + np.arange(5)))
    with pytest.raises(DatasetError) as err:
        with_trajectory(bag, tmp_path / "late.tum")
    msg = str(err.value)
    assert "late.tum: 5 poses" in msg and "4 scans of bag:rec.bag" in msg
    assert msg.count("] s") == 2 and "\n" not in msg  # both stamp ranges


def test_scan_folder_reopened_with_poses(tmp_path):
    from blockloc.datasets.pointclouds import write_point_cloud

    for i in range(3):
        write_point_cloud(tmp_path / "scans" / f"{i:06d}.pcd", np.full((5, 3), i, np.float32))
    folder = ScanFolderSequence(tmp_path)
    assert folder.ground_truth() is None and folder.stamp_source == "index"
    traj = _traj(100.0 + 0.5 * np.arange(3))
    tf = tmp_path / "slam.tum"
    write_tum(tf, traj)
    seq = with_trajectory(folder, read_trajectory_file(tf), frame_name="odom")
    assert isinstance(seq, ScanFolderSequence) and seq.info.map_frame == "odom"
    np.testing.assert_allclose(seq.frame_stamps(), traj.stamps)  # equal counts: pose i <-> scan i
    np.testing.assert_allclose(seq.ground_truth().poses, traj.poses, atol=1e-9)
    # wrapping twice replaces, not stacks
    again = with_trajectory(with_trajectory(folder, traj), traj)
    assert isinstance(again, ScanFolderSequence)


def test_covered_mask_rules():
    traj = Trajectory(np.array([0.0, 1.0, 2.0, 10.0, 11.0]), np.repeat(np.eye(4)[None], 5, axis=0))
    t = np.array([-0.1, -0.04, 0.5, 2.0, 5.0, 10.0, 11.04, 11.2])
    # median spacing 1 s: gaps over max(5 x 1, 1) = 5 s leave frames uncovered (the 8 s gap)
    np.testing.assert_array_equal(covered_mask(t, traj),
                                  [False, True, True, True, False, True, True, False])
    np.testing.assert_array_equal(covered_mask(t, traj, max_gap_s=10.0),
                                  [False, True, True, True, True, True, True, False])
    m = match_trajectory(t[1:4], traj, traj_name="a", seq_name="b")
    assert not m.by_index and len(m.uncovered) == 0
