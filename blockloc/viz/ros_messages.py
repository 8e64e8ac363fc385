"""A run as ROS 2 messages: the topics, frames and decimation shared by the MCAP recorder and the live server.

Messages are built as rosbags' typestore classes (ROS 2 Humble definitions) and serialized to CDR
by rosbags; the schemas written beside them are rosbags' concatenated ``.msg`` definitions
(``ros2msg``, the format ``ros2 bag`` writes). Nothing here hand-encodes bytes.

Frames (REP 105 names): ``map`` the prior map's frame; ``odom`` equal to ``map`` (blockloc
estimates the body pose in the map directly, it keeps no separate drifting odometry frame, so
``map -> odom`` is the identity at every stamp); ``base_link`` the body frame of ``poses.tum`` and
ground truth; ``lidar`` the sensor (``base_link -> lidar`` is the calibration ``T_body_lidar``).

Topics (:data:`TOPICS`), every stamp the scan's sensor time:

- ``/tf`` (tf2_msgs/TFMessage): ``map -> odom -> base_link`` and ``base_link -> lidar`` at every
  localized frame, so the chain resolves at each pose stamp.
- ``/localization/pose`` (geometry_msgs/PoseWithCovarianceStamped), ``/localization/odometry``
  (nav_msgs/Odometry): the pose with the window's marginal covariance converted by
  :func:`covariance_to_ros`; the odometry's twist is in ``base_link`` (linear from the estimated
  velocity, angular from the rotation between consecutive localized frames).
- ``/localization/path``, ``/ground_truth/path`` (nav_msgs/Path): decimated, see :class:`RunMessages`.
- ``/points/aligned`` (sensor_msgs/PointCloud2, x y z float32, ``map`` frame): the deskewed scan
  moved by its estimated pose, decimated to the points budget (:class:`Decimator`).
- ``/map/local`` (PointCloud2, ``map``): the served local map, once per change, subsampled.
- ``/map/blocks`` (visualization_msgs/MarkerArray): every block/tile outline, the served ones
  highlighted, re-sent whole whenever the served set changes.
- ``/diagnostics`` (diagnostic_msgs/DiagnosticArray): one status per frame (level from the
  tracking status, every diagnostics field as a key/value).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Iterable

import numpy as np

from blockloc.viz.events import FrameEvent, RunInfo, VizError

log = logging.getLogger(__name__)

FRAME_MAP, FRAME_ODOM, FRAME_BASE, FRAME_LIDAR = "map", "odom", "base_link", "lidar"

TOPICS: dict[str, str] = {
    "/tf": "tf2_msgs/msg/TFMessage",
    "/localization/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "/localization/odometry": "nav_msgs/msg/Odometry",
    "/localization/path": "nav_msgs/msg/Path",
    "/points/aligned": "sensor_msgs/msg/PointCloud2",
    "/map/local": "sensor_msgs/msg/PointCloud2",
    "/map/blocks": "visualization_msgs/msg/MarkerArray",
    "/ground_truth/path": "nav_msgs/msg/Path",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
# Topics whose last message stays true until the next one (a late viewer needs them re-sent).
LATCHED = ("/map/blocks", "/map/local", "/ground_truth/path", "/localization/path")

DIAG_NAME, DIAG_HARDWARE_ID = "tracking", "blockloc"
_LEVEL = {"ok": 0, "rejected": 1, "imu_only": 1, "recovered": 1, "lost": 2, "uninitialized": 2}
_POINT_BYTES = 12  # x, y, z float32
_CLOUD_OVERHEAD_BYTES = 120  # header, fields, CDR framing of one PointCloud2


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


def covariance_to_ros(cov_tangent: np.ndarray, R_map_body: np.ndarray) -> np.ndarray:
    """(6, 6) Pose3 tangent covariance (rot, trans; body frame, right perturbation) -> ROS order.

    ROS's ``PoseWithCovariance`` holds (x, y, z, rotation about X, Y, Z) in the header's frame
    (``map``). With ``T = T_hat Exp([w, v])`` the position moves by ``R v`` and the orientation by
    the rotation vector ``R w`` about the map's fixed axes (first order), so the ROS covariance
    is ``J P J^T`` with ``J = [[0, R], [R, 0]]``. Returns (6, 6) float64.
    """
    R = np.asarray(R_map_body, dtype=np.float64)
    J = np.zeros((6, 6))
    J[:3, 3:] = R
    J[3:, :3] = R
    out = J @ np.asarray(cov_tangent, dtype=np.float64) @ J.T
    return 0.5 * (out + out.T)


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    """(3, 3) or (N, 3, 3) rotation -> (4,) or (N, 4) unit quaternion x, y, z, w (w >= 0)."""
    R = np.asarray(R, dtype=np.float64)
    if R.ndim == 3:
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(R).as_quat()
        return q * np.where(q[:, 3:] < 0, -1.0, 1.0)
    return _quat_one(R)


def _quat_one(R: np.ndarray) -> np.ndarray:
    """One (3, 3) rotation -> (4,) x, y, z, w with w >= 0. Shepperd's method on the largest of
    w, x, y, z; numpy scalars because scipy's Rotation costs ~0.3 ms a call, too much per frame."""
    m00, m01, m02 = R[0]
    m10, m11, m12 = R[1]
    m20, m21, m22 = R[2]
    tr = m00 + m11 + m22
    if tr >= max(m00, m11, m22):
        w = 0.5 * math.sqrt(max(1.0 + tr, 0.0))
        x, y, z = (m21 - m12) / (4 * w), (m02 - m20) / (4 * w), (m10 - m01) / (4 * w)
    elif m00 >= m11 and m00 >= m22:
        x = 0.5 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        w, y, z = (m21 - m12) / (4 * x), (m01 + m10) / (4 * x), (m02 + m20) / (4 * x)
    elif m11 >= m22:
        y = 0.5 * math.sqrt(max(1.0 - m00 + m11 - m22, 0.0))
        w, x, z = (m02 - m20) / (4 * y), (m01 + m10) / (4 * y), (m12 + m21) / (4 * y)
    else:
        z = 0.5 * math.sqrt(max(1.0 - m00 - m11 + m22, 0.0))
        w, x, y = (m10 - m01) / (4 * z), (m02 + m20) / (4 * z), (m12 + m21) / (4 * z)
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def _rotvec(R: np.ndarray) -> np.ndarray:
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
        self.path(0, [0, 1], np.zeros((2, 3)), _quat_xyzw(np.stack([np.eye(3)] * 2)))  # imports scipy
        self.cloud(0, FRAME_MAP, np.zeros((1, 3), np.float32))
        self.serialize(self.MarkerArray(markers=[self.marker(0, "", 0, 0, points=np.zeros((2, 3)))]),
                       TOPICS["/map/blocks"])
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
        return self.serialize(msg, TOPICS["/tf"])

    def pose_with_covariance(self, t_ns: int, T_map_body: np.ndarray, q: np.ndarray,
                             cov_ros: np.ndarray) -> bytes:
        msg = self.PoseWithCovarianceStamped(
            header=self.header(t_ns, FRAME_MAP),
            pose=self.PoseWithCovariance(pose=self.pose(T_map_body[:3, 3], q), covariance=cov_ros.reshape(36)))
        return self.serialize(msg, TOPICS["/localization/pose"])

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
        return self.serialize(msg, TOPICS["/localization/odometry"])

    def path(self, t_ns: int, stamps_ns: Iterable[int], positions: np.ndarray, quats: np.ndarray) -> bytes:
        """positions: (K, 3) map frame, quats: (K, 4) x y z w."""
        poses = [self.PoseStamped(header=self.header(int(s), FRAME_MAP), pose=self.pose(p, q))
                 for s, p, q in zip(stamps_ns, positions, quats)]
        return self.serialize(self.Path(header=self.header(t_ns, FRAME_MAP), poses=poses), TOPICS["/localization/path"])

    def cloud(self, t_ns: int, frame_id: str, points: np.ndarray) -> bytes:
        """points: (N, 3) float32 in ``frame_id``."""
        pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        msg = self.PointCloud2(header=self.header(t_ns, frame_id), height=1, width=len(pts),
                               fields=self._xyz_fields, is_bigendian=False, point_step=_POINT_BYTES,
                               row_step=_POINT_BYTES * len(pts), data=pts.view(np.uint8).reshape(-1),
                               is_dense=True)
        return self.serialize(msg, TOPICS["/points/aligned"])

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
                              TOPICS["/diagnostics"])


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


