"""``LocalizationNode``: blockloc as a live ROS 2 node over DDS.

In: sensor_msgs/PointCloud2 (``points_topic``), sensor_msgs/Imu (``imu_topic``), /tf (an
``odom -> base_link`` from the robot's odometry), /tf_static (``base_link -> <cloud frame>``,
``base_link -> <imu frame>``), /initialpose (PoseWithCovarianceStamped, frame ``map``: global
init around it), /blockloc/relocalize (std_msgs/Empty: global init over the whole map).

Out, per processed scan and stamped with its header stamp: /blockloc/pose
(PoseWithCovarianceStamped, ``map``), /blockloc/odom (Odometry, covariance from the window's
marginals), /tf (``map -> odom`` when an ``odom -> base_link`` is seen, else ``map ->
base_link``), /diagnostics (state initializing / ok / degraded / lost / no data, fitness,
latency, block, dropped scans); /blockloc/local_map (PointCloud2, reliable + transient local)
again at every block switch. Nothing is published as a pose before a verified initialization.

Only verified poses go out: a scan whose registration passed the tracker's acceptance tests
(status ok) or a pose found by a verified global init (recovered). The pose of a rejected scan,
or the IMU's prediction when no scan could be registered, is withheld from /blockloc/pose,
/blockloc/odom and /tf (navigation stacks read those, not /diagnostics): the transform then goes
stale, which tf2 users see as a lookup that fails after their timeout, rather than a wrong pose
taken as good. /diagnostics still comes for every scan: state degraded, ``pose_published``
False, ``poses_withheld`` counted. The pose is published the moment the tracker has it, before
the run folder, the MCAP recording, the local map and the diagnostics.

Real time: Cyclone's receive threads only queue. Scans are processed on one worker thread in
arrival order (:class:`blockloc.node.buffer.ScanBuffer`): while tracking at most ``queue_size``
wait, and when processing falls behind the oldest is dropped; while a global initialization runs
(and while the worker catches up after it) up to ``backlog_size`` wait, thinned evenly when
more come, so the tracker follows them from the verified pose to the newest scan instead of
jumping seconds ahead. Every drop is counted (in the diagnostics). Every IMU sample is kept
(until fed). Time is the messages' stamps; wall time only measures latency and how long no
scan came (``no data``).
A scan stamp that jumps back (a player restarted) resets the tracker (one warning line).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from blockloc.errors import BlocklocError
from blockloc.node.buffer import ScanBuffer
from blockloc.node.player import FrameNames

log = logging.getLogger(__name__)

STATES = ("initializing", "ok", "degraded", "lost", "no data")
_LEVEL = {"ok": 0, "initializing": 1, "degraded": 1, "lost": 2, "no data": 3}
_STATE_OF = {"ok": "ok", "recovered": "ok", "rejected": "degraded", "imu_only": "degraded", "lost": "lost",
             "uninitialized": "initializing"}
# statuses whose pose is published: verified by this scan's registration (ok) or by a global init
# (recovered); a rejected scan's or an IMU-only prediction is withheld from /blockloc/pose, /odom and /tf
_PUBLISHED = ("ok", "recovered")


def _freeze_heap() -> None:
    """Move every object alive now (the map, the place index, the session, compiled kernels) out of
    the garbage collector's reach: a full collection then walks only what tracking made since.
    Measured in-process (small world's loc session, 0.5x, 300 scans, wall time of the collections,
    1-min load 22-39): without it 3 full collections, 2.0 s in all, the longest 1.15 s; with it 2,
    0.80 s in all, the longest 0.64 s. A pause like that makes the scans waiting behind it late,
    or dropped."""
    import gc

    gc.freeze()


@dataclass
class NodeSettings:
    """points_topic, imu_topic: ROS topics in. frames: TF frame names. queue_size: scans that may
    wait while tracking (older ones are dropped). backlog_size: scans that may wait while a global
    initialization runs and the worker catches up after it (thinned evenly past it; 40 scans of
    64k points hold about 80 MB). no_data_timeout_s: wall seconds without a scan before the
    diagnostics say "no data". imu_timeout_s: stamp seconds without an IMU sample before the end
    of a sweep after which tracking goes on LiDAR-only. extrinsics_wait_s: wall seconds the first
    scan waits for /tf_static. local_map_points_max: points of /blockloc/local_map (thinned)."""

    points_topic: str = "/points"
    imu_topic: str = "/imu/data"
    frames: FrameNames = field(default_factory=FrameNames)
    queue_size: int = 2
    backlog_size: int = 40
    no_data_timeout_s: float = 5.0
    imu_timeout_s: float = 0.5
    extrinsics_wait_s: float = 1.0
    local_map_points_max: int = 200_000


@dataclass
class NodeStats:
    received: int = 0
    processed: int = 0
    dropped: int = 0
    bad_scans: int = 0
    failed_scans: int = 0
    max_waiting: int = 0  # the most scans ever waiting at once (at most backlog_size)
    caught_up: int = 0  # scans processed while catching up after a global initialization
    verified_inits: int = 0  # global initializations that restarted the tracker
    nan_points: int = 0
    imu_samples: int = 0
    imu_out_of_order: int = 0
    restarts: int = 0
    published: int = 0
    withheld: int = 0  # poses of rejected or IMU-only scans, not published (degraded in /diagnostics)
    refused_initialposes: int = 0
    latency_ms: list = field(default_factory=list)


class LocalizationNode:
    """The node on ``dds`` (a :class:`blockloc.ros2.dds.Dds`).

    make_session(info, imu) -> Session: the tracking session for a source with ``info``
    (SequenceInfo: extrinsics from /tf_static, gravity) and the IMU samples received so far
    (ImuData; none: LiDAR-only). map_bounds: ((xmin, ymin), (xmax, ymax)) of the map, metres, for
    refusing an /initialpose outside it. gravity_map: (3,) m/s^2. init_pose: (x, y, yaw or None).
    on_frame(frame, est): called on the worker with each processed scan (LidarFrame) and the
    tracker's Estimate of it, in order, after its pose and diagnostics are published (e.g.
    :class:`blockloc.node.changes.NodeChanges`); it should return quickly (the next scan waits).
    on_restart(): called on the worker when the source restarted (scan stamps jumped back), before
    the first scan after it is processed (e.g. :meth:`NodeChanges.restart`).
    """

    def __init__(self, dds, make_session: Callable, *, settings: NodeSettings = NodeSettings(),
                 gravity_map=(0.0, 0.0, -9.81), map_bounds=None, init_pose: tuple | None = None,
                 on_frame: Callable | None = None, on_restart: Callable | None = None) -> None:
        from blockloc.ros2 import messages as m
        from blockloc.ros2.dds import LATCHED, RELIABLE, SENSOR_DATA

        self.settings = s = settings
        self.make_session = make_session
        self.on_frame = on_frame
        self.on_restart = on_restart
        self.gravity_map = np.asarray(gravity_map, float)
        self.map_bounds = map_bounds
        self.stats = NodeStats()
        self.session = None
        self.state = "initializing"
        self._hint = init_pose  # (x, y, yaw|None) for the next global init
        self._relocalize = False
        self._lock = threading.Condition()
        self._scans = ScanBuffer(s.queue_size, s.backlog_size)
        self._imu_t: list[float] = []
        self._imu_acc: list = []
        self._imu_gyro: list = []
        self._imu_last: float | None = None
        self._imu_frame: str | None = None
        self._static: dict[tuple[str, str], np.ndarray] = {}
        self._T_odom_base: np.ndarray | None = None
        self._last_stamp: float | None = None
        self._last_arrival = time.monotonic()
        self._no_data_said = False
        self._lidar_only_said = False
        self._next_index = 0
        self._local_version = None
        self._stop = threading.Event()
        self._failure: BaseException | None = None
        f = s.frames
        self._frames = f  # before the readers: a listener reader (/tf) may call back at once
        self._pub_pose = dds.writer("/blockloc/pose", m.PoseWithCovarianceStamped, RELIABLE)
        self._pub_odom = dds.writer("/blockloc/odom", m.Odometry, RELIABLE)
        self._pub_tf = dds.writer("/tf", m.TFMessage, RELIABLE)
        self._pub_diag = dds.writer("/diagnostics", m.DiagnosticArray, RELIABLE)
        self._pub_map = dds.writer("/blockloc/local_map", m.PointCloud2, LATCHED)
        # Polled (not on Cyclone's delivery thread, which would wait for the GIL while the worker
        # computes), with histories deep enough to outlast a stall: the backlog's scans, and
        # 10 s of IMU at 200 Hz (every sample is kept). Best effort, as sensor drivers publish.
        dds.reader(s.points_topic, m.PointCloud2, self._on_cloud, ("sensor", max(SENSOR_DATA[1], s.backlog_size)),
                   poll=True)
        dds.reader(s.imu_topic, m.Imu, self._on_imu, ("sensor", 2000), poll=True)
        dds.reader("/tf", m.TFMessage, self._on_tf, SENSOR_DATA, ignore_own=True)  # not the node's own transforms
        dds.reader("/tf_static", m.TFMessage, self._on_tf_static, LATCHED)
        dds.reader("/initialpose", m.PoseWithCovarianceStamped, self._on_initialpose, RELIABLE)
        dds.reader("/blockloc/relocalize", m.Empty, self._on_relocalize, RELIABLE)
        self._worker = threading.Thread(target=self._work, name="blockloc-node", daemon=True)

    # ----------------------------------------------------------------- receive threads (queue only)
    def _on_cloud(self, msg) -> None:
        from blockloc.ros2.messages import time_to_stamp

        stamp = time_to_stamp(msg.header.stamp)
        with self._lock:
            self.stats.received += 1
            self.stats.dropped += len(self._scans.push(stamp, (msg, time.monotonic())))
            self.stats.max_waiting = max(self.stats.max_waiting, len(self._scans))
            self._last_arrival = time.monotonic()
            self._lock.notify_all()

    def _on_imu(self, msg) -> None:
        from blockloc.ros2.convert import imu_sample

        t, acc, gyro = imu_sample(msg)
        with self._lock:
            self._imu_frame = msg.header.frame_id
            if self._imu_last is not None and t <= self._imu_last:
                if t < self._imu_last - 1.0:  # the source restarted: its scans will say so too
                    self._imu_t.clear(), self._imu_acc.clear(), self._imu_gyro.clear()
                else:
                    self.stats.imu_out_of_order += 1
                    if self.stats.imu_out_of_order == 1:
                        log.warning("IMU sample at t=%.3f is not after the last one (t=%.3f): out-of-order "
                                    "samples are dropped (counted in the diagnostics)", t, self._imu_last)
                    return
            self._imu_last = t
            self._imu_t.append(t)
            self._imu_acc.append(acc)
            self._imu_gyro.append(gyro)
            self.stats.imu_samples += 1

    def _on_tf(self, msg) -> None:
        from blockloc.ros2.convert import matrix_of

        f = self._frames
        for tr in msg.transforms:
            if tr.header.frame_id == f.odom and tr.child_frame_id == f.base:
                self._T_odom_base = matrix_of(tr.transform.translation, tr.transform.rotation)

    def _on_tf_static(self, msg) -> None:
        from blockloc.ros2.convert import matrix_of

        with self._lock:
            for tr in msg.transforms:
                self._static[(tr.header.frame_id, tr.child_frame_id)] = matrix_of(tr.transform.translation,
                                                                                  tr.transform.rotation)
            self._lock.notify_all()

    def _on_initialpose(self, msg) -> None:
        from blockloc.geometry import R_to_rpy
        from blockloc.ros2.convert import matrix_of

        p = msg.pose.pose
        if msg.header.frame_id != self._frames.map:
            self.stats.refused_initialposes += 1
            log.warning("/initialpose refused: frame %r, expected %r", msg.header.frame_id, self._frames.map)
            return
        if not self._inside_map(p.position.x, p.position.y):
            self.stats.refused_initialposes += 1
            log.warning("/initialpose refused: (%.1f, %.1f) is outside the map", p.position.x, p.position.y)
            return
        try:
            yaw = float(R_to_rpy(matrix_of(p.position, p.orientation)[:3, :3])[2])
        except Exception:  # noqa: BLE001 - a quaternion that is no rotation: position only
            yaw = None
        with self._lock:
            self._hint = (float(p.position.x), float(p.position.y), yaw)
        log.info("/initialpose: global init around (%.1f, %.1f) on the next scan", p.position.x, p.position.y)

    def _on_relocalize(self, _msg) -> None:
        with self._lock:
            self._relocalize = True
        log.info("/blockloc/relocalize: global init over the whole map on the next scan")

    def _inside_map(self, x: float, y: float) -> bool:
        if self.map_bounds is None:
            return True
        (x0, y0), (x1, y1) = self.map_bounds
        return bool(np.isfinite([x, y]).all() and x0 <= x <= x1 and y0 <= y <= y1)

    # ----------------------------------------------------------------- the worker
    def start(self) -> "LocalizationNode":
        self._worker.start()
        return self

    def spin(self, should_stop: Callable[[], bool]) -> None:
        """Until ``should_stop()`` (or the worker failed: re-raised here)."""
        while not should_stop():
            if self._failure is not None:
                raise self._failure
            time.sleep(0.05)

    def close(self, interrupted: bool = False):
        """Stop the worker (after its current scan) and finish the session: its RunResult, or
        None when no scan ever came."""
        self._stop.set()
        with self._lock:
            self._lock.notify_all()
        if self._worker.is_alive():
            self._worker.join()
        if self.session is None:
            return None
        return self.session.finish(interrupted=interrupted)

    def _work(self) -> None:
        try:
            while not self._stop.is_set():
                with self._lock:
                    if not self._scans:
                        self._lock.wait(0.05)
                    catching_up = self._scans.catching_up
                    item = self._scans.pop()
                if item is None:
                    self._check_no_data()
                    continue
                self._no_data_said = False
                try:
                    self._process(*item, catching_up=catching_up)
                except Exception as exc:  # noqa: BLE001 - one scan's failure, the node goes on
                    self.stats.failed_scans += 1
                    log.error("scan %d could not be processed: %s: %s", self._next_index - 1, type(exc).__name__, exc,
                              exc_info=log.isEnabledFor(logging.DEBUG))
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            log.error("the node's worker stopped: %s", exc)
            self._failure = exc

    def _check_no_data(self) -> None:
        quiet = time.monotonic() - self._last_arrival
        if quiet > self.settings.no_data_timeout_s and not self._no_data_said:
            self._no_data_said = True
            self.state = "no data"
            log.warning("no scan on %s for %.1f s", self.settings.points_topic, quiet)
            self._publish_diagnostics(self._last_stamp or 0.0, None, {})

    def _process(self, msg, arrived: float, catching_up: bool = False) -> None:
        from blockloc.datasets.base import LidarFrame
        from blockloc.ros2.convert import CloudError, cloud_arrays

        try:
            cloud = cloud_arrays(msg)
        except CloudError as exc:
            self.stats.bad_scans += 1
            log.warning("scan skipped: %s", exc)
            return
        frame = LidarFrame(self._next_index, cloud.stamp, cloud.points, cloud.intensity, cloud.time_offsets)
        self._next_index += 1
        if cloud.dropped:
            self.stats.nan_points += cloud.dropped
        if self._last_stamp is not None and frame.stamp <= self._last_stamp:
            if frame.stamp < self._last_stamp - 1e-6:
                self.stats.restarts += 1
                log.warning("scan stamps jumped back from t=%.3f to t=%.3f (the source restarted?): "
                            "tracking starts over", self._last_stamp, frame.stamp)
                self._restart()
            else:
                self.stats.bad_scans += 1
                log.warning("scan at t=%.3f repeats the last stamp: skipped", frame.stamp)
                return
        self._last_stamp = frame.stamp
        if self.session is None:
            self._make_session(msg.header.frame_id)
            _freeze_heap()
        self._feed_imu()
        self._watch_imu(frame)
        session = self.session
        with self._lock:
            hint, self._hint = self._hint, None
            reloc, self._relocalize = self._relocalize, False
        if not session.tracker.initialized or hint is not None or reloc:
            log.info("t=%.2f: global init %s", frame.stamp, "over the whole map" if hint is None
                     else f"around ({hint[0]:.1f}, {hint[1]:.1f})")
            with self._lock:  # the scans coming while it searches wait, to be caught up on
                self._scans.start_backlog()
            t0 = time.monotonic()
            try:
                ok = session.reinitialize(frame, hint)
            except BlocklocError as exc:  # e.g. a scan that cannot be levelled without an IMU
                ok = False
                log.warning("t=%.2f: global init failed: %s", frame.stamp, exc)
            if ok:
                self.stats.verified_inits += 1
                _freeze_heap()
                with self._lock:
                    waiting = len(self._scans)
                log.info("t=%.2f: verified pose in %.2f s; catching up on %d scans that came meanwhile",
                         frame.stamp, time.monotonic() - t0, waiting)
            if not ok:
                if hint is not None and not session.tracker.initialized:
                    with self._lock:
                        self._hint = self._hint or hint  # try around it again on the next scan
                log.info("t=%.2f: global init%s found no verified pose%s", frame.stamp,
                         "" if hint is None else f" around ({hint[0]:.1f}, {hint[1]:.1f})",
                         "" if session.tracker.initialized else "; still initializing")
        published: dict = {}

        def publish_first(est) -> None:  # the pose goes out before the run folder, MCAP, diagnostics
            try:
                published["latency_ms"] = self._publish_pose(frame, est, arrived)
            except Exception as exc:  # noqa: BLE001 - the session still records the scan
                log.error("the pose of scan %d could not be published: %s: %s", frame.index, type(exc).__name__, exc)

        est = session.step(frame, on_estimate=publish_first)
        if "latency_ms" not in published:  # no tracker estimate (not initialized): nothing published
            published["latency_ms"] = (time.monotonic() - arrived) * 1e3
        self.stats.processed += 1
        self.stats.caught_up += int(catching_up)
        if session.tracker.initialized:
            with self._lock:
                self._scans.end_backlog()
        self._publish_after(frame, est, published["latency_ms"], catching_up)
        if self.on_frame is not None:
            self.on_frame(frame, est)

    def _restart(self) -> None:
        if self.session is not None:
            self.session.restart_stream()
        self._local_version = None
        if self.on_restart is not None:
            try:
                self.on_restart()
            except Exception as exc:  # noqa: BLE001 - a hook's failure never stops tracking
                log.error("the restart hook failed: %s: %s", type(exc).__name__, exc)

    def _make_session(self, lidar_frame: str) -> None:
        from blockloc.datasets.base import ImuData, SequenceInfo

        f = self._frames
        t0 = time.monotonic()
        with self._lock:
            while (f.base, lidar_frame) not in self._static and time.monotonic() - t0 < self.settings.extrinsics_wait_s:
                self._lock.wait(0.05)
            T_body_lidar = self._static.get((f.base, lidar_frame))
            T_body_imu = self._static.get((f.base, self._imu_frame)) if self._imu_frame else None
            imu = ImuData(np.asarray(self._imu_t, float), np.asarray(self._imu_acc, float).reshape(-1, 3),
                          np.asarray(self._imu_gyro, float).reshape(-1, 3))
            self._imu_t, self._imu_acc, self._imu_gyro = [], [], []
        if T_body_lidar is None:
            log.warning("no /tf_static %s -> %s: the LiDAR is taken at the body origin", f.base, lidar_frame)
        if len(imu) and T_body_imu is None:
            log.warning("no /tf_static %s -> %s: the IMU is taken at the body origin", f.base, self._imu_frame)
        if not len(imu):
            log.warning("no IMU on %s: LiDAR-only tracking (as track --no-imu)", self.settings.imu_topic)
            self._lidar_only_said = True
        info = SequenceInfo("live", T_body_lidar=np.eye(4) if T_body_lidar is None else T_body_lidar,
                            T_body_imu=np.eye(4) if T_body_imu is None else T_body_imu,
                            gravity_map=self.gravity_map,
                            lidar_rate_hz=0.0)  # unknown: the session's gap check learns it from the stamps
        self.session = self.make_session(info, imu)

    def _feed_imu(self) -> None:
        with self._lock:
            t, acc, gyro = self._imu_t, self._imu_acc, self._imu_gyro
            self._imu_t, self._imu_acc, self._imu_gyro = [], [], []
        if t:
            self.session.extend_imu(np.asarray(t), np.asarray(acc), np.asarray(gyro))

    def _watch_imu(self, frame) -> None:
        """The IMU stopped (no sample for imu_timeout_s before the sweep's end): LiDAR-only from here."""
        if self.session.tracker.lidar_only or self._lidar_only_said:
            return
        imu = self.session.imu
        t_end = frame.stamp + (float(np.max(frame.time_offsets)) if frame.time_offsets is not None else 0.0)
        last = float(imu.t[-1]) if len(imu) else -np.inf
        if t_end - last > self.settings.imu_timeout_s:
            self._lidar_only_said = True
            log.warning("no IMU sample on %s since t=%.2f (scan at t=%.2f): LiDAR-only tracking from here",
                        self.settings.imu_topic, last, frame.stamp)
            self.session.drop_imu()

    # ----------------------------------------------------------------- publishing
    def _publish_pose(self, frame, est, arrived: float) -> float:
        """/blockloc/pose, /blockloc/odom and /tf of a verified estimate (status ok or recovered);
        any other is withheld (counted, and said in the diagnostics). Returns the latency from the
        scan's arrival to here, ms."""
        from blockloc.geometry import inv_T
        from blockloc.ros2 import convert
        from blockloc.ros2 import messages as m

        f = self._frames
        status = est.diagnostics.status
        if est.T_map_body is not None and status in _PUBLISHED:
            stamp = float(frame.stamp)
            T = np.asarray(est.T_map_body)
            self._pub_pose.write(convert.pose_with_covariance(T, est.covariance, stamp, f.map))
            T_odom_base = self._T_odom_base
            if T_odom_base is not None:
                tf = convert.transform_stamped(T @ inv_T(T_odom_base), stamp, f.map, f.odom)
            else:
                tf = convert.transform_stamped(T, stamp, f.map, f.base)
            self._pub_tf.write(m.TFMessage(transforms=[tf]))
            self._pub_odom.write(convert.odometry(T, est.covariance, est.velocity_map, stamp, f.map, f.base))
            self.stats.published += 1
        elif est.T_map_body is not None:
            self.stats.withheld += 1
        return (time.monotonic() - arrived) * 1e3

    def _publish_after(self, frame, est, latency_ms: float, catching_up: bool = False) -> None:
        """What follows the pose: the node's state, the local map at a block switch, the diagnostics."""
        status = est.diagnostics.status
        self.state = _STATE_OF.get(status, "degraded")
        stamp = float(frame.stamp)
        self._publish_local_map(stamp)
        self.stats.latency_ms.append(latency_ms)
        # catching_up: the scan waited through a global initialization (its latency is that wait)
        self._publish_diagnostics(stamp, est, {"latency_ms": f"{latency_ms:.1f}", "catching_up": catching_up,
                                               "pose_published": status in _PUBLISHED
                                               and est.T_map_body is not None})

    def _publish_local_map(self, stamp: float) -> None:
        from blockloc.ros2 import convert

        provider = self.session.provider
        local = provider.current() if hasattr(provider, "current") else None
        if local is None or local.version == self._local_version:
            return
        self._local_version = local.version
        pts = np.asarray(local.points)
        if len(pts) > self.settings.local_map_points_max:
            pts = pts[np.linspace(0, len(pts) - 1, self.settings.local_map_points_max).astype(int)]
        self._pub_map.write(convert.cloud_from_points(pts, stamp, self._frames.map))

    def _publish_diagnostics(self, stamp: float, est, extra: dict) -> None:
        from blockloc.ros2 import convert

        d = est.diagnostics if est is not None else None
        values = {"state": self.state, "stamp": f"{stamp:.6f}", "scans_received": self.stats.received,
                  "scans_processed": self.stats.processed, "dropped_scans": self.stats.dropped,
                  "waiting_scans": len(self._scans), "caught_up_scans": self.stats.caught_up,
                  "verified_inits": self.stats.verified_inits,
                  "bad_scans": self.stats.bad_scans, "restarts": self.stats.restarts,
                  "imu_out_of_order": self.stats.imu_out_of_order,
                  "poses_published": self.stats.published, "poses_withheld": self.stats.withheld,
                  "lidar_only": bool(self.session is not None and self.session.tracker.lidar_only)}
        if d is not None:
            values.update(status=d.status, fitness=f"{d.fitness:.3f}", block=d.block_id, update_ms=f"{d.update_ms:.1f}")
        values.update(extra)
        self._pub_diag.write(convert.diagnostics(stamp, _LEVEL[self.state], "blockloc: localization", self.state,
                                                 values))
