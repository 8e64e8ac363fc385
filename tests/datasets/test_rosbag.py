"""ROS bags written with write_rosbag (ROS1, ROS2 sqlite3, ROS2 mcap) read back by RosbagSequence."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from blockloc.datasets.base import LidarFrame, Sequence
from blockloc.datasets.rosbag import (RosbagSequence, decode_pointcloud2, point_time_offsets,
                                      read_trajectory_file, write_rosbag)
from blockloc.errors import DatasetError

VERSIONS = ["ros1", "ros2-sqlite3", "ros2-mcap"]


def _bag_path(tmp_path, version):
    return tmp_path / ("rec.bag" if version == "ros1" else "rec")


@pytest.mark.parametrize("version", VERSIONS)
def test_bag_round_trip(tmp_path, session_data, version):
    frames, imu = session_data["frames"], session_data["imu"]
    path = write_rosbag(_bag_path(tmp_path, version), iter(frames), imu, version=version,
                        imu_topic="/handsfree/imu")
    assert not list(tmp_path.glob("*.tmp-*"))
    seq = RosbagSequence(path, lidar_topic="/velodyne_points", imu_topic="/handsfree/imu")
    assert isinstance(seq, Sequence)
    assert len(seq) == len(frames)
    np.testing.assert_allclose(seq.frame_stamps(), [f.stamp for f in frames], atol=1e-6)
    for got, ref in zip(seq.frames(), frames):
        np.testing.assert_allclose(got.points, ref.points, atol=1e-5 * 80)  # float32 transport
        np.testing.assert_array_equal(got.intensity, ref.intensity)
        np.testing.assert_array_equal(got.ring, ref.ring)
        np.testing.assert_array_equal(got.time_offsets, ref.time_offsets)
    f2 = seq.frame(2)  # random access agrees with the sequential pass
    assert f2.index == 2 and np.array_equal(f2.ring, frames[2].ring)
    got_imu = seq.imu()
    np.testing.assert_allclose(got_imu.t, imu.t, atol=1e-6)
    np.testing.assert_array_equal(got_imu.acc, imu.acc)
    np.testing.assert_array_equal(got_imu.gyro, imu.gyro)
    assert seq.info.imu_rate_hz == pytest.approx(100.0)
    assert seq.info.lidar_rate_hz == pytest.approx(10.0)
    assert seq.ground_truth() is None
    seq.close()


def test_bag_without_topic_lists_topics(tmp_path, session_data):
    path = write_rosbag(tmp_path / "a.bag", session_data["frames"][:1], session_data["imu"])
    with pytest.raises(DatasetError, match=r"no topic '/points'; the bag has: /imu \(sensor_msgs/msg/Imu\), "
                                           r"/velodyne_points \(sensor_msgs/msg/PointCloud2\)"):
        RosbagSequence(path, lidar_topic="/points", imu_topic="/imu")
    with pytest.raises(DatasetError, match=r"topic '/imu' carries sensor_msgs/msg/Imu, expected .*PointCloud2"):
        RosbagSequence(path, lidar_topic="/imu", imu_topic="/imu")
    with pytest.raises(DatasetError, match="bag not found"):
        RosbagSequence(tmp_path / "none.bag", lidar_topic="/a", imu_topic="/b")
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    with pytest.raises(DatasetError, match="cannot be read as a ROS bag"):
        RosbagSequence(tmp_path / "junk.bag", lidar_topic="/a", imu_topic="/b")


def test_nan_points_dropped_and_empty_cloud(tmp_path, session_data, caplog):
    fr = session_data["frames"]
    pts = fr[0].points.copy()
    pts[:10] = np.nan
    pts[10] = [np.inf, 0, 0]
    frames = [LidarFrame(0, fr[0].stamp, pts, fr[0].intensity, fr[0].time_offsets, fr[0].ring),
              LidarFrame(1, fr[1].stamp, np.zeros((0, 3)), None, None, None)]
    path = write_rosbag(tmp_path / "b.bag", frames, session_data["imu"])
    seq = RosbagSequence(path, lidar_topic="/velodyne_points", imu_topic="/imu", min_range_m=0.0)
    f0 = seq.frame(0)
    assert len(f0) == len(pts) - 11 and np.isfinite(f0.points).all()
    np.testing.assert_array_equal(f0.ring, fr[0].ring[11:])
    with caplog.at_level(logging.WARNING):
        f1 = seq.frame(1)
    assert len(f1) == 0 and f1.points.shape == (0, 3) and "no valid points" in caplog.text


def test_imu_out_of_order_and_duplicates(tmp_path, caplog):
    """Header stamps out of order / repeated while bag (arrival) times increase."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    T = store.types
    stamps_ms = [0, 10, 30, 20, 40, 40, 50]  # swapped pair, one duplicate
    path = tmp_path / "imu.bag"
    with Writer(path) as w:
        ic = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
        lc = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=store)
        for k, ms in enumerate(stamps_ms):
            hdr = T["std_msgs/msg/Header"](seq=k, stamp=T["builtin_interfaces/msg/Time"](sec=100, nanosec=ms * 1_000_000),
                                           frame_id="imu")
            v = T["geometry_msgs/msg/Vector3"]
            m = T["sensor_msgs/msg/Imu"](header=hdr, orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1),
                                         orientation_covariance=np.zeros(9), angular_velocity=v(x=0, y=0, z=float(ms)),
                                         angular_velocity_covariance=np.zeros(9),
                                         linear_acceleration=v(x=float(k), y=0, z=-9.8),
                                         linear_acceleration_covariance=np.zeros(9))
            w.write(ic, 100_000_000_000 + k * 10_000_000, store.serialize_ros1(m, "sensor_msgs/msg/Imu"))
        assert lc is not None
    seq = RosbagSequence(path, lidar_topic="/points", imu_topic="/imu")
    assert len(seq) == 0
    with caplog.at_level(logging.WARNING):
        got = seq.imu()
    assert "1 IMU rows out of time order; sorted" in caplog.text
    assert "1 IMU rows with a duplicate stamp" in caplog.text
    np.testing.assert_allclose(got.t - 100, [0, 0.01, 0.02, 0.03, 0.04, 0.05], atol=1e-9)
    np.testing.assert_allclose(got.gyro[:, 2], [0, 10, 20, 30, 40, 50])
    np.testing.assert_allclose(got.acc[:, 0], [0, 1, 3, 2, 4, 6])


