"""numpy <-> ROS 2 messages (:mod:`blockloc.ros2.messages`): clouds, IMU samples, poses, transforms.

Pure functions, no DDS. Frames by name: a PointCloud2 is in its ``header.frame_id`` (the LiDAR),
a pose message ``T_map_body`` in ``map``. Stamps are float seconds here, ``builtin_interfaces/Time``
on the wire.

Per-point times of a cloud (:func:`cloud_arrays`): a ``time``, ``t`` or ``timestamp`` field.
Float fields are seconds, relative to the header stamp, or absolute when they are more than a
day from zero (then the stamp is subtracted); integer fields are nanoseconds (Ouster's ``t``:
uint32 ns from the sweep start), relative, or absolute when larger than a day.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.errors import BlocklocError
from blockloc.geometry import covariance_to_ros, quat_xyzw
from blockloc.ros2 import messages as m

#: PointField.datatype -> numpy dtype (little endian)
POINT_TYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
FLOAT32, FLOAT64 = 7, 8
TIME_FIELDS = ("time", "t", "timestamp")
DAY_S = 86400.0


class CloudError(BlocklocError):
    """A PointCloud2 that cannot be read as points (layout, fields, size)."""


def cloud_from_points(points: np.ndarray, stamp: float, frame_id: str, *, time_offsets: np.ndarray | None = None,
                      intensity: np.ndarray | None = None) -> m.PointCloud2:
    """A dense PointCloud2 of float32 fields x, y, z [, intensity] [, time].

    points: (N, 3) metres in ``frame_id``; time_offsets: (N,) s relative to ``stamp``;
    intensity: (N,)."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    names = ["x", "y", "z"]
    cols = [pts[:, 0], pts[:, 1], pts[:, 2]]
    if intensity is not None:
        names.append("intensity")
        cols.append(np.asarray(intensity, np.float32).reshape(-1))
    if time_offsets is not None:
        names.append("time")
        cols.append(np.asarray(time_offsets, np.float32).reshape(-1))
    dtype = np.dtype([(n, "<f4") for n in names])
    rec = np.empty(len(pts), dtype)
    for n, c in zip(names, cols):
        rec[n] = c
    fields = [m.PointField(name=n, offset=4 * i, datatype=FLOAT32, count=1) for i, n in enumerate(names)]
    return m.PointCloud2(header=m.Header(stamp=m.stamp_to_time(stamp), frame_id=frame_id), height=1,
                         width=len(pts), fields=fields, is_bigendian=False, point_step=dtype.itemsize,
                         row_step=dtype.itemsize * len(pts), data=rec.tobytes(), is_dense=True)


@dataclass(frozen=True)
class Cloud:
    """A PointCloud2's points (what a ``LidarFrame`` holds, made by the node).

    stamp: the header stamp, s; points: (N, 3) in the cloud's frame, float32 when its x, y, z
    fields are (as every common driver's), else float64; intensity: (N,) float32 or None; time_offsets: (N,) float32 s relative to ``stamp`` or None; dropped: the
    number of non-finite points left out."""

    stamp: float
    points: np.ndarray
    intensity: np.ndarray | None
    time_offsets: np.ndarray | None
    dropped: int


