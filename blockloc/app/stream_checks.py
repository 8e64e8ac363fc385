"""Gaps in a session's sensor streams: logged once per gap and counted (``imu_gaps``,
``lidar_gaps``), never a reason to stop tracking; points a loader dropped for NaN/inf
coordinates, counted (``nonfinite_points``) and warned about once."""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

log = logging.getLogger("blockloc.app.session")

IMU_GAP_WARN_S = 0.5  # an IMU gap longer than this is logged and counted (once per gap)
LIDAR_GAP_FACTOR = 3.0  # a gap between scans of more than this many scan periods is logged
LIVE_PERIOD_SCANS = 50  # a source of unknown rate: its scan period is the median of this many last spacings


class StreamChecks:
    """info: the sequence's SequenceInfo (``lidar_rate_hz``; 0: unknown, a live source: the scan
    period is learned from the stamps); counters: the session's counters."""

    def __init__(self, info, counters: dict) -> None:
        self.info = info
        self.counters = counters
        self._last_stamp: float | None = None
        self._spacings: deque[float] = deque(maxlen=LIVE_PERIOD_SCANS)  # s, between the last scans
        self._imu_gap_s = 0.0  # the longest gap of the IMU gap in progress, or 0

    def restart(self) -> None:
        """The stream started over (a live source's stamps jumped back): no gap in progress."""
        self._last_stamp = None
        self._imu_gap_s = 0.0

    def imu_gap(self, index: int, gap_s: float) -> None:
        """Count a gap of the IMU stream once, logged on the first frame it spans and on the
        frame where samples are back (the frames between see the same gap, growing)."""
        if gap_s > IMU_GAP_WARN_S:
            if self._imu_gap_s == 0.0:
                self.counters["imu_gaps"] += 1
                log.warning("frame %d: an IMU gap: no samples for the last %.2f s", index, gap_s)
            self._imu_gap_s = max(self._imu_gap_s, gap_s)
        elif self._imu_gap_s > 0.0:
            log.warning("frame %d: IMU samples again, after a gap of %.2f s", index, self._imu_gap_s)
            self._imu_gap_s = 0.0

    def scan_period(self) -> float | None:
        """The scan period, s: the sequence's (``1 / lidar_rate_hz``: a recorded sequence's median
        stamp spacing), else (rate 0, a live source) the median spacing of the last
        LIVE_PERIOD_SCANS scans seen, the same rule on what has come so far; None before a spacing."""
        rate = float(getattr(self.info, "lidar_rate_hz", 0.0) or 0.0)
        if rate > 0:
            return 1.0 / rate
        return float(np.median(self._spacings)) if self._spacings else None

    def lidar_frame(self, frame) -> None:
        """Count and log a gap before ``frame`` longer than LIDAR_GAP_FACTOR scan periods, and the
        points its loader dropped for NaN/inf coordinates."""
        self._count_nonfinite(frame)
        stamp = float(frame.stamp)
        if self._last_stamp is not None:
            gap = stamp - self._last_stamp
            period = self.scan_period()  # from the spacings before this one
            if period is not None and gap > LIDAR_GAP_FACTOR * period:
                self.counters["lidar_gaps"] += 1
                log.warning("frame %d: no LiDAR scan for %.2f s before it", frame.index, gap)
            if gap > 0:
                self._spacings.append(gap)
        self._last_stamp = stamp

    def _count_nonfinite(self, frame) -> None:
        """Count the points the loader dropped for NaN/inf coordinates (``num_nonfinite``;
        metrics: nonfinite_points); the first frame with any is warned about, naming it."""
        n = int(getattr(frame, "num_nonfinite", 0) or 0)
        if n:
            if not self.counters.get("nonfinite_points"):
                log.warning("frame %d: %d points with NaN/inf coordinates dropped (counted in metrics "
                            "nonfinite_points; later frames are not warned about)", frame.index, n)
            self.counters["nonfinite_points"] = self.counters.get("nonfinite_points", 0) + n