def test_point_time_conventions():
    stamp_ns = 1_700_000_000_500_000_000
    rel = np.array([0.0, 0.05, 0.099], dtype=np.float32)              # Velodyne float seconds
    np.testing.assert_allclose(point_time_offsets(rel, stamp_ns), rel)
    ouster = np.array([0, 50_000_000, 99_000_000], dtype=np.uint32)   # Ouster t, uint32 ns
    np.testing.assert_allclose(point_time_offsets(ouster, stamp_ns), rel, atol=1e-7)
    abs_s = 1_700_000_000.5 + rel.astype(np.float64)                  # absolute float seconds
    np.testing.assert_allclose(point_time_offsets(abs_s, stamp_ns), rel, atol=1e-6)
    abs_ns_f = stamp_ns + rel.astype(np.float64) * 1e9                # Livox float64 absolute ns
    np.testing.assert_allclose(point_time_offsets(abs_ns_f, stamp_ns), rel, atol=1e-6)
    abs_ns_i = (np.uint64(stamp_ns) + (rel.astype(np.float64) * 1e9).round().astype(np.uint64))
    np.testing.assert_allclose(point_time_offsets(abs_ns_i, stamp_ns), rel, atol=1e-7)


def test_decode_organized_cloud_with_padding_and_other_fields():
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE).types
    PF = types["sensor_msgs/msg/PointField"]
    # Ouster-like: x y z (f4), pad, t (u4), reflectivity..., 'ring' (u1 here), 2 rows padded by 4 bytes
    dt = np.dtype({"names": ["x", "y", "z", "t", "ring"], "formats": ["<f4", "<f4", "<f4", "<u4", "u1"],
                   "offsets": [0, 4, 8, 16, 20], "itemsize": 24})
    cloud = np.zeros((2, 3), dtype=dt)
    cloud["x"] = [[1, 2, np.nan], [4, 5, 6]]
    cloud["t"] = [[0, 1000, 2000], [3000, 4000, 5_000_000]]
    cloud["ring"] = [[0, 0, 0], [1, 1, 1]]
    rows = np.zeros((2, 3 * 24 + 4), dtype=np.uint8)
    rows[:, :72] = np.frombuffer(cloud.tobytes(), np.uint8).reshape(2, 72)
    fields = [PF(name="x", offset=0, datatype=7, count=1), PF(name="y", offset=4, datatype=7, count=1),
              PF(name="z", offset=8, datatype=7, count=1), PF(name="t", offset=16, datatype=6, count=1),
              PF(name="ring", offset=20, datatype=2, count=1)]
    Header = types["std_msgs/msg/Header"]
    Time = types["builtin_interfaces/msg/Time"]
    msg = types["sensor_msgs/msg/PointCloud2"](
        header=Header(stamp=Time(sec=10, nanosec=0), frame_id="os"), height=2, width=3, fields=fields,
        is_bigendian=False, point_step=24, row_step=76, data=rows.reshape(-1), is_dense=False)
    pts, inten, offs, ring = decode_pointcloud2(msg)
    np.testing.assert_array_equal(pts[:, 0], [1, 2, 4, 5, 6])
    assert inten is None
    np.testing.assert_allclose(offs, [0, 1e-6, 3e-6, 4e-6, 5e-3], atol=1e-9)
    np.testing.assert_array_equal(ring, [0, 0, 1, 1, 1])
    msg.fields = fields[1:]
    with pytest.raises(DatasetError, match=r"lacks field\(s\) \['x'\]"):
        decode_pointcloud2(msg)


