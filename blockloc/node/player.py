"""``Player``: a sequence published as a robot's ROS 2 topics at its recorded pace.

Publishes, in stamp order: every IMU sample (sensor_msgs/Imu on ``imu_topic``, best effort), every
scan once its sweep is over (sensor_msgs/PointCloud2 on ``points_topic``, best effort, header
stamp = the frame stamp, per-point ``time`` offsets from it, in the LiDAR frame), the ground
truth at each scan stamp when the sequence has some (nav_msgs/Odometry ``map -> base_link`` on
``/blockloc/ground_truth``), and once, latched, the extrinsics on ``/tf_static``
(``base_link -> lidar``, ``base_link -> imu``).

Pace: message stamps against a monotonic clock, scaled by ``rate`` (``on_pace`` is told where it
starts: a stamp and the clock second it is due); a player that falls behind
publishes at once and does not skip. ``loop`` starts over (the stamps jump back, as a restarted
recording does).
"""

from __future__ import annotations

import heapq
import logging
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameNames:
    """TF frame names: map, odom, base (the body), lidar, imu."""

    map: str = "map"
    odom: str = "odom"
    base: str = "base_link"
    lidar: str = "lidar"
    imu: str = "imu"


@dataclass
class PlayStats:
    scans: int = 0
    imu: int = 0
    ground_truth: int = 0
    loops: int = 0
    late_s: float = 0.0  # the largest lag behind the pace, s


class Player:
    """Publish ``seq`` (a Sequence) over ``dds`` (a :class:`blockloc.ros2.dds.Dds`)."""

    def __init__(self, dds, seq, *, rate: float = 1.0, loop: bool = False, max_frames: int | None = None,
                 points_topic: str = "/points", imu_topic: str = "/imu/data",
                 ground_truth_topic: str = "/blockloc/ground_truth", frames: FrameNames = FrameNames(),
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 on_pace: Callable[[float, float], None] | None = None) -> None:
        from blockloc.ros2 import messages as m
        from blockloc.ros2.dds import LATCHED, RELIABLE, SENSOR_DATA

        if not rate > 0:
            raise ValueError("rate must be positive")
        self.seq, self.rate, self.loop, self.max_frames = seq, float(rate), bool(loop), max_frames
        self.frames = frames
        self.clock, self.sleep = clock, sleep
        self.on_pace = on_pace  # (stamp s, clock s it is due at): called when a pass starts
        self.stats = PlayStats()
        self._points = dds.writer(points_topic, m.PointCloud2, SENSOR_DATA)
        self._imu = dds.writer(imu_topic, m.Imu, SENSOR_DATA)
        self._gt = dds.writer(ground_truth_topic, m.Odometry, RELIABLE)
        self._tf_static = dds.writer("/tf_static", m.TFMessage, LATCHED)

    def publish_static(self, stamp: float) -> None:
        from blockloc.ros2 import convert
        from blockloc.ros2 import messages as m

        info, f = self.seq.info, self.frames
        self._tf_static.write(m.TFMessage(transforms=[
            convert.transform_stamped(info.T_body_lidar, stamp, f.base, f.lidar),
            convert.transform_stamped(info.T_body_imu, stamp, f.base, f.imu)]))

    def _events(self):
        """(publish time s, kind, payload) in time order: IMU samples and scans (at sweep end)."""
        n = len(self.seq) if self.max_frames is None else min(len(self.seq), int(self.max_frames))
        imu = self.seq.imu()
        t_end_scans = None
        stamps = np.asarray(self.seq.frame_stamps(), float)[:n]
        if n:
            t_end_scans = float(stamps[-1]) + 0.2
        imu_events = ((float(imu.t[i]), 0, i) for i in range(len(imu))
                      if t_end_scans is None or (stamps[0] - 1.0 <= imu.t[i] <= t_end_scans))

        def scans():
            for frame in self.seq.frames(0, n):
                off = frame.time_offsets
                end = float(frame.stamp) + (float(np.max(off)) if off is not None and len(off) else 0.0)
                yield end, 1, frame

        return heapq.merge(imu_events, scans(), key=lambda e: (e[0], e[1]))

    def run(self, should_stop: Callable[[], bool] = lambda: False) -> PlayStats:
        """Publish until the end (or forever with ``loop``), or until ``should_stop()``."""
        while True:
            self._play_once(should_stop)
            if not self.loop or should_stop():
                return self.stats
            self.stats.loops += 1
            log.info("play: from the start again (loop %d)", self.stats.loops + 1)

    def _play_once(self, should_stop) -> None:
        from blockloc.ros2 import convert

        imu = self.seq.imu()
        gt = self.seq.ground_truth()
        f = self.frames
        start_wall = None
        start_t = None
        for t, kind, payload in self._events():
            if should_stop():
                return
            if start_wall is None:
                start_wall, start_t = self.clock(), t
                if self.on_pace is not None:
                    self.on_pace(start_t, start_wall)
                self.publish_static(t)
            wait = start_wall + (t - start_t) / self.rate - self.clock()
            if wait > 0:
                self.sleep(wait)
            else:
                self.stats.late_s = max(self.stats.late_s, -wait)
            if kind == 0:
                self._imu.write(convert.imu_message(t, imu.acc[payload], imu.gyro[payload], f.imu))
                self.stats.imu += 1
                continue
            frame = payload
            self._points.write(convert.cloud_from_points(frame.points, frame.stamp, f.lidar,
                                                         time_offsets=frame.time_offsets, intensity=frame.intensity))
            self.stats.scans += 1
            if gt is not None and gt.stamps[0] <= frame.stamp <= gt.stamps[-1]:
                T = gt.interpolate(np.array([frame.stamp]))[0]
                h = 0.05
                p = gt.interpolate(np.array([frame.stamp - h, frame.stamp + h]))[:, :3, 3]
                self._gt.write(convert.odometry(T, None, (p[1] - p[0]) / (2 * h), frame.stamp, f.map, f.base))
                self.stats.ground_truth += 1