def outline_xy(entry: dict) -> np.ndarray:
    """(K, 2) closed outline of a block/tile: its footprint, else its bounds' rectangle."""
    fp = entry.get("footprint")
    if fp is not None and len(fp) >= 3:
        xy = np.asarray(fp, dtype=np.float64).reshape(-1, 2)
    else:
        lo, hi = np.asarray(entry["bounds_min"], float), np.asarray(entry["bounds_max"], float)
        xy = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    if not np.allclose(xy[0], xy[-1]):
        xy = np.vstack([xy, xy[:1]])
    return xy


def _segments(entries: list[dict]) -> np.ndarray:
    """(2S, 3) LINE_LIST points (pairs) of the entries' outlines, each at its bounds' bottom z."""
    out = []
    for e in entries:
        xy = outline_xy(e)
        z = float(np.asarray(e["bounds_min"], float)[2])
        seg = np.empty((2 * (len(xy) - 1), 3))
        seg[0::2, :2], seg[1::2, :2] = xy[:-1], xy[1:]
        seg[:, 2] = z
        out.append(seg)
    return np.vstack(out) if out else np.zeros((0, 3))


@dataclass
class Outgoing:
    """One serialized message: topic, MCAP log time (ns, sensor time) and CDR bytes."""

    topic: str
    log_time_ns: int
    data: bytes


