"""Our Cyclone IDL messages put on the wire exactly the bytes of rosbags' ROS 2 Humble CDR, both ways.

rosbags is the independent reference: for every message the node or the player sends or receives,
our serialization decodes in rosbags to the same values and re-encodes to the same bytes, and
rosbags' bytes of a message decode in ours to the same values and re-encode to the same bytes.
"""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.ros2 import convert
from blockloc.ros2 import messages as m


@pytest.fixture(scope="module")
def typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def header(frame="lidar"):
    return m.Header(stamp=m.Time(sec=1_700_000_123, nanosec=456_789_012), frame_id=frame)


def samples():
    rng = np.random.default_rng(3)
    T = np.eye(4)
    T[:3, 3] = [1.5, -2.25, 0.125]
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    cov = np.diag([0.01, 0.02, 0.03, 0.001, 0.002, 0.003])
    cloud = convert.cloud_from_points(rng.normal(size=(37, 3)), 12.5, "velodyne",
                                      time_offsets=np.linspace(0, 0.1, 37), intensity=rng.random(37))
    tf = m.TFMessage(transforms=[convert.transform_stamped(T, 3.25, "map", "odom"),
                                 convert.transform_stamped(np.eye(4), 3.25, "odom", "base_link")])
    return {
        "builtin_interfaces/msg/Time": m.Time(sec=-3, nanosec=999_999_999),
        "std_msgs/msg/Header": header(),
        "std_msgs/msg/Empty": m.Empty(),
        "sensor_msgs/msg/PointField": m.PointField(name="intensity", offset=12, datatype=7, count=1),
        "sensor_msgs/msg/PointCloud2": cloud,
        "sensor_msgs/msg/Imu": convert.imu_message(7.001, [0.1, -0.2, 9.81], [0.01, 0.02, -0.03], "imu_link"),
        "geometry_msgs/msg/PoseWithCovarianceStamped": convert.pose_with_covariance(T, cov, 9.5),
        "geometry_msgs/msg/PoseStamped": m.PoseStamped(header(), convert.pose_of(T)),
        "geometry_msgs/msg/TransformStamped": tf.transforms[0],
        "tf2_msgs/msg/TFMessage": tf,
        "nav_msgs/msg/Odometry": convert.odometry(T, cov, np.array([1.0, 2.0, 0.5]), 9.5, "map", "base_link"),
        "diagnostic_msgs/msg/KeyValue": m.KeyValue("fitness", "0.93"),
        "diagnostic_msgs/msg/DiagnosticStatus": m.DiagnosticStatus(level=2, name="blockloc: localization",
                                                                   message="lost", hardware_id="blockloc",
                                                                   values=[m.KeyValue("a", "1")]),
        "diagnostic_msgs/msg/DiagnosticArray": convert.diagnostics(4.0, 1, "blockloc: localization", "degraded",
                                                                   {"fitness": 0.5, "dropped_scans": 3}),
    }


def test_every_message_type_is_covered():
    assert set(samples()) <= set(m.ROS_NAMES.values())
    # the node's and the player's types, named by the task
    need = {"sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/PointField", "sensor_msgs/msg/Imu",
            "geometry_msgs/msg/PoseWithCovarianceStamped", "geometry_msgs/msg/TransformStamped",
            "tf2_msgs/msg/TFMessage", "nav_msgs/msg/Odometry", "diagnostic_msgs/msg/DiagnosticArray",
            "diagnostic_msgs/msg/DiagnosticStatus", "diagnostic_msgs/msg/KeyValue", "std_msgs/msg/Empty",
            "std_msgs/msg/Header", "builtin_interfaces/msg/Time"}
    assert need <= set(samples())


def test_dds_type_names_are_ros2s():
    assert m.PointCloud2.__idl_typename__ == "sensor_msgs::msg::dds_::PointCloud2_"
    assert m.Time.__idl_typename__ == "builtin_interfaces::msg::dds_::Time_"
    assert m.TFMessage.__idl_typename__ == "tf2_msgs::msg::dds_::TFMessage_"
    for cls, name in m.ROS_NAMES.items():
        pkg, _, typ = name.split("/")
        assert cls.__idl_typename__ == f"{pkg}::msg::dds_::{typ}_"


