"""ROS 2 message objects and their CDR bytes, built with rosbags' typestore (ROS 2 Humble definitions).

Nothing here hand-encodes bytes: messages are rosbags' generated classes, serialized by
``typestore.serialize_cdr``; the schemas are rosbags' concatenated ``.msg`` definitions
(``ros2msg``, what ``ros2 bag`` writes). The small math the messages need, quaternions and the
covariance in ROS's order and frame, is :mod:`blockloc.geometry`'s (shared with
:mod:`blockloc.ros2`); a rotation vector is here.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Iterable

import numpy as np

from blockloc.geometry import _quat_one, covariance_to_ros, quat_xyzw  # noqa: F401 - their names here too
from blockloc.viz.events import VizError

FRAME_MAP, FRAME_ODOM, FRAME_BASE, FRAME_LIDAR = "map", "odom", "base_link", "lidar"
DIAG_NAME, DIAG_HARDWARE_ID = "tracking", "blockloc"
# Schema of each kind of message RosBuilder makes.
MSG_TF, MSG_POSE = "tf2_msgs/msg/TFMessage", "geometry_msgs/msg/PoseWithCovarianceStamped"
MSG_ODOMETRY, MSG_PATH = "nav_msgs/msg/Odometry", "nav_msgs/msg/Path"
MSG_CLOUD, MSG_MARKERS = "sensor_msgs/msg/PointCloud2", "visualization_msgs/msg/MarkerArray"
MSG_DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
POINT_BYTES = 12  # x, y, z float32


@lru_cache(maxsize=1)
def typestore():
    """rosbags' ROS 2 Humble typestore (built once; rosbags is imported only when needed)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


@lru_cache(maxsize=None)
def schema_text(msgtype: str) -> str:
    """The ``ros2msg`` schema of ``msgtype`` ('pkg/msg/Name'): its .msg text and its dependencies'."""
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return text


def stamp_ns(stamp_s: float) -> int:
    """Sensor time (s) -> integer nanoseconds (MCAP log time); raises VizError before the epoch."""
    if not stamp_s >= 0.0:
        raise VizError(f"stamp {stamp_s!r} s: MCAP and ROS 2 need non-negative times")
    return int(round(stamp_s * 1e9))


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """One (3, 3) rotation -> (3,) rotation vector, radians (via its quaternion)."""
    q = _quat_one(R)
    s = np.linalg.norm(q[:3])
    if s < 1e-12:
        return 2.0 * q[:3]
    return q[:3] * (2.0 * math.atan2(s, q[3]) / s)