class Decimator:
    """Thins a frame's point clouds to the points budget (cheap numpy; runs in the tracking process).

    points_budget_mb_per_min: raw point payload (12 bytes per point) allowed on ``/points/aligned``
    and ``/map/local`` together, per minute of sensor time (None: no budget). A token bucket over
    sensor time holds it: the local map is always kept (it shows what the scan was aligned to),
    strided down to at most ``map_points_max`` points and charged to the bucket; a scan, first thinned by striding
    to at most ``scan_points_max`` points, is kept only when the bucket can pay for it (so scans are
    dropped, never delayed). The bucket holds at most ``burst_s`` seconds of budget.
    """

    def __init__(self, *, points_budget_mb_per_min: float | None = 20.0, scan_points_max: int = 8000,
                 map_points_max: int = 100_000, burst_s: float = 2.0) -> None:
        if points_budget_mb_per_min is not None and not points_budget_mb_per_min > 0:
            raise VizError(f"points_budget_mb_per_min {points_budget_mb_per_min!r}: expected a positive number of MB")
        self.budget_bytes_per_s = (None if points_budget_mb_per_min is None
                                   else points_budget_mb_per_min * 1e6 / 60.0)
        self.scan_points_max, self.map_points_max = int(scan_points_max), int(map_points_max)
        self.burst_s = float(burst_s)
        self.start()

    def start(self) -> None:
        self.counts = {"scans_kept": 0, "scans_dropped": 0, "maps_kept": 0, "points_bytes": 0}
        self._bucket = 0.0 if self.budget_bytes_per_s is None else self.budget_bytes_per_s * self.burst_s
        self._last_stamp: float | None = None
        self._t0: float | None = None
        self._map_bytes = 0
        self._warned = False

    def thin(self, ev: FrameEvent) -> FrameEvent:
        """``ev`` with its scan thinned (or None when over budget or not localized) and its local map
        subsampled; the input is not modified."""
        self._refill(ev.stamp)
        scan, local_map = ev.scan_lidar, ev.local_map_points
        if local_map is not None and len(local_map):
            local_map = np.asarray(local_map)
            # Striding, like the scan: free (a view), and the same map gives the same subsample
            # in the file and on the live view.
            local_map = local_map[::max(1, math.ceil(len(local_map) / self.map_points_max))]
            cost = self._charge(len(local_map), force=True)
            self._map_bytes += cost
            self.counts["maps_kept"] += 1
            self._warn_if_maps_exceed_budget(ev.stamp, len(local_map))
        else:
            local_map = None
        if scan is not None and len(scan) and ev.T_map_body is not None:
            scan = np.asarray(scan)
            scan = scan[::max(1, math.ceil(len(scan) / self.scan_points_max))]
            if self._charge(len(scan), force=False):
                self.counts["scans_kept"] += 1
            else:
                scan = None
                self.counts["scans_dropped"] += 1
        else:
            scan = None
        return dataclasses.replace(ev, scan_lidar=scan, local_map_points=local_map)

    def _refill(self, stamp: float) -> None:
        if self._t0 is None:
            self._t0 = stamp
        if self.budget_bytes_per_s is None:
            return
        if self._last_stamp is not None and stamp > self._last_stamp:
            cap = self.budget_bytes_per_s * self.burst_s
            self._bucket = min(cap, self._bucket + self.budget_bytes_per_s * (stamp - self._last_stamp))
        self._last_stamp = stamp

    def _charge(self, n_points: int, *, force: bool) -> int:
        """Pay for a cloud of n_points; 0 (and nothing paid) when refused."""
        cost = n_points * _POINT_BYTES + _CLOUD_OVERHEAD_BYTES
        if self.budget_bytes_per_s is not None:
            if not force and self._bucket < cost:
                return 0
            self._bucket -= cost
        self.counts["points_bytes"] += cost
        return cost

    def _warn_if_maps_exceed_budget(self, stamp: float, n_points: int) -> None:
        if self.budget_bytes_per_s is None or self._warned:
            return
        allowed = self.budget_bytes_per_s * (stamp - self._t0 + 60.0)
        if self._map_bytes > allowed:
            self._warned = True
            log.warning("the local maps alone (%d points per change) use more than the points budget of "
                        "%.0f MB/min; scans are mostly dropped", n_points, self.budget_bytes_per_s * 60 / 1e6)


