"""Global initialization and relocalization of a tracking session: a scan prepared as
``blockloc init`` prepares it (gyro deskew, gravity from the accelerometer), searched around a
hint or over the whole map; only verified poses come back, and every attempt is logged."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from blockloc.errors import GlobalInitError, MapError, RegistrationError, TrackingError
from blockloc.geometry import transform_points
from blockloc.global_init.relocalize import pose_error
from blockloc.jit import CompileClock
from blockloc.global_init.scan_prep import gravity_from_imu, prepare_for_init

log = logging.getLogger("blockloc.app.session")


@dataclass(frozen=True)
class GlobalInitSettings:
    """Search windows of global init: window_m (side, m) and yaw_window_deg around a hint."""

    window_m: float = 40.0
    yaw_window_deg: float = 360.0


class Recovery:
    """Global init and relocalization with a ``GlobalLocalizer`` (or None: neither is possible).

    settings: the search windows; info: the sequence's SequenceInfo; imu: its ImuData;
    ground_truth: a Trajectory or None (the error of a verified pose is recorded); counters: the
    session's counters (``map_faults`` counts map entries that could not be read). ``log``: one
    dict per relocalization attempt.
    """

    def __init__(self, localizer, settings: GlobalInitSettings, info, imu, ground_truth, counters: dict) -> None:
        self.localizer = localizer
        self.settings = settings
        self.info = info
        self.imu = imu
        self.ground_truth = ground_truth
        self.counters = counters
        self.log: list[dict] = []

    def global_init(self, frame, hint_xy, hint_yaw, init_info: dict):
        """Global init of one frame (prepared as ``blockloc init`` does); records it in init_info.
        Returns (T_map_body or None when not verified, InitResult, stamp of the pose)."""
        if self.localizer is None:
            raise TrackingError("no global localizer: cannot initialize without a pose")
        s = self.settings
        scan = prepare_for_init(frame, self.imu, self.info)
        yaw_window = s.yaw_window_deg if hint_yaw is not None else 360.0
        t0 = time.perf_counter()
        with CompileClock() as jit:
            res = self.localizer.localize(scan.points_body, scan.gravity_body, hint_xy, hint_yaw, s.window_m,
                                          yaw_window if hint_xy is not None else 360.0)
        # a first run after install compiles the kernels inside the search: reported apart
        init_info.update(time_s=time.perf_counter() - t0 - jit.seconds, compile_s=jit.seconds,
                         verified=bool(res.verified),
                         fitness=float(res.fitness), score=float(res.score), ambiguous=bool(res.ambiguous),
                         frame=int(frame.index), stamp=scan.stamp)
        ok = res.T_map_body is not None and res.verified
        if ok and self.ground_truth is not None:
            Tg = self.ground_truth.interpolate(np.array([scan.stamp]))[0]
            init_info["error_m"], init_info["error_deg"] = pose_error(np.asarray(res.T_map_body), Tg)
        return (np.asarray(res.T_map_body) if ok else None), res, scan.stamp

    def relocalize(self, points_lidar: np.ndarray, hint: Optional[np.ndarray], gravity_body: np.ndarray,
                   stamp: float) -> Optional[np.ndarray]:
        """The tracker's recovery: global init of a scan (lidar frame) around ``hint``
        (T_map_body), and, when nothing there is verified, over the whole map (the place index:
        a kidnapped robot is outside any window around its last pose). Only a verified pose is
        returned; a failed or impossible attempt returns None. Every attempt is in ``reloc_log``."""
        if self.localizer is None:
            return None
        pts_body = transform_points(self.info.T_body_lidar, points_lidar)
        T, searched = self._relocalize_once(pts_body, hint, gravity_body, stamp)
        if T is None and searched and hint is not None:
            # The hint's attitude comes from a state that has diverged: level the scan by the
            # accelerometer when there is one.
            T, _ = self._relocalize_once(pts_body, None, self._gravity_at(stamp, gravity_body), stamp)
        return T

    def _gravity_at(self, stamp: float, fallback: np.ndarray) -> np.ndarray:
        """Gravity (3,) in the body frame at ``stamp`` from the accelerometer, else ``fallback``."""
        if self.imu is None or len(self.imu) == 0:
            return np.asarray(fallback, float)
        try:
            return gravity_from_imu(self.imu, float(stamp), self.info.T_body_imu)
        except GlobalInitError:
            return np.asarray(fallback, float)

    def _relocalize_once(self, pts_body: np.ndarray, hint: Optional[np.ndarray], gravity_body: np.ndarray,
                         stamp: float) -> tuple[Optional[np.ndarray], bool]:
        """(verified T_map_body or None, whether the search ran: False when global init could not
        start, e.g. a scan too sparse to project, which another search would not change)."""
        s = self.settings
        entry = {"stamp": float(stamp), "hint": hint is not None}
        try:
            if hint is None:
                res = self.localizer.localize(pts_body, gravity_body, None, None, s.window_m, 360.0)
            else:
                yaw = float(np.arctan2(hint[1, 0], hint[0, 0]))
                res = self.localizer.localize(pts_body, gravity_body, (float(hint[0, 3]), float(hint[1, 3])),
                                              yaw, s.window_m, s.yaw_window_deg)
        except (GlobalInitError, RegistrationError, MapError) as exc:
            # e.g. a scan too sparse to project, or a map entry that cannot be read: this attempt
            # failed, tracking goes on
            if isinstance(exc, MapError):
                self.counters["map_faults"] += 1
            log.warning("relocalization at t=%.2f failed: %s", stamp, exc)
            self.log.append({**entry, "verified": False, "fitness": 0.0, "time_s": 0.0, "error": str(exc)})
            return None, False
        self.log.append({**entry, "verified": bool(res.verified), "ambiguous": bool(res.ambiguous),
                               "fitness": float(res.fitness), "time_s": float(res.time_s)})
        if not res.verified or res.T_map_body is None:
            log.info("relocalization at t=%.2f%s: no verified match (best fitness %.2f)", stamp,
                     "" if hint is not None else " over the whole map", res.fitness)
            return None, True
        return np.asarray(res.T_map_body), True