def test_tum_ground_truth_file(tmp_path):
    p = tmp_path / "street_01.txt"
    p.write_text("# t x y z qx qy qz qw\n"
                 "1.0 1 2 3 0 0 0 1\n"
                 "2.0 nan 2 3 0 0 0 1\n"
                 "3.0 4 5 6 0 0 0.7071067811865476 0.7071067811865476\n")
    traj = read_trajectory_file(p)
    assert len(traj) == 2
    np.testing.assert_allclose(traj.positions, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(traj.poses[1, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    p.write_text("1.0 1 2 3 0 0 0\n")
    with pytest.raises(DatasetError, match=r"street_01.txt:1: 7 columns, expected 8"):
        read_trajectory_file(p)


@pytest.mark.parametrize("fmt", ["rosbag1", "rosbag2"])
def test_simulator_bag_carries_ground_truth_and_extrinsics(tmp_path, fmt):
    """Issue 16 finding 5: a bag written by ``blockloc sim`` opens (by path, as the CLI opens it)
    with the ground truth, mapping poses, extrinsics and gravity of the NCLT-layout output."""
    from blockloc.app.catalog import open_sequence
    from blockloc.datasets.rosbag import sidecar_path
    from blockloc.sim import generate_dataset

    kw = dict(max_frames=4, azimuth_steps=60)
    nclt = generate_dataset("tiny", 5, tmp_path / "nclt", "nclt", **kw)
    bags = generate_dataset("tiny", 5, tmp_path / fmt, fmt, **kw)
    for session in ("map", "loc"):
        bag = bags / (f"{session}.bag" if fmt == "rosbag1" else session)
        assert sidecar_path(bag).is_file()
        b, n = open_sequence(str(bag)), open_sequence(str(nclt / session))
        assert np.allclose(b.info.T_body_lidar, n.info.T_body_lidar)
        assert not np.allclose(b.info.T_body_lidar, np.eye(4))
        assert np.allclose(b.info.T_body_imu, n.info.T_body_imu)
        assert np.allclose(b.info.gravity_map, n.info.gravity_map)
        gb, gn = b.ground_truth(), n.ground_truth()
        assert len(gb) == len(gn) > 20
        assert np.allclose(gb.stamps, gn.stamps) and np.allclose(gb.poses, gn.poses, atol=1e-6)
        mb, mn = b.mapping_poses(), n.mapping_poses()
        assert np.allclose(mb.poses, mn.poses, atol=1e-6)
        if session == "map":  # offline-SLAM poses, not the ground truth
            assert not np.allclose(mb.poses, gb.poses, atol=1e-4)
        assert np.allclose(b.frame_stamps(), n.frame_stamps())


def test_bad_sidecar_is_one_line_error(tmp_path, session_data):
    from blockloc.datasets.rosbag import RosbagSequence, sidecar_path, write_rosbag

    frames, imu = session_data["frames"], session_data["imu"]
    bag = write_rosbag(tmp_path / "s.bag", frames[:2], imu)
    sidecar_path(bag).write_text('{"T_body_lidar": [[1, 0], [0, 1]]}')
    with pytest.raises(DatasetError, match="not a valid bag sidecar"):
        RosbagSequence(bag, lidar_topic="/velodyne_points", imu_topic="/imu")
