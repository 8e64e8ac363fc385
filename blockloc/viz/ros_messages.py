"""A run as ROS 2 messages: the topics, frames and decimation shared by the MCAP recorder and the live server.

The messages themselves are built and serialized by :mod:`blockloc.viz.ros_codec` (rosbags'
typestore and CDR serializer; no hand-written encoding).

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
from typing import Callable

import numpy as np

from blockloc.viz.events import FrameEvent, RunInfo, VizError
from blockloc.viz.ros_codec import (
    FRAME_MAP,
    MSG_CLOUD,
    MSG_DIAGNOSTICS,
    MSG_MARKERS,
    MSG_ODOMETRY,
    MSG_PATH,
    MSG_POSE,
    MSG_TF,
    POINT_BYTES,
    RosBuilder,
    covariance_to_ros,
    quat_xyzw,
    rotation_vector,
    stamp_ns,
)

log = logging.getLogger(__name__)

TOPICS: dict[str, str] = {
    "/tf": MSG_TF,
    "/localization/pose": MSG_POSE,
    "/localization/odometry": MSG_ODOMETRY,
    "/localization/path": MSG_PATH,
    "/points/aligned": MSG_CLOUD,
    "/map/local": MSG_CLOUD,
    "/map/blocks": MSG_MARKERS,
    "/ground_truth/path": MSG_PATH,
    "/diagnostics": MSG_DIAGNOSTICS,
}
# Topics whose last message stays true until the next one (a late viewer needs them re-sent).
LATCHED = ("/map/blocks", "/map/local", "/ground_truth/path", "/localization/path")

_LEVEL = {"ok": 0, "rejected": 1, "imu_only": 1, "recovered": 1, "lost": 2, "uninitialized": 2}
_CLOUD_OVERHEAD_BYTES = 120  # header, fields, CDR framing of one PointCloud2


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
        cost = n_points * POINT_BYTES + _CLOUD_OVERHEAD_BYTES
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
        self.q_body_lidar = quat_xyzw(self.T_body_lidar[:3, :3])
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
        data = self.ros.path(t_ns, stamps, gt.positions[keep], quat_xyzw(gt.poses[keep, :3, :3]))
        return [Outgoing("/ground_truth/path", t_ns, data)]

    def _pose_messages(self, t_ns: int, ev: FrameEvent, want) -> list[Outgoing]:
        T = np.asarray(ev.T_map_body, dtype=np.float64)
        R = T[:3, :3]
        q = quat_xyzw(R)
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
            angular = rotation_vector(self._prev_pose[1][:3, :3].T @ R) / (ev.stamp - self._prev_pose[0])
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
        return self.ros.path(t_ns, self._path_stamps, Ts[:, :3, 3], quat_xyzw(Ts[:, :3, :3]) if len(Ts) else Ts[:, 0])

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
        return ros.serialize(ros.MarkerArray(markers=markers), MSG_MARKERS)

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