class RosBuilder:
    """Makes rosbags message objects and their CDR bytes (one typestore, classes looked up once)."""

    def __init__(self) -> None:
        self.store = typestore()
        t = self.store.types
        self.Time, self.Duration = t["builtin_interfaces/msg/Time"], t["builtin_interfaces/msg/Duration"]
        self.Header = t["std_msgs/msg/Header"]
        self.ColorRGBA = t["std_msgs/msg/ColorRGBA"]
        self.Point, self.Quaternion = t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Quaternion"]
        self.Vector3, self.Pose = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Pose"]
        self.Transform, self.TransformStamped = t["geometry_msgs/msg/Transform"], t["geometry_msgs/msg/TransformStamped"]
        self.PoseStamped = t["geometry_msgs/msg/PoseStamped"]
        self.PoseWithCovariance = t["geometry_msgs/msg/PoseWithCovariance"]
        self.PoseWithCovarianceStamped = t["geometry_msgs/msg/PoseWithCovarianceStamped"]
        self.Twist, self.TwistWithCovariance = t["geometry_msgs/msg/Twist"], t["geometry_msgs/msg/TwistWithCovariance"]
        self.Odometry, self.Path = t["nav_msgs/msg/Odometry"], t["nav_msgs/msg/Path"]
        self.TFMessage = t["tf2_msgs/msg/TFMessage"]
        self.PointField, self.PointCloud2 = t["sensor_msgs/msg/PointField"], t["sensor_msgs/msg/PointCloud2"]
        self.CompressedImage = t["sensor_msgs/msg/CompressedImage"]
        self.Marker, self.MarkerArray = t["visualization_msgs/msg/Marker"], t["visualization_msgs/msg/MarkerArray"]
        self.MeshFile = t["visualization_msgs/msg/MeshFile"]
        self.KeyValue = t["diagnostic_msgs/msg/KeyValue"]
        self.DiagnosticStatus = t["diagnostic_msgs/msg/DiagnosticStatus"]
        self.DiagnosticArray = t["diagnostic_msgs/msg/DiagnosticArray"]
        self._xyz_fields = [self.PointField(name=n, offset=4 * i, datatype=self.PointField.FLOAT32, count=1)
                            for i, n in enumerate("xyz")]
        self._empty_u8 = np.zeros(0, dtype=np.uint8)

    def prime(self) -> None:
        """Serialize one message of every type: rosbags compiles a serializer on first use (~50 ms
        each), better before the first frame than during it."""
        T, q, cov = np.eye(4), np.array([0.0, 0.0, 0.0, 1.0]), np.zeros((6, 6))
        self.tf(0, T, q, T, q)
        self.pose_with_covariance(0, T, q, cov)
        self.odometry(0, T, q, cov, np.zeros(3), np.zeros(3))
        self.path(0, [0, 1], np.zeros((2, 3)), quat_xyzw(np.stack([np.eye(3)] * 2)))  # imports scipy
        self.cloud(0, FRAME_MAP, np.zeros((1, 3), np.float32))
        self.serialize(self.MarkerArray(markers=[self.marker(0, "", 0, 0, points=np.zeros((2, 3)))]),
                       MSG_MARKERS)
        self.diagnostics(0, 0, "", {"a": 1.0})

    def serialize(self, msg, msgtype: str) -> bytes:
        return bytes(self.store.serialize_cdr(msg, msgtype))

    # ------------------------------------------------------------ small pieces
    def header(self, t_ns: int, frame_id: str):
        return self.Header(stamp=self.Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000),
                           frame_id=frame_id)

    def pose(self, t: np.ndarray, q: np.ndarray):
        return self.Pose(position=self.Point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                         orientation=self.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))

    def transform(self, t_ns: int, parent: str, child: str, t: np.ndarray, q: np.ndarray):
        return self.TransformStamped(
            header=self.header(t_ns, parent), child_frame_id=child,
            transform=self.Transform(translation=self.Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                                     rotation=self.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                              w=float(q[3]))))

    def color(self, rgba) -> object:
        return self.ColorRGBA(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]), a=float(rgba[3]))

    # ------------------------------------------------------------ whole messages
    def tf(self, t_ns: int, T_map_body: np.ndarray, q_map_body: np.ndarray, T_body_lidar: np.ndarray,
           q_body_lidar: np.ndarray) -> bytes:
        zero, unit = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        msg = self.TFMessage(transforms=[
            self.transform(t_ns, FRAME_MAP, FRAME_ODOM, zero, unit),
            self.transform(t_ns, FRAME_ODOM, FRAME_BASE, T_map_body[:3, 3], q_map_body),
            self.transform(t_ns, FRAME_BASE, FRAME_LIDAR, T_body_lidar[:3, 3], q_body_lidar),
        ])
        return self.serialize(msg, MSG_TF)

    def pose_with_covariance(self, t_ns: int, T_map_body: np.ndarray, q: np.ndarray,
                             cov_ros: np.ndarray) -> bytes:
        msg = self.PoseWithCovarianceStamped(
            header=self.header(t_ns, FRAME_MAP),
            pose=self.PoseWithCovariance(pose=self.pose(T_map_body[:3, 3], q), covariance=cov_ros.reshape(36)))
        return self.serialize(msg, MSG_POSE)

    def odometry(self, t_ns: int, T_map_body: np.ndarray, q: np.ndarray, cov_ros: np.ndarray,
                 linear_body: np.ndarray, angular_body: np.ndarray) -> bytes:
        # Twist covariance unknown: -1 in the first element, the convention of sensor_msgs.
        twist_cov = np.zeros(36)
        twist_cov[0] = -1.0
        msg = self.Odometry(
            header=self.header(t_ns, FRAME_ODOM), child_frame_id=FRAME_BASE,
            pose=self.PoseWithCovariance(pose=self.pose(T_map_body[:3, 3], q), covariance=cov_ros.reshape(36)),
            twist=self.TwistWithCovariance(
                twist=self.Twist(linear=self.Vector3(x=float(linear_body[0]), y=float(linear_body[1]),
                                                     z=float(linear_body[2])),
                                 angular=self.Vector3(x=float(angular_body[0]), y=float(angular_body[1]),
                                                      z=float(angular_body[2]))),
                covariance=twist_cov))
        return self.serialize(msg, MSG_ODOMETRY)

    def path(self, t_ns: int, stamps_ns: Iterable[int], positions: np.ndarray, quats: np.ndarray) -> bytes:
        """positions: (K, 3) map frame, quats: (K, 4) x y z w."""
        poses = [self.PoseStamped(header=self.header(int(s), FRAME_MAP), pose=self.pose(p, q))
                 for s, p, q in zip(stamps_ns, positions, quats)]
        return self.serialize(self.Path(header=self.header(t_ns, FRAME_MAP), poses=poses), MSG_PATH)

    def cloud(self, t_ns: int, frame_id: str, points: np.ndarray) -> bytes:
        """points: (N, 3) float32 in ``frame_id``."""
        pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        msg = self.PointCloud2(header=self.header(t_ns, frame_id), height=1, width=len(pts),
                               fields=self._xyz_fields, is_bigendian=False, point_step=POINT_BYTES,
                               row_step=POINT_BYTES * len(pts), data=pts.view(np.uint8).reshape(-1),
                               is_dense=True)
        return self.serialize(msg, MSG_CLOUD)

    def marker(self, t_ns: int, ns: str, mid: int, mtype: int, *, points=None, scale=(1.0, 1.0, 1.0),
               rgba=(1.0, 1.0, 1.0, 1.0), text: str = "", position=(0.0, 0.0, 0.0), action: int = 0):
        pts = [] if points is None else [self.Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in points]
        return self.Marker(
            header=self.header(t_ns, FRAME_MAP), ns=ns, id=int(mid), type=int(mtype), action=int(action),
            pose=self.pose(np.asarray(position, float), np.array([0.0, 0.0, 0.0, 1.0])),
            scale=self.Vector3(x=float(scale[0]), y=float(scale[1]), z=float(scale[2])),
            color=self.color(rgba), lifetime=self.Duration(sec=0, nanosec=0), frame_locked=False,
            points=pts, colors=[], texture_resource="",
            texture=self.CompressedImage(header=self.header(0, ""), format="", data=self._empty_u8),
            uv_coordinates=[], text=text, mesh_resource="",
            mesh_file=self.MeshFile(filename="", data=self._empty_u8), mesh_use_embedded_materials=False)

    def diagnostics(self, t_ns: int, level: int, message: str, values: dict) -> bytes:
        kv = [self.KeyValue(key=str(k), value=_format_value(v)) for k, v in values.items()]
        status = self.DiagnosticStatus(level=level, name=DIAG_NAME, message=message,
                                       hardware_id=DIAG_HARDWARE_ID, values=kv)
        return self.serialize(self.DiagnosticArray(header=self.header(t_ns, ""), status=[status]),
                              MSG_DIAGNOSTICS)


def _format_value(v) -> str:
    """A diagnostics value as the text of a KeyValue (numbers parse back with float())."""
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.9g}"
    if isinstance(v, (list, tuple)):
        return ",".join(str(x) for x in v)
    return str(v)
