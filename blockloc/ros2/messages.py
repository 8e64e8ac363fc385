"""ROS 2 messages as Cyclone DDS IDL types: what ``rmw_cyclonedds`` puts on the wire.

Each class is a ``cyclonedds.idl.IdlStruct`` with the DDS type name ROS 2 gives the message
(``pkg::msg::dds_::Type_``), fields in the ``.msg`` order, so Cyclone serializes them itself as
plain CDR (XCDR1, little endian, a 4-byte encapsulation header), exactly the bytes a ROS 2 node
sends; ``tests/ros2/test_messages.py`` checks every one against rosbags' CDR both ways.

Only the messages the node and the player use. Arrays: ``types.array[T, n]`` is a fixed-size
array (``float64[9]`` of a covariance), ``types.sequence[T]`` an unbounded sequence. The uint8
payloads (PointCloud2.data) are handed over as ``bytes``.
"""

# no `from __future__ import annotations`: Cyclone resolves the field types from live annotations
from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t


def _zeros(n: int):
    return field(default_factory=lambda: [0.0] * n)


# ----------------------------------------------------------------------------- builtin_interfaces / std_msgs
@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    """builtin_interfaces/Time: sec (int32), nanosec (uint32)."""

    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    """std_msgs/Header: stamp, frame_id."""

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Empty(IdlStruct, typename="std_msgs::msg::dds_::Empty_"):
    """std_msgs/Empty: ROS 2 gives an empty message one uint8 (``structure_needs_at_least_one_member``)."""

    structure_needs_at_least_one_member: t.uint8 = 0


# ----------------------------------------------------------------------------- geometry_msgs
@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    """pose; covariance: 36 float64, row-major 6x6 over (x, y, z, rot x, rot y, rot z)."""

    pose: Pose = field(default_factory=Pose)
    covariance: t.array[t.float64, 36] = _zeros(36)


@dataclass
class PoseWithCovarianceStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"):
    header: Header = field(default_factory=Header)
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    twist: Twist = field(default_factory=Twist)
    covariance: t.array[t.float64, 36] = _zeros(36)


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    """header.frame_id: the parent frame; child_frame_id: the child (the transform maps child
    coordinates into the parent: T_parent_child)."""

    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: t.sequence[TransformStamped] = field(default_factory=list)


# ----------------------------------------------------------------------------- nav_msgs
@dataclass
class Odometry(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)
    twist: TwistWithCovariance = field(default_factory=TwistWithCovariance)


# ----------------------------------------------------------------------------- sensor_msgs
@dataclass
class PointField(IdlStruct, typename="sensor_msgs::msg::dds_::PointField_"):
    """name, offset (bytes into a point), datatype (INT8=1 ... FLOAT64=8), count."""

    name: str = ""
    offset: t.uint32 = 0
    datatype: t.uint8 = 0
    count: t.uint32 = 1


@dataclass
class PointCloud2(IdlStruct, typename="sensor_msgs::msg::dds_::PointCloud2_"):
    header: Header = field(default_factory=Header)
    height: t.uint32 = 1
    width: t.uint32 = 0
    fields: t.sequence[PointField] = field(default_factory=list)
    is_bigendian: bool = False
    point_step: t.uint32 = 0
    row_step: t.uint32 = 0
    data: t.sequence[t.uint8] = field(default_factory=bytes)  # bytes in, bytes out (see _octets)
    is_dense: bool = True


@dataclass
class Imu(IdlStruct, typename="sensor_msgs::msg::dds_::Imu_"):
    """Covariances row-major 3x3; a first element of -1 means "not given" (REP 145)."""

    header: Header = field(default_factory=Header)
    orientation: Quaternion = field(default_factory=Quaternion)
    orientation_covariance: t.array[t.float64, 9] = _zeros(9)
    angular_velocity: Vector3 = field(default_factory=Vector3)
    angular_velocity_covariance: t.array[t.float64, 9] = _zeros(9)
    linear_acceleration: Vector3 = field(default_factory=Vector3)
    linear_acceleration_covariance: t.array[t.float64, 9] = _zeros(9)


# ----------------------------------------------------------------------------- diagnostic_msgs
@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    """level: OK=0, WARN=1, ERROR=2, STALE=3 (a ``byte`` in the .msg: octet on the wire)."""

    level: t.byte = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: t.sequence[KeyValue] = field(default_factory=list)


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header = field(default_factory=Header)
    status: t.sequence[DiagnosticStatus] = field(default_factory=list)


def _octets(cls, member: str) -> None:
    """Serialize ``cls.member`` (a sequence<uint8>) as one block of bytes: Cyclone's Python
    machine packs it element by element (0.7 s for a 2 MB cloud). The wire form is the same
    (a uint32 length, then the bytes); the value is ``bytes`` both ways."""
    from cyclonedds.idl._machinery import PlainCdrV2SequenceOfPrimitiveMachine

    class OctetSequence(PlainCdrV2SequenceOfPrimitiveMachine):
        def serialize(self, buffer, value, *args, **kwargs):
            buffer.align(4)
            buffer.write("I", 4, len(value))
            buffer.write_bytes(bytes(value))

        def deserialize(self, buffer, *args, **kwargs):
            buffer.align(4)
            return buffer.read_bytes(buffer.read("I", 4))

    idl = cls.__idl__
    idl.populate()
    for machine in (idl.v1_machine, idl.v2_machine):
        assert isinstance(machine.members_machines[member], PlainCdrV2SequenceOfPrimitiveMachine)
        machine.members_machines[member] = OctetSequence(t.uint8)


_octets(PointCloud2, "data")

#: The ROS 2 message name (rosbags' spelling) of every type here.
ROS_NAMES = {cls: cls.__idl_typename__.replace("::dds_::", "::").replace("::", "/").rstrip("_")
             for cls in (Time, Header, Empty, Point, Vector3, Quaternion, Pose, PoseWithCovariance,
                         PoseWithCovarianceStamped, PoseStamped, Twist, TwistWithCovariance, Transform,
                         TransformStamped, TFMessage, Odometry, PointField, PointCloud2, Imu, KeyValue,
                         DiagnosticStatus, DiagnosticArray)}

DIAG_OK, DIAG_WARN, DIAG_ERROR, DIAG_STALE = 0, 1, 2, 3


def stamp_to_time(stamp_s: float) -> Time:
    """A float stamp (s) as builtin_interfaces/Time (rounded to the nanosecond)."""
    ns = int(round(float(stamp_s) * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def time_to_stamp(time: Time) -> float:
    """builtin_interfaces/Time as float seconds."""
    return float(time.sec) + float(time.nanosec) * 1e-9