class RunMessages:
    """A run's (thinned) events -> the ROS 2 messages to send.

    Point clouds are sent as they come (thin them first with :class:`Decimator`). Paths: a pose
    joins ``/localization/path`` when it is ``path_spacing_m`` from the last one kept; the path is
    sent every ``path_period_s`` of sensor time and at the end; past ``path_max_poses`` every
    other kept pose is dropped (the spacing doubles), so a message stays bounded.
    ``/ground_truth/path`` is sent once, on the first frame, thinned to ``gt_path_max_poses``.
    ``/map/blocks`` is sent on the first frame and whenever the served set changes; entry labels
    only for the served entries past ``label_max_entries`` entries.
    """

    def __init__(self, *, path_spacing_m: float = 0.5, path_period_s: float = 5.0, path_max_poses: int = 1000,
                 gt_path_max_poses: int = 5000, label_max_entries: int = 300) -> None:
        self.path_spacing_m, self.path_period_s = float(path_spacing_m), float(path_period_s)
        self.path_max_poses, self.gt_path_max_poses = int(path_max_poses), int(gt_path_max_poses)
        self.label_max_entries = int(label_max_entries)
        self.ros = RosBuilder()
        self.info: RunInfo | None = None
        self._reset()

    def _reset(self) -> None:
        self._first = True
        self._active: tuple | None = None
        self._prev_pose: tuple[float, np.ndarray] | None = None
        self._path_stamps: list[int] = []
        self._path_T: list[np.ndarray] = []
        self._path_stride = 1
        self._last_path_sent: float | None = None
        self._path_dirty = False
        self._last_t_ns = 0

    def start(self, info: RunInfo) -> None:
        self.info = info
        self.T_body_lidar = np.asarray(info.T_body_lidar, dtype=np.float64).reshape(4, 4)
        self.q_body_lidar = _quat_xyzw(self.T_body_lidar[:3, :3])
        self._reset()

    # ------------------------------------------------------------ per frame
    def frame(self, ev: FrameEvent, wants: Callable[[str], bool] | None = None) -> list[Outgoing]:
        """The messages of one frame. ``wants(topic)`` False skips building a topic (nobody listens);
        the path and block state advance either way."""
        if self.info is None:
            raise VizError("RunMessages.frame before start(): the run's RunInfo is needed first")
        want = wants or (lambda _topic: True)
        t_ns = stamp_ns(ev.stamp)
        self._last_t_ns = max(self._last_t_ns, t_ns)
        out: list[Outgoing] = []
        if self._first:
            self._first = False
            out += self._ground_truth(t_ns, want)
        active = tuple(ev.active_entries)
        if active != self._active:
            self._active = active
            if want("/map/blocks"):
                out.append(Outgoing("/map/blocks", t_ns, self.blocks_message(t_ns, active)))
        if ev.local_map_points is not None and len(ev.local_map_points) and want("/map/local"):
            out.append(Outgoing("/map/local", t_ns, self.ros.cloud(t_ns, FRAME_MAP, ev.local_map_points)))
        if ev.T_map_body is not None:
            out += self._pose_messages(t_ns, ev, want)
        if want("/diagnostics"):
            out.append(Outgoing("/diagnostics", t_ns, self.diagnostics_message(t_ns, ev)))
        if self._path_dirty and (self._last_path_sent is None or ev.stamp - self._last_path_sent >= self.path_period_s):
            self._last_path_sent = ev.stamp
            self._path_dirty = False
            if want("/localization/path"):
                out.append(Outgoing("/localization/path", t_ns, self.path_message(t_ns)))
        return out

    def finish(self, wants: Callable[[str], bool] | None = None) -> list[Outgoing]:
        """The final path (if it changed since it was last sent)."""
        want = wants or (lambda _topic: True)
        if self.info is None or not self._path_stamps or not self._path_dirty or not want("/localization/path"):
            return []
        self._path_dirty = False
        return [Outgoing("/localization/path", self._last_t_ns, self.path_message(self._last_t_ns))]

    def _ground_truth(self, t_ns: int, want) -> list[Outgoing]:
        gt = self.info.ground_truth
        if gt is None or len(gt) == 0 or not want("/ground_truth/path"):
            return []
        keep = _thin_by_distance(gt.positions, self.path_spacing_m / 2, self.gt_path_max_poses)
        stamps = [stamp_ns(max(float(s), 0.0)) for s in gt.stamps[keep]]
        data = self.ros.path(t_ns, stamps, gt.positions[keep], _quat_xyzw(gt.poses[keep, :3, :3]))
        return [Outgoing("/ground_truth/path", t_ns, data)]

    def _pose_messages(self, t_ns: int, ev: FrameEvent, want) -> list[Outgoing]:
        T = np.asarray(ev.T_map_body, dtype=np.float64)
        R = T[:3, :3]
        q = _quat_xyzw(R)
        out = []
        if want("/tf"):
            out.append(Outgoing("/tf", t_ns, self.ros.tf(t_ns, T, q, self.T_body_lidar, self.q_body_lidar)))
        need_cov = want("/localization/pose") or want("/localization/odometry")
        cov = (covariance_to_ros(ev.covariance, R) if need_cov and ev.covariance is not None
               else np.zeros((6, 6)))
        if want("/localization/pose"):
            out.append(Outgoing("/localization/pose", t_ns, self.ros.pose_with_covariance(t_ns, T, q, cov)))
        angular = np.zeros(3)
        if self._prev_pose is not None and ev.stamp > self._prev_pose[0]:
            angular = _rotvec(self._prev_pose[1][:3, :3].T @ R) / (ev.stamp - self._prev_pose[0])
        self._prev_pose = (ev.stamp, T)
        if want("/localization/odometry"):
            linear = R.T @ np.asarray(ev.velocity_map, dtype=np.float64).reshape(3)
            out.append(Outgoing("/localization/odometry", t_ns, self.ros.odometry(t_ns, T, q, cov, linear, angular)))
        self._extend_path(t_ns, T)
        if ev.scan_lidar is not None and len(ev.scan_lidar) and want("/points/aligned"):
            T_map_lidar = (T @ self.T_body_lidar).astype(np.float32)
            pts = np.asarray(ev.scan_lidar, dtype=np.float32) @ T_map_lidar[:3, :3].T + T_map_lidar[:3, 3]
            out.append(Outgoing("/points/aligned", t_ns, self.ros.cloud(t_ns, FRAME_MAP, pts)))
        return out

    def _extend_path(self, t_ns: int, T: np.ndarray) -> None:
        if self._path_T and np.linalg.norm(T[:3, 3] - self._path_T[-1][:3, 3]) < self.path_spacing_m * self._path_stride:
            return
        self._path_stamps.append(t_ns)
        self._path_T.append(T)
        self._path_dirty = True
        if len(self._path_T) > self.path_max_poses:
            self._path_stamps, self._path_T = self._path_stamps[::2], self._path_T[::2]
            self._path_stride *= 2

    # ------------------------------------------------------------ message bodies
    def path_message(self, t_ns: int) -> bytes:
        Ts = np.asarray(self._path_T).reshape(-1, 4, 4)
        return self.ros.path(t_ns, self._path_stamps, Ts[:, :3, 3], _quat_xyzw(Ts[:, :3, :3]) if len(Ts) else Ts[:, 0])

    def blocks_message(self, t_ns: int, active: tuple) -> bytes:
        """Every outline (one LINE_LIST), the served ones again thicker and orange, and labels."""
        ros, entries = self.ros, self.info.map_entries
        active_set = {str(a) for a in active}
        on = [e for e in entries if str(e["id"]) in active_set]
        off = [e for e in entries if str(e["id"]) not in active_set]
        markers = [ros.marker(t_ns, "", 0, ros.Marker.LINE_LIST, action=ros.Marker.DELETEALL)]
        if off:
            markers.append(ros.marker(t_ns, "blocks", 0, ros.Marker.LINE_LIST, points=_segments(off),
                                      scale=(0.25, 0, 0), rgba=(0.45, 0.6, 0.85, 0.8)))
        if on:
            markers.append(ros.marker(t_ns, "active", 0, ros.Marker.LINE_LIST, points=_segments(on),
                                      scale=(0.8, 0, 0), rgba=(1.0, 0.55, 0.0, 1.0)))
        labelled = entries if len(entries) <= self.label_max_entries else on
        for k, e in enumerate(labelled):
            c = np.asarray(e["centroid"], float)
            hot = str(e["id"]) in active_set
            markers.append(ros.marker(t_ns, "labels", k, ros.Marker.TEXT_VIEW_FACING, text=str(e["id"]),
                                      position=(c[0], c[1], float(np.asarray(e["bounds_max"], float)[2]) + 2.0),
                                      scale=(0, 0, 4.0 if hot else 2.5),
                                      rgba=(1.0, 0.55, 0.0, 1.0) if hot else (0.8, 0.85, 0.95, 0.9)))
        return ros.serialize(ros.MarkerArray(markers=markers), TOPICS["/map/blocks"])

    def diagnostics_message(self, t_ns: int, ev: FrameEvent) -> bytes:
        d = ev.diagnostics or {}
        message = ev.status
        if d.get("switched"):
            message += f", switched to {d.get('block_id') or ev.local_map_id or 'a new map'}"
        values = {"status": ev.status, "frame_index": ev.index, "localized": ev.T_map_body is not None}
        values.update((k, v) for k, v in d.items() if k not in values)
        values.setdefault("local_map_id", ev.local_map_id)
        values["active_entries"] = list(ev.active_entries)
        return self.ros.diagnostics(t_ns, _LEVEL.get(ev.status, 1), message, values)


def _thin_by_distance(positions: np.ndarray, spacing_m: float, max_poses: int) -> np.ndarray:
    """Indices (K,) of positions (N, 3) at least ``spacing_m`` apart along the path, first and last
    kept, then strided down to at most ``max_poses``."""
    if len(positions) == 0:
        return np.zeros(0, dtype=int)
    step = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))]
    bins = np.floor(step / max(spacing_m, 1e-9)).astype(np.int64)
    keep = np.r_[0, np.flatnonzero(np.diff(bins)) + 1]
    if keep[-1] != len(positions) - 1:
        keep = np.r_[keep, len(positions) - 1]
    if len(keep) > max_poses:
        keep = keep[np.linspace(0, len(keep) - 1, max_poses).round().astype(int)]
    return np.unique(keep)
