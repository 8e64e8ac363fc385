"""Scan folders: layouts, stamps, trajectories (TUM, KITTI), IMU/extrinsics, bad input, the real walk."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from blockloc.datasets.base import Sequence
from blockloc.datasets.pointclouds import write_point_cloud
from blockloc.datasets.scanfolder import ScanFolderSequence, is_scan_folder, stamps_from_names
from blockloc.errors import DatasetError
from blockloc.trajectory_io import read_tum, write_kitti, write_tum
from blockloc.geometry import Trajectory, xyzrpy_to_T

T0 = 1_630_500_000.0


def _traj(stamps) -> Trajectory:
    t = np.asarray(stamps, float)
    s = t - t[0]
    return Trajectory(t, xyzrpy_to_T(s, 0.5 * s, 0.01 * s, 0.0, 0.0, 0.1 * s))


def _scan(i: int, n: int = 200) -> np.ndarray:
    rng = np.random.default_rng(i)
    return rng.uniform(-20, 20, (n, 3)).astype(np.float32)


def _folder(root, names, *, sub="scans", suffix=".pcd", extra=None):
    d = root / sub if sub else root
    d.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        write_point_cloud(d / f"{name}{suffix}", _scan(i), intensity=np.full(200, i, np.float32),
                          extra=None if extra is None else extra(i))
    return root


def test_tum_equal_counts_pair_by_index(tmp_path):
    stamps = T0 + 0.1 * np.arange(6)
    root = _folder(tmp_path, [f"{i:06d}" for i in range(6)])
    traj = _traj(stamps + 0.05)  # stamped at the sweep end: still pose i <-> scan i
    write_tum(root / "poses.tum", traj)
    assert is_scan_folder(root) and is_scan_folder(root / "scans")
    seq = ScanFolderSequence(root)
    assert isinstance(seq, Sequence)
    assert len(seq) == 6 and seq.stamp_source == "poses"
    np.testing.assert_allclose(seq.frame_stamps(), traj.stamps)
    np.testing.assert_allclose(seq.ground_truth().poses, traj.poses, atol=1e-9)
    assert seq.mapping_poses() is seq.ground_truth()
    f = seq.frame(3)
    assert f.index == 3 and f.stamp == seq.frame_stamps()[3]
    np.testing.assert_array_equal(f.points, _scan(3))
    assert (f.intensity == 3).all()
    assert [fr.index for fr in seq.frames(2, 5)] == [2, 3, 4]
    assert len(seq.imu()) == 0 and seq.info.imu_rate_hz == 0.0  # no IMU: LiDAR only
    np.testing.assert_array_equal(seq.info.T_body_lidar, np.eye(4))
    np.testing.assert_array_equal(seq.info.gravity_map, [0, 0, -9.81])
    assert seq.info.map_frame == "map" and seq.info.lidar_rate_hz == pytest.approx(10.0)
    assert len(seq.uncovered_frames()) == 0


def test_numeric_names_order_and_stamps(tmp_path):
    names = ["1630500000.5", "1630500000.05", "1630500000.25"]
    root = _folder(tmp_path, names, sub=None)
    seq = ScanFolderSequence(root)
    assert [f.name for f in seq.files] == ["1630500000.05.pcd", "1630500000.25.pcd", "1630500000.5.pcd"]
    assert seq.stamp_source == "file names" and seq.ground_truth() is None
    np.testing.assert_allclose(seq.frame_stamps(), T0 + np.array([0.05, 0.25, 0.5]), atol=1e-6)
    ns = stamps_from_names([tmp_path / "1630500000123456789.pcd", tmp_path / "1630500000223456789.pcd"])
    np.testing.assert_allclose(ns, [1630500000.123456789, 1630500000.223456789], atol=1e-6)
    assert stamps_from_names([tmp_path / "000012.pcd"]) is None  # an index
    # index names sort by value, not as text
    idx = ScanFolderSequence(_folder(tmp_path / "b", ["2", "10", "1"], sub=None))
    assert [f.stem for f in idx.files] == ["1", "2", "10"]


def test_kitti_layout_with_times(tmp_path):
    stamps = T0 + 0.1 * np.arange(5)
    root = _folder(tmp_path, [f"{i:06d}" for i in range(5)], sub="scans", suffix=".bin")
    traj = _traj(stamps)
    write_kitti(root / "poses.txt", traj, write_times=False)
    (root / "times.txt").write_text("".join(f"{t:.6f}\n" for t in stamps))
    seq = ScanFolderSequence(root)
    assert seq.stamp_source.endswith("times.txt")
    np.testing.assert_allclose(seq.frame_stamps(), stamps)
    np.testing.assert_allclose(seq.ground_truth().poses, traj.poses, atol=1e-6)
    f = seq.frame(4)
    np.testing.assert_array_equal(f.points, _scan(4))


def test_untimed_kitti_poses_pair_by_index(tmp_path):
    root = _folder(tmp_path, [f"{i:06d}" for i in range(4)], sub=None, suffix=".ply")
    traj = _traj(T0 + np.arange(4))
    write_kitti(tmp_path / "kitti_poses.txt", traj, write_times=False)
    seq = ScanFolderSequence(root, poses=tmp_path / "kitti_poses.txt", rate_hz=5.0)
    np.testing.assert_allclose(seq.frame_stamps(), np.arange(4) / 5.0)  # no stamp anywhere
    np.testing.assert_allclose(seq.ground_truth().poses, traj.poses, atol=1e-6)


def test_counts_differ_interpolates_and_names_uncovered_scans(tmp_path, caplog):
    # scans at 10 Hz over 2 s; poses at 20 Hz over [0.13, 0.58] and [1.28, 1.53] s
    scan_t = T0 + 0.1 * np.arange(20)
    root = _folder(tmp_path, [f"{t:.3f}" for t in scan_t])
    pose_t = T0 + np.round(np.concatenate([0.13 + 0.05 * np.arange(10), 1.28 + 0.05 * np.arange(6)]), 6)
    traj = _traj(pose_t)
    write_tum(tmp_path / "poses.tum", traj)
    with caplog.at_level(logging.WARNING):
        seq = ScanFolderSequence(root, max_gap_s=0.3)
    assert len(seq) == 20 and seq.stamp_source == "file names"
    # 0.1 s lies 0.03 s before the first pose (within tolerance: held); 0.6 s lies in the gap;
    # 1.6 s lies 0.07 s after the last pose: not covered (never extrapolated)
    covered = np.setdiff1d(np.arange(20), seq.uncovered_frames())
    np.testing.assert_array_equal(covered, [1, 2, 3, 4, 5, 13, 14, 15])
    assert "does not cover 12 scan(s)" in caplog.text
    assert f"{scan_t[0]:.3f}.pcd" in caplog.text and "and 4 more" in caplog.text
    gt = seq.ground_truth()  # the trajectory as given: evaluation interpolates it
    np.testing.assert_array_equal(gt.stamps, traj.stamps)


def test_map_building_skips_uncovered_scans(tmp_path):
    from blockloc.maps.mapping import mapping_keyframes

    scan_t = T0 + 0.1 * np.arange(10)
    root = _folder(tmp_path, [f"{t:.3f}" for t in scan_t])
    write_tum(root / "poses.tum", _traj(T0 + np.arange(0.0, 0.55, 0.05)))
    seq = ScanFolderSequence(root)
    np.testing.assert_array_equal(seq.uncovered_frames(), [6, 7, 8, 9])
    kfs = list(mapping_keyframes(seq, keyframe_distance_m=0.0, keyframe_angle_deg=0.0))
    assert [k.index for k in kfs] == [0, 1, 2, 3, 4, 5]  # never extrapolated past 0.5 s


def test_cloud_times_give_stamps(tmp_path):
    """opencalib-like: date-time file names, absolute per-point times, a denser INS trajectory."""
    sweep = np.linspace(0.0, 0.1, 200)
    names = [f"2021-10-26-16-21-29-{468 + 100 * i}" for i in range(4)]
    root = _folder(tmp_path, names, sub=None,
                   extra=lambda i: {"timestamp": T0 + 0.1 * i + sweep})
    write_tum(tmp_path / "ins.tum", _traj(T0 - 1 + 0.01 * np.arange(300)))
    seq = ScanFolderSequence(root, poses=tmp_path / "ins.tum")
    assert seq.stamp_source == "cloud times"
    np.testing.assert_allclose(seq.frame_stamps(), T0 + 0.1 * np.arange(4), atol=1e-6)
    f = seq.frame(2)
    np.testing.assert_allclose(f.time_offsets, sweep, atol=2e-6)


def test_imu_and_extrinsics(tmp_path):
    root = _folder(tmp_path, [f"{i:06d}" for i in range(3)])
    write_tum(root / "poses.tum", _traj(T0 + 0.1 * np.arange(3)))
    t = T0 + 0.005 * np.arange(60)
    rows = ["t,ax,ay,az,gx,gy,gz"] + [f"{v:.6f},0.1,0.2,9.8,0.01,0.02,0.03" for v in t]
    (root / "imu.csv").write_text("\n".join(rows) + "\n")
    T_bl = xyzrpy_to_T(0.1, 0.0, 0.2, 0.0, 0.0, np.pi / 2)
    (root / "extrinsics.yaml").write_text(
        "T_body_lidar: " + str(T_bl.tolist()) + "\n"
        "T_body_imu: [1,0,0,0, 0,1,0,0, 0,0,1,0.05, 0,0,0,1]\n"
        "gravity_map: [0, 0, 9.81]\nmap_frame: camera_init\n")
    seq = ScanFolderSequence(root)
    imu = seq.imu()
    assert len(imu) == 60 and seq.info.imu_rate_hz == pytest.approx(200.0)
    np.testing.assert_allclose(imu.acc[0], [0.1, 0.2, 9.8])
    np.testing.assert_allclose(imu.gyro[-1], [0.01, 0.02, 0.03])
    np.testing.assert_allclose(seq.info.T_body_lidar, T_bl)
    assert seq.info.T_body_imu[2, 3] == 0.05
    np.testing.assert_array_equal(seq.info.gravity_map, [0, 0, 9.81])
    assert seq.info.map_frame == "camera_init"
    assert ScanFolderSequence(root, frame_name="odom").info.map_frame == "odom"


@pytest.mark.parametrize("text,match", [
    ("T_lidar: [1]\n", "unknown key.*T_lidar"),
    ("T_body_lidar: [1, 2, 3]\n", "T_body_lidar must be a 4x4"),
    ("T_body_lidar: [2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n", "not a rigid transform"),
    ("gravity_map: [0, 0, 1]\n", "about 9.81"),
])
def test_bad_extrinsics(tmp_path, text, match):
    root = _folder(tmp_path, ["000000"])
    (root / "extrinsics.yaml").write_text(text)
    with pytest.raises(DatasetError, match=match) as err:
        ScanFolderSequence(root)
    assert "extrinsics.yaml" in str(err.value)


def test_counts_differ_without_stamps_one_line(tmp_path):
    root = _folder(tmp_path, [f"{i:06d}" for i in range(5)])
    write_tum(root / "poses.tum", _traj(T0 + 0.1 * np.arange(7)))
    with pytest.raises(DatasetError) as err:
        ScanFolderSequence(root)
    msg = str(err.value)
    assert "\n" not in msg
    assert "poses.tum" in msg and "scans" in msg  # both files
    assert "7 poses" in msg and "5 scans" in msg  # both counts
    assert f"[{T0:.3f}, {T0 + 0.6:.3f}] s" in msg and "unknown stamps" in msg  # both ranges


def test_stamps_that_do_not_overlap_one_line(tmp_path):
    root = _folder(tmp_path, [f"{T0 + 0.1 * i:.2f}" for i in range(4)])
    write_tum(root / "poses.tum", _traj(T0 + 100 + 0.1 * np.arange(7)))
    with pytest.raises(DatasetError, match=r"7 poses \(\[1630500100.000, 1630500100.600\] s\) "
                                           r"cannot be matched to the 4 scans of .*scans "
                                           r"\(\[1630500000.000, 1630500000.300\] s\)"):
        ScanFolderSequence(root)


def test_times_file_count_mismatch(tmp_path):
    root = _folder(tmp_path, [f"{i:06d}" for i in range(3)])
    (root / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DatasetError, match="times.txt: 2 stamps .*expected one per scan .*3 scans"):
        ScanFolderSequence(root)


def test_truncated_scan_names_its_path(tmp_path):
    root = _folder(tmp_path, [f"{i:06d}" for i in range(3)])
    bad = root / "scans" / "000001.pcd"
    bad.write_bytes(bad.read_bytes()[:-100])
    seq = ScanFolderSequence(root)  # opening reads no cloud
    seq.frame(0)
    with pytest.raises(DatasetError, match="000001.pcd: truncated binary PCD"):
        seq.frame(1)


def test_not_a_scan_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    assert not is_scan_folder(tmp_path / "empty")
    with pytest.raises(DatasetError, match="no point clouds"):
        ScanFolderSequence(tmp_path / "empty")
    nclt = tmp_path / "nclt"
    (nclt / "velodyne_sync").mkdir(parents=True)
    (nclt / "velodyne_hits.bin").write_bytes(b"\0" * 32)
    assert not is_scan_folder(nclt)
    assert not is_scan_folder(tmp_path / "nope")


def test_real_walk(shared_data):
    walk = shared_data / "balm_hilti_walk"
    ref = read_tum(walk / "poses_T_world_lidar.tum")
    seq = ScanFolderSequence(walk / "scans", poses=walk / "poses_T_world_lidar.tum")
    assert len(seq) == 177 and is_scan_folder(walk)
    np.testing.assert_array_equal(seq.frame_stamps(), ref.stamps)
    np.testing.assert_array_equal(seq.ground_truth().poses, ref.poses)
    assert len(seq.imu()) == 0 and len(seq.uncovered_frames()) == 0
    assert seq.info.lidar_rate_hz == pytest.approx(2.0)
    f = seq.frame(176)
    assert seq.files[176].name == "000176.pcd" and 10_000 < len(f) < 40_000
    assert f.time_offsets is None and f.ring is None
    # the trajectory is in the lidar frame (body = lidar): scans 0 and 1 overlap once placed
    from scipy.spatial import cKDTree

    a = seq.frame(0).points @ ref.poses[0, :3, :3].T + ref.poses[0, :3, 3]
    b = seq.frame(1).points @ ref.poses[1, :3, :3].T + ref.poses[1, :3, 3]
    d, _ = cKDTree(a).query(b, distance_upper_bound=1.0)
    assert np.median(d) < 0.1


def test_scans_subfolder_given_directly_finds_side_files(tmp_path):
    root = _folder(tmp_path, [f"{i:06d}" for i in range(3)])
    traj = _traj(T0 + 0.1 * np.arange(3))
    write_tum(root / "poses.tum", traj)
    seq = ScanFolderSequence(root / "scans")
    assert seq.root == root and seq.info.name == f"scans:{root.name}"
    np.testing.assert_allclose(seq.ground_truth().poses, traj.poses, atol=1e-9)