@pytest.mark.parametrize("name", sorted(samples()))
def test_ours_decodes_in_rosbags_and_reencodes_to_the_same_bytes(typestore, name):
    ours = samples()[name].serialize()
    assert ours[:4] == b"\x00\x01\x00\x00"  # plain CDR (XCDR1), little endian
    theirs = typestore.deserialize_cdr(ours, name)
    assert bytes(typestore.serialize_cdr(theirs, name)) == ours


@pytest.mark.parametrize("name", sorted(samples()))
def test_rosbags_bytes_decode_in_ours_to_the_same_values(typestore, name):
    msg = samples()[name]
    theirs = bytes(typestore.serialize_cdr(typestore.deserialize_cdr(msg.serialize(), name), name))
    back = type(msg).deserialize(theirs)
    assert back == msg
    assert back.serialize() == theirs


def test_values_survive_as_rosbags_reads_them(typestore):
    s = samples()
    pc = typestore.deserialize_cdr(s["sensor_msgs/msg/PointCloud2"].serialize(), "sensor_msgs/msg/PointCloud2")
    assert (pc.header.stamp.sec, pc.header.frame_id, pc.width, pc.point_step) == (12, "velodyne", 37, 20)
    assert [f.name for f in pc.fields] == ["x", "y", "z", "intensity", "time"]
    pose = typestore.deserialize_cdr(s["geometry_msgs/msg/PoseWithCovarianceStamped"].serialize(),
                                     "geometry_msgs/msg/PoseWithCovarianceStamped")
    assert (pose.pose.pose.position.x, pose.pose.pose.position.y) == (1.5, -2.25)
    assert pose.pose.pose.orientation.z == pytest.approx(np.sqrt(0.5))
    assert pose.header.frame_id == "map" and pose.header.stamp.sec == 9 and pose.header.stamp.nanosec == 500_000_000
    # tangent (rot .01 .02 .03, trans .001 .002 .003) -> ROS (x, y, z, rx, ry, rz) in the map: the
    # 90 deg yaw swaps x and y
    assert np.diag(pose.pose.covariance.reshape(6, 6)) == pytest.approx([0.002, 0.001, 0.003, 0.02, 0.01, 0.03])
    diag = typestore.deserialize_cdr(s["diagnostic_msgs/msg/DiagnosticArray"].serialize(),
                                     "diagnostic_msgs/msg/DiagnosticArray")
    assert diag.status[0].level == 1 and {kv.key: kv.value for kv in diag.status[0].values}["dropped_scans"] == "3"


def test_a_rosbags_cloud_reads_as_a_frame(typestore):
    """A cloud as a ROS 2 driver sends it (rosbags' bytes, float64 absolute times in ``timestamp``)
    reads with its per-point times relative to the header stamp."""
    T = typestore.types
    n, stamp = 5, 1_700_000_000.25
    rec = np.zeros(n, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pad", "<f4"), ("timestamp", "<f8")]))
    rec["x"] = np.arange(n)
    rec["timestamp"] = stamp + np.arange(n) * 0.01
    fields = [T["sensor_msgs/msg/PointField"](name=k, offset=o, datatype=d, count=1)
              for k, o, d in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("timestamp", 16, 8))]
    msg = T["sensor_msgs/msg/PointCloud2"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=250_000_000),
                                        frame_id="lidar"),
        height=1, width=n, fields=fields, is_bigendian=False, point_step=24, row_step=24 * n,
        data=np.frombuffer(rec.tobytes(), np.uint8), is_dense=True)
    ours = m.PointCloud2.deserialize(bytes(typestore.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")))
    cloud = convert.cloud_arrays(ours)
    assert cloud.dropped == 0 and cloud.stamp == pytest.approx(stamp)
    assert cloud.points[:, 0] == pytest.approx(np.arange(n))
    assert cloud.time_offsets == pytest.approx(np.arange(n) * 0.01, abs=1e-6)