def cloud_arrays(msg: m.PointCloud2) -> Cloud:
    """A PointCloud2 -> its finite points, intensity and per-point times (:class:`Cloud`).

    Raises CloudError for a layout it cannot read (no x/y/z field, a point_step smaller than the
    fields, a data size that does not match, big endian) or a cloud without finite points."""
    stamp = m.time_to_stamp(msg.header.stamp)
    if msg.is_bigendian:
        raise CloudError("big-endian PointCloud2 is not supported")
    fields = {f.name: f for f in msg.fields}
    for name in ("x", "y", "z"):
        if name not in fields:
            raise CloudError(f"no {name!r} field (fields: {', '.join(fields) or 'none'})")
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    if n == 0:
        raise CloudError("empty cloud (0 points)")
    data = msg.data if isinstance(msg.data, (bytes, bytearray)) else bytes(msg.data)
    formats, offsets, names = [], [], []
    for f in msg.fields:
        if f.datatype not in POINT_TYPES or f.count != 1:
            continue
        size = np.dtype(POINT_TYPES[f.datatype]).itemsize
        if f.offset + size > step:
            raise CloudError(f"field {f.name!r} at offset {f.offset} does not fit point_step {step}")
        names.append(f.name)
        formats.append(POINT_TYPES[f.datatype])
        offsets.append(int(f.offset))
    rows = int(msg.height)
    row_step = int(msg.row_step) or step * int(msg.width)
    if row_step < step * int(msg.width) or len(data) < row_step * rows:
        raise CloudError(f"data holds {len(data)} bytes, expected {rows} rows of {row_step} "
                         f"({msg.width} points of {step} bytes)")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    if row_step == step * int(msg.width):
        rec = np.frombuffer(data, dtype=dtype, count=n)
    else:  # padded rows
        rec = np.concatenate([np.frombuffer(data, dtype=dtype, count=int(msg.width), offset=r * row_step)
                              for r in range(rows)])
    unreadable = [k for k in ("x", "y", "z") if k not in names]
    if unreadable:
        raise CloudError(f"field {unreadable[0]!r} has datatype {fields[unreadable[0]].datatype} count "
                         f"{fields[unreadable[0]].count}: expected one number of a PointField type 1-8")
    # one strided copy per field, in the fields' own precision (float32 from every common driver:
    # the tracker selects its points first and converts only those, as it does for a recording)
    xyz_type = np.result_type(*(np.dtype(POINT_TYPES[fields[k].datatype]) for k in ("x", "y", "z")))
    pts = np.empty((n, 3), np.float32 if xyz_type == np.float32 else np.float64)
    for j, k in enumerate(("x", "y", "z")):
        pts[:, j] = rec[k]
    times = None
    for name in TIME_FIELDS:
        if name in fields and name in names:
            times = _time_offsets(rec[name], fields[name].datatype, stamp)
            break
    finite = np.isfinite(pts)
    if finite.all() and (times is None or np.isfinite(times).all()):  # a dense cloud: no masked copies
        ok, dropped = slice(None), 0
    else:
        ok = finite[:, 0] & finite[:, 1] & finite[:, 2]
        if times is not None:
            ok &= np.isfinite(times)
        dropped = int(n - np.count_nonzero(ok))
        if dropped == n:
            raise CloudError(f"no finite point among {n}")
    intensity = np.asarray(rec["intensity"], np.float32)[ok] if "intensity" in names else None
    return Cloud(stamp, pts[ok], intensity, None if times is None else times[ok], dropped)


def _time_offsets(values: np.ndarray, datatype: int, stamp: float) -> np.ndarray:
    """Per-point times (see the module doc) -> (N,) float32 s relative to ``stamp``."""
    if datatype == FLOAT32:
        v = np.asarray(values, np.float32)  # the common case: relative seconds, one copy
        if len(v) and np.nanmax(np.abs(v)) > DAY_S:  # absolute stamps (float32 cannot hold them well)
            return (v.astype(np.float64) - stamp).astype(np.float32)
        return v
    v = values.astype(np.float64)
    if datatype == FLOAT64:
        if len(v) and np.nanmax(np.abs(v)) > DAY_S:  # absolute stamps
            v -= stamp
        return v.astype(np.float32)
    if len(v) and np.max(np.abs(v)) > DAY_S * 1e9:  # absolute nanoseconds
        return ((values.astype(np.float64) * 1e-9) - stamp).astype(np.float32)
    return (v * 1e-9).astype(np.float32)


def imu_message(t: float, acc: np.ndarray, gyro: np.ndarray, frame_id: str) -> m.Imu:
    """sensor_msgs/Imu without orientation (its covariance -1, REP 145). acc m/s^2, gyro rad/s."""
    a, g = np.asarray(acc, float).reshape(3), np.asarray(gyro, float).reshape(3)
    return m.Imu(header=m.Header(stamp=m.stamp_to_time(t), frame_id=frame_id),
                 orientation=m.Quaternion(0.0, 0.0, 0.0, 1.0), orientation_covariance=[-1.0] + [0.0] * 8,
                 angular_velocity=m.Vector3(*map(float, g)), linear_acceleration=m.Vector3(*map(float, a)))


