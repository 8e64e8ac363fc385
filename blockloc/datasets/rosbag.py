"""ROS1 ``.bag`` and ROS2 (sqlite3, mcap) bags as Sequences, via ``rosbags`` (no ROS needed).

Reading: ``sensor_msgs/PointCloud2`` on ``lidar_topic`` (fields x, y, z; optional intensity
(``intensity`` | ``i``), ring (``ring`` | ``line`` | ``channel``) and per-point time) and
``sensor_msgs/Imu`` on ``imu_topic``. Frame stamps and IMU stamps are the message header stamps.

Per-point time conventions (the field found first among ``time``, ``t``, ``timestamp``,
``offset_time``):
- floating point, |value| < 1e6: seconds relative to the header stamp (Velodyne driver ``time``;
  M2DGR's VLP-32C bags; Hesai relative mode).
- floating point, larger: absolute time; seconds if < 1e11, else nanoseconds (Hesai/Livox
  ``timestamp`` float64); converted to seconds relative to the header stamp.
- integer, < 1e12: nanoseconds relative to the header stamp (Ouster ``t`` uint32, Livox
  ``offset_time`` uint32).
- integer, larger: absolute nanoseconds (some Livox/Robosense exports).
Offsets are returned relative to the frame's ``stamp`` (= header stamp) and may be negative.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable, Iterator, Literal

import numpy as np

from blockloc.datasets.base import ImuData, LidarFrame, SequenceInfo, frame_index
from blockloc.errors import DatasetError
from blockloc.geometry import Trajectory

log = logging.getLogger(__name__)

_PCL_TYPE = "sensor_msgs/msg/PointCloud2"
_IMU_TYPE = "sensor_msgs/msg/Imu"
# sensor_msgs/PointField datatype -> numpy type char
_PF_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_TIME_FIELDS = ("time", "t", "timestamp", "offset_time")
_RING_FIELDS = ("ring", "line", "channel")
_INTENSITY_FIELDS = ("intensity", "i")


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def decode_pointcloud2(msg, *, min_range_m: float = 0.0, max_range_m: float = np.inf
                       ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """A deserialized PointCloud2 -> points (N, 3) float32, intensity (N,) float32 | None,
    time offsets (N,) float32 s relative to the header stamp | None, ring (N,) uint16 | None.

    Non-finite points (organized clouds pad with NaN) and points outside the range limits are
    dropped. Raises DatasetError when x, y or z is missing.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise DatasetError(f"PointCloud2 lacks field(s) {missing}; has {sorted(fields)}")
    end = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _PF_DTYPES:
            continue
        names.append(f.name)
        base = end + _PF_DTYPES[f.datatype]
        formats.append(base if f.count <= 1 else (base, (f.count,)))
        offsets.append(f.offset)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                      "itemsize": msg.point_step})
    data = np.asarray(msg.data, dtype=np.uint8)
    n_pts = int(msg.width) * int(msg.height)
    if n_pts == 0 or msg.point_step == 0:
        cloud = np.zeros(0, dtype=dtype)
    elif msg.row_step == msg.width * msg.point_step:
        cloud = np.frombuffer(data[: n_pts * msg.point_step].tobytes(), dtype=dtype)
    else:  # rows padded
        rows = data[: msg.height * msg.row_step].reshape(msg.height, msg.row_step)
        cloud = np.frombuffer(rows[:, : msg.width * msg.point_step].tobytes(), dtype=dtype)
    pts = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float32)
    r2 = np.einsum("ij,ij->i", pts.astype(np.float64), pts.astype(np.float64))
    keep = np.isfinite(r2) & (r2 >= min_range_m ** 2) & (r2 <= max_range_m ** 2)
    intensity = next((cloud[n].astype(np.float32) for n in _INTENSITY_FIELDS if n in fields), None)
    ring = next((cloud[n].astype(np.uint16) for n in _RING_FIELDS if n in fields), None)
    tname = next((n for n in _TIME_FIELDS if n in fields), None)
    offsets_s = None
    if tname is not None:
        offsets_s = point_time_offsets(cloud[tname], _stamp_ns(msg.header))
    pick = lambda a: None if a is None else a[keep]  # noqa: E731
    return pts[keep], pick(intensity), pick(offsets_s), pick(ring)


def point_time_offsets(values: np.ndarray, stamp_ns: int) -> np.ndarray:
    """Per-point time field (N,) -> seconds (N,) float32 relative to the header stamp (see the
    module docstring for the conventions)."""
    if len(values) == 0:
        return np.zeros(0, dtype=np.float32)
    v = np.asarray(values)
    mag = float(np.nanmax(np.abs(v)))
    if np.issubdtype(v.dtype, np.floating):
        if mag < 1e6:
            return v.astype(np.float32)
        if mag < 1e11:  # absolute seconds
            sec, ns = divmod(stamp_ns, 1_000_000_000)
            return ((v.astype(np.float64) - sec) - ns * 1e-9).astype(np.float32)
        return ((v.astype(np.float64) - float(stamp_ns)) * 1e-9).astype(np.float32)
    if mag < 1e12:
        return (v.astype(np.float64) * 1e-9).astype(np.float32)
    return ((v.astype(np.int64) - np.int64(stamp_ns)) * 1e-9).astype(np.float32)


def _open_reader(path: Path):
    from rosbags.highlevel import AnyReader

    if not path.exists():
        raise DatasetError(f"{path}: bag not found; expected a ROS1 .bag file or a ROS2 bag "
                           "directory (metadata.yaml + .db3 or .mcap)")
    try:
        reader = AnyReader([path])
        reader.open()
    except Exception as exc:  # rosbags raises its own error types per format
        raise DatasetError(f"{path}: cannot be read as a ROS bag ({exc})") from None
    return reader


SIDECAR_SUFFIX = ".blockloc.json"


def sidecar_path(bag: str | Path) -> Path:
    """The calibration / ground-truth sidecar beside a bag: ``<bag>.blockloc.json`` (a ROS1
    ``x.bag`` -> ``x.bag.blockloc.json``; a ROS2 bag directory ``x/`` -> ``x.blockloc.json``)."""
    bag = Path(bag)
    return bag.with_name(bag.name.rstrip("/") + SIDECAR_SUFFIX)


def write_sidecar(bag: str | Path, *, T_body_lidar, T_body_imu, gravity_map,
                  ground_truth: str | None = None, mapping_poses: str | None = None) -> Path:
    """Write the sidecar the loader reads (see ``RosbagSequence``): extrinsics (4x4, body <- sensor),
    gravity in the map frame (m/s^2) and the names of the ground-truth / mapping-pose files
    (relative to the bag's directory; NCLT csv or TUM, T_map_body)."""
    import json

    from blockloc.fileio import atomic_write_text

    doc = {"format": "blockloc bag sidecar", "version": 1,
           "T_body_lidar": np.asarray(T_body_lidar, float).tolist(),
           "T_body_imu": np.asarray(T_body_imu, float).tolist(),
           "gravity_map": [float(g) for g in gravity_map]}
    if ground_truth:
        doc["ground_truth"] = str(ground_truth)
    if mapping_poses:
        doc["mapping_poses"] = str(mapping_poses)
    out = sidecar_path(bag)
    atomic_write_text(out, json.dumps(doc, indent=1) + "\n")
    return out


def _read_sidecar(bag: Path) -> dict:
    import json

    p = sidecar_path(bag)
    if not p.is_file():
        return {}
    try:
        doc = json.loads(p.read_text())
        for k in ("T_body_lidar", "T_body_imu"):
            if k in doc and np.asarray(doc[k], float).shape != (4, 4):
                raise ValueError(f"{k} is not 4x4")
        if "gravity_map" in doc and np.asarray(doc["gravity_map"], float).shape != (3,):
            raise ValueError("gravity_map is not 3 numbers")
    except (ValueError, TypeError) as exc:
        raise DatasetError(f"{p}: not a valid bag sidecar ({exc}); expected JSON with T_body_lidar "
                           "(4x4), T_body_imu (4x4), gravity_map (3) and optional ground_truth") from None
    for k in ("ground_truth", "mapping_poses"):
        if k in doc:
            doc[k] = p.parent / doc[k]
    return doc