def imu_sample(msg: m.Imu) -> tuple[float, np.ndarray, np.ndarray]:
    """(t s, acc (3,), gyro (3,)) of an Imu message."""
    a, g = msg.linear_acceleration, msg.angular_velocity
    return m.time_to_stamp(msg.header.stamp), np.array([a.x, a.y, a.z]), np.array([g.x, g.y, g.z])


def pose_of(T: np.ndarray) -> m.Pose:
    """(4, 4) -> geometry_msgs/Pose."""
    T = np.asarray(T, np.float64)
    q = quat_xyzw(T[:3, :3])
    return m.Pose(m.Point(*map(float, T[:3, 3])), m.Quaternion(*map(float, q)))


def transform_of(T: np.ndarray) -> m.Transform:
    p = pose_of(T)
    return m.Transform(m.Vector3(p.position.x, p.position.y, p.position.z), p.orientation)


def matrix_of(translation, rotation) -> np.ndarray:
    """A Point/Vector3 and a Quaternion -> (4, 4)."""
    from scipy.spatial.transform import Rotation

    q = np.array([rotation.x, rotation.y, rotation.z, rotation.w], float)
    if not np.isfinite(q).all() or np.linalg.norm(q) < 1e-9:
        raise CloudError("a quaternion that is not a rotation")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
    T[:3, 3] = [translation.x, translation.y, translation.z]
    return T


def ros_covariance(cov_tangent: np.ndarray | None, T_map_body: np.ndarray) -> list[float]:
    """A Pose3 tangent covariance (6, 6) -> 36 floats in ROS order and the map frame (zeros if None)."""
    if cov_tangent is None:
        return [0.0] * 36
    return [float(v) for v in covariance_to_ros(cov_tangent, np.asarray(T_map_body)[:3, :3]).reshape(-1)]


def pose_with_covariance(T_map_body: np.ndarray, cov_tangent, stamp: float, frame_id: str = "map"
                         ) -> m.PoseWithCovarianceStamped:
    return m.PoseWithCovarianceStamped(
        header=m.Header(stamp=m.stamp_to_time(stamp), frame_id=frame_id),
        pose=m.PoseWithCovariance(pose_of(T_map_body), ros_covariance(cov_tangent, T_map_body)))


def odometry(T_map_body: np.ndarray, cov_tangent, velocity_map: np.ndarray, stamp: float, frame_id: str,
             child_frame_id: str) -> m.Odometry:
    """nav_msgs/Odometry: the pose in ``frame_id``, the twist in ``child_frame_id`` (the body)."""
    v_body = np.asarray(T_map_body)[:3, :3].T @ np.asarray(velocity_map, float).reshape(3)
    return m.Odometry(header=m.Header(stamp=m.stamp_to_time(stamp), frame_id=frame_id),
                      child_frame_id=child_frame_id,
                      pose=m.PoseWithCovariance(pose_of(T_map_body), ros_covariance(cov_tangent, T_map_body)),
                      twist=m.TwistWithCovariance(m.Twist(m.Vector3(*map(float, v_body)), m.Vector3())))


def transform_stamped(T_parent_child: np.ndarray, stamp: float, parent: str, child: str) -> m.TransformStamped:
    return m.TransformStamped(header=m.Header(stamp=m.stamp_to_time(stamp), frame_id=parent),
                              child_frame_id=child, transform=transform_of(T_parent_child))


def diagnostics(stamp: float, level: int, name: str, message: str, values: dict) -> m.DiagnosticArray:
    """One DiagnosticStatus; values as KeyValue strings."""
    return m.DiagnosticArray(header=m.Header(stamp=m.stamp_to_time(stamp)),
                             status=[m.DiagnosticStatus(level=int(level), name=name,
                                                        message=message, hardware_id="blockloc",
                                                        values=[m.KeyValue(str(k), str(v)) for k, v in values.items()])])