class RosbagSequence:
    """A ROS1/ROS2 bag as a ``Sequence``.

    On open, the lidar topic is indexed (bag time and header stamp of every message, read from
    the raw message bytes without decoding the clouds); ``frame(i)`` then reads the one message.
    Points are in the cloud's own frame (``lidar``). Calibration and ground truth come from the
    arguments, else from a sidecar ``<bag>.blockloc.json`` beside the bag (``write_sidecar``;
    ``blockloc sim --format rosbag1|rosbag2`` writes one), else ``T_body_lidar``/``T_body_imu``
    are identity and ``gravity_map`` z-up. ``ground_truth_path``: a TUM file (``t x y z qx qy
    qz qw``) or an NCLT-style csv, T_map_body. ``mapping_poses()``: the sidecar's mapping poses
    (a mapping drive's offline-SLAM poses) or the ground truth.
    """

    def __init__(self, path: str | Path, *, lidar_topic: str, imu_topic: str,
                 T_body_lidar: np.ndarray | None = None, T_body_imu: np.ndarray | None = None,
                 gravity_map=None, ground_truth_path: str | Path | None = None,
                 min_range_m: float = 0.0, max_range_m: float = np.inf, name: str | None = None):
        self.path = Path(path)
        side = _read_sidecar(self.path)
        if side:
            log.info("%s: calibration and ground truth from %s", self.path, sidecar_path(self.path))
        T_body_lidar = side.get("T_body_lidar") if T_body_lidar is None else T_body_lidar
        T_body_imu = side.get("T_body_imu") if T_body_imu is None else T_body_imu
        if gravity_map is None:
            gravity_map = side.get("gravity_map", (0.0, 0.0, -9.81))
        ground_truth_path = ground_truth_path or side.get("ground_truth")
        self._mp_path = side.get("mapping_poses")
        self._mp: Trajectory | None = None
        self.lidar_topic, self.imu_topic = lidar_topic, imu_topic
        self.min_range_m, self.max_range_m = float(min_range_m), float(max_range_m)
        self._reader = _open_reader(self.path)
        topics = {c.topic: c.msgtype for c in self._reader.connections}
        for topic, want in ((lidar_topic, _PCL_TYPE), (imu_topic, _IMU_TYPE)):
            if topic not in topics:
                listing = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "none"
                raise DatasetError(f"{self.path}: no topic {topic!r}; the bag has: {listing}")
            if topics[topic] != want:
                raise DatasetError(f"{self.path}: topic {topic!r} carries {topics[topic]}, "
                                   f"expected {want}")
        self._lidar_conns = [c for c in self._reader.connections if c.topic == lidar_topic]
        self._imu_conns = [c for c in self._reader.connections if c.topic == imu_topic]
        self._index_lidar()
        self._imu: ImuData | None = None
        self._gt_path = Path(ground_truth_path) if ground_truth_path else None
        self._gt: Trajectory | None | bool = False
        self.info = SequenceInfo(
            name=name or f"bag:{self.path.name}",
            T_body_lidar=np.eye(4) if T_body_lidar is None else np.asarray(T_body_lidar, float),
            T_body_imu=np.eye(4) if T_body_imu is None else np.asarray(T_body_imu, float),
            gravity_map=np.asarray(gravity_map, dtype=np.float64),
            lidar_rate_hz=_rate(self._stamps_ns), imu_rate_hz=self._imu_rate())

    def _index_lidar(self) -> None:
        bag_ts, stamps = [], []
        for conn, ts, raw in self._reader.messages(connections=self._lidar_conns):
            bag_ts.append(ts)
            stamps.append(_raw_header_stamp_ns(raw, conn))
        bag_ts = np.asarray(bag_ts, dtype=np.int64)
        stamps = np.asarray(stamps, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        keep = np.concatenate([[True], np.diff(stamps[order]) > 0]) if len(order) else order.astype(bool)
        if not keep.all():
            log.warning("%s: dropped %d %s messages with a duplicate header stamp",
                        self.path, int((~keep).sum()), self.lidar_topic)
        self._bag_ts = bag_ts[order][keep]
        self._stamps_ns = stamps[order][keep]

    def _imu_rate(self) -> float:
        ts = []
        for conn, _, raw in self._reader.messages(connections=self._imu_conns):
            ts.append(_raw_header_stamp_ns(raw, conn))
            if len(ts) >= 200:
                break
        return _rate(np.sort(np.asarray(ts, dtype=np.int64)))

    # protocol ----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._stamps_ns)

    def frame_stamps(self) -> np.ndarray:
        return self._stamps_ns * 1e-9

    def frame(self, index: int) -> LidarFrame:
        index = frame_index(index, len(self))
        ts = int(self._bag_ts[index])
        want = int(self._stamps_ns[index])
        for conn, _, raw in self._reader.messages(connections=self._lidar_conns, start=ts, stop=ts + 1):
            if _raw_header_stamp_ns(raw, conn) == want:
                return self._to_frame(index, conn, raw)
        raise DatasetError(f"{self.path}: {self.lidar_topic} message at bag time {ts} ns vanished")

    def _to_frame(self, index, conn, raw) -> LidarFrame:
        msg = self._reader.deserialize(raw, conn.msgtype)
        pts, inten, offs, ring = decode_pointcloud2(msg, min_range_m=self.min_range_m,
                                                    max_range_m=self.max_range_m)
        if len(pts) == 0:
            log.warning("%s: %s message %d holds no valid points", self.path, self.lidar_topic, index)
        return LidarFrame(index, _stamp_ns(msg.header) * 1e-9, pts, inten, offs, ring)

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[LidarFrame]:
        stop = len(self) if stop is None else min(stop, len(self))
        if start >= stop:
            return
        # one sequential pass over the bag's time range is far cheaper than per-frame seeks
        t0, t1 = int(self._bag_ts[start:stop].min()), int(self._bag_ts[start:stop].max()) + 1
        wanted = {}
        for i in range(start, stop):
            wanted.setdefault(int(self._stamps_ns[i]), i)
        pending = {}
        next_i = start
        for conn, _, raw in self._reader.messages(connections=self._lidar_conns, start=t0, stop=t1):
            i = wanted.get(_raw_header_stamp_ns(raw, conn))
            if i is None or i in pending:
                continue
            pending[i] = (conn, raw)
            while next_i in pending:
                c, r = pending.pop(next_i)
                yield self._to_frame(next_i, c, r)
                next_i += 1
        while next_i < stop:  # anything not met in the pass (should not happen): fetch directly
            yield self.frame(next_i)
            next_i += 1

    def imu(self) -> ImuData:
        if self._imu is None:
            from blockloc.datasets.nclt import clean_imu

            t, acc, gyro = [], [], []
            for conn, _, raw in self._reader.messages(connections=self._imu_conns):
                m = self._reader.deserialize(raw, conn.msgtype)
                t.append(_stamp_ns(m.header))
                a, g = m.linear_acceleration, m.angular_velocity
                acc.append((a.x, a.y, a.z))
                gyro.append((g.x, g.y, g.z))
            t = np.asarray(t, dtype=np.int64)
            t0 = int(t.min()) if len(t) else 0
            self._imu = clean_imu(f"{self.path}:{self.imu_topic}", (t - t0) * 1e-9 + t0 * 1e-9,
                                  np.asarray(acc, float).reshape(-1, 3),
                                  np.asarray(gyro, float).reshape(-1, 3))
        return self._imu

    def ground_truth(self) -> Trajectory | None:
        if self._gt is False:
            self._gt = read_trajectory_file(self._gt_path) if self._gt_path else None
        return self._gt

    def mapping_poses(self) -> Trajectory | None:
        if self._mp_path is not None:
            if self._mp is None:
                self._mp = read_trajectory_file(self._mp_path)
            return self._mp
        return self.ground_truth()

    def close(self) -> None:
        self._reader.close()


def _rate(stamps_ns: np.ndarray) -> float:
    dt = np.diff(np.asarray(stamps_ns, dtype=np.int64)) * 1e-9
    dt = dt[dt > 0]
    return float(round(1.0 / np.median(dt), 1)) if len(dt) else 10.0


def _raw_header_stamp_ns(raw: bytes, conn) -> int:
    """Header stamp from a serialized message's first bytes (no full decode).

    ROS1: uint32 seq, uint32 sec, uint32 nsec. ROS2 CDR: 4-byte encapsulation (byte 1 = 1 for
    little endian), int32 sec, uint32 nanosec.
    """
    b = bytes(raw[:12])
    if conn.digest and len(conn.digest) == 32 and not conn.digest.startswith("RIHS"):
        # ROS1 md5 digest
        sec, nsec = np.frombuffer(b[4:12], dtype="<u4")
        return int(sec) * 1_000_000_000 + int(nsec)
    little = b[1] == 1
    sec, nsec = np.frombuffer(b[4:12], dtype="<i4" if little else ">i4")
    return int(sec) * 1_000_000_000 + int(np.uint32(nsec))


def read_trajectory_file(path: str | Path) -> Trajectory:
    """TUM (``t x y z qx qy qz qw``, space separated, ``#`` comments) or NCLT csv -> Trajectory.

    Rows holding NaN are dropped with a warning; DatasetError names the line of a short row.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: ground-truth file not found (expected TUM: t x y z qx qy qz qw)")
    with open(path) as fh:
        first = next((ln for ln in fh if ln.strip() and not ln.lstrip().startswith("#")), "")
    if "," in first:
        from blockloc.datasets.nclt import read_groundtruth_csv

        return read_groundtruth_csv(path)
    from scipy.spatial.transform import Rotation

    rows = []
    with open(path) as fh:
        for lineno, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            if len(parts) < 8:
                raise DatasetError(f"{path}:{lineno}: {len(parts)} columns, expected 8 "
                                   "(t x y z qx qy qz qw)")
            try:
                rows.append([float(p) for p in parts[:8]])
            except ValueError:
                raise DatasetError(f"{path}:{lineno}: non-numeric value, expected t x y z qx qy qz qw") from None
    data = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    bad = ~np.isfinite(data).all(axis=1)
    if bad.any():
        log.warning("%s: dropped %d rows holding NaN/inf", path, int(bad.sum()))
        data = data[~bad]
    data = data[np.argsort(data[:, 0], kind="stable")]
    data = data[np.concatenate([[True], np.diff(data[:, 0]) > 0])] if len(data) else data
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(data[:, 4:8]).as_matrix()
    poses[:, :3, 3] = data[:, 1:4]
    return Trajectory(data[:, 0], poses)


# --- writer -----------------------------------------------------------------------------------

def _pointcloud2_msg(types, frame: LidarFrame, frame_id: str, ros1: bool):
    """LidarFrame -> PointCloud2 with x y z intensity (float32), ring (uint16), time (float32 s
    relative to the header stamp): the Velodyne driver's XYZIRT layout."""
    PointField = types["sensor_msgs/msg/PointField"]
    n = len(frame.points)
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "time"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
                   "offsets": [0, 4, 8, 12, 16, 18], "itemsize": 22})
    cloud = np.zeros(n, dtype=dt)
    pts = np.asarray(frame.points)
    cloud["x"], cloud["y"], cloud["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if frame.intensity is not None:
        cloud["intensity"] = frame.intensity
    if frame.ring is not None:
        cloud["ring"] = frame.ring
    if frame.time_offsets is not None:
        cloud["time"] = frame.time_offsets
    fields = [PointField(name="x", offset=0, datatype=7, count=1),
              PointField(name="y", offset=4, datatype=7, count=1),
              PointField(name="z", offset=8, datatype=7, count=1),
              PointField(name="intensity", offset=12, datatype=7, count=1),
              PointField(name="ring", offset=16, datatype=4, count=1),
              PointField(name="time", offset=18, datatype=7, count=1)]
    return types["sensor_msgs/msg/PointCloud2"](
        header=_header(types, frame.stamp, frame_id, ros1, frame.index), height=1, width=n,
        fields=fields, is_bigendian=False, point_step=22, row_step=22 * n,
        data=np.frombuffer(cloud.tobytes(), dtype=np.uint8), is_dense=True)


def _header(types, stamp_s: float, frame_id: str, ros1: bool, seq: int = 0):
    ns = int(round(stamp_s * 1e9))
    Time = types["builtin_interfaces/msg/Time"]
    t = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    Header = types["std_msgs/msg/Header"]
    if ros1:
        return Header(seq=seq, stamp=t, frame_id=frame_id)
    return Header(stamp=t, frame_id=frame_id)


def write_rosbag(path: str | Path, frames: Iterable[LidarFrame], imu: ImuData, *,
                 version: Literal["ros1", "ros2-sqlite3", "ros2-mcap"] = "ros1",
                 lidar_topic: str = "/velodyne_points", imu_topic: str = "/imu",
                 frame_id: str = "velodyne", imu_frame_id: str = "imu") -> Path:
    """Write frames (PointCloud2, Velodyne XYZIRT layout) and IMU (sensor_msgs/Imu) to a bag.

    ``path``: the .bag file (ros1) or the bag directory (ros2). Frames are streamed; messages
    are written in time order (IMU samples interleaved up to each frame's stamp). Written into a
    temp path beside ``path`` and renamed at the end.
    """
    import os
    import shutil
    import tempfile

    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    ros1 = version == "ros1"
    if version not in ("ros1", "ros2-sqlite3", "ros2-mcap"):
        raise DatasetError(f"rosbag version {version!r}: expected ros1, ros2-sqlite3 or ros2-mcap")
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = store.types
    path.parent.mkdir(parents=True, exist_ok=True)
    tmpdir = Path(tempfile.mkdtemp(prefix=f"{path.name}.tmp-", dir=path.parent))
    tmp = tmpdir / path.name
    try:
        if ros1:
            from rosbags.rosbag1 import Writer

            writer = Writer(tmp)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if version == "ros2-mcap" else StoragePlugin.SQLITE3
            writer = Writer(tmp, version=9, storage_plugin=plugin)
        serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
        with writer:
            lc = writer.add_connection(lidar_topic, _PCL_TYPE, typestore=store)
            ic = writer.add_connection(imu_topic, _IMU_TYPE, typestore=store)
            Vector3 = types["geometry_msgs/msg/Vector3"]
            Quat = types["geometry_msgs/msg/Quaternion"]
            ImuMsg = types[_IMU_TYPE]
            cov = np.zeros(9)
            j = 0

            def write_imu_until(t_end: float):
                nonlocal j
                while j < len(imu.t) and imu.t[j] <= t_end:
                    a, g = imu.acc[j], imu.gyro[j]
                    m = ImuMsg(header=_header(types, float(imu.t[j]), imu_frame_id, ros1, j),
                               orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
                               orientation_covariance=np.array([-1.0] + [0.0] * 8),
                               angular_velocity=Vector3(x=float(g[0]), y=float(g[1]), z=float(g[2])),
                               angular_velocity_covariance=cov,
                               linear_acceleration=Vector3(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                               linear_acceleration_covariance=cov)
                    writer.write(ic, int(round(float(imu.t[j]) * 1e9)), serialize(m, _IMU_TYPE))
                    j += 1

            for frame in frames:
                write_imu_until(frame.stamp)
                msg = _pointcloud2_msg(types, frame, frame_id, ros1)
                writer.write(lc, int(round(frame.stamp * 1e9)), serialize(msg, _PCL_TYPE))
            write_imu_until(np.inf)
        if path.exists():
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        os.replace(tmp, path)
        return path
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


# ----------------------------------------------------------------------------- as a --seq path
PRESET = None  # no preset fits every bag


def detect(path: Path) -> bool:
    """True for a ROS1 ``.bag`` file or a ROS2 bag directory (``metadata.yaml``)."""
    return (path.is_file() and path.suffix == ".bag") or (path.is_dir() and (path / "metadata.yaml").is_file())


def open_path(path: Path, options: dict) -> "RosbagSequence":
    """The bag at ``path``; options: lidar_topic, imu_topic, min_range_m, max_range_m."""
    return RosbagSequence(path, lidar_topic=options.get("lidar_topic") or "/velodyne_points",
                          imu_topic=options.get("imu_topic") or "/imu",
                          min_range_m=options.get("min_range_m", 0.0), max_range_m=options.get("max_range_m", np.inf))
