"""Global initialization and relocalization of a tracking session: a scan prepared as
``blockloc init`` prepares it (gyro deskew, gravity from the accelerometer), searched around a
hint or over the whole map; only verified poses come back, and every attempt is logged.

An ambiguous result (one scan fits two places nearly equally: a street of repeated structure) is
not dropped: its hypotheses wait for the next scan (:mod:`blockloc.global_init.second_scan`), which
is registered to it for the motion between the two and tested at each hypothesis moved by it. One
hypothesis verified there, and no other, is the answer; still ambiguous, the newer scan's
hypotheses wait for the one after; none plausible, the full search runs again. Verification is
the same as any candidate's."""

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
from blockloc.global_init.second_scan import Ambiguity, follow_up
from blockloc.global_init.verify import InitResult

log = logging.getLogger("blockloc.app.session")

#: an ambiguity waits this long (s) for a later scan; after it, the motion between the two scans is
#: too long to register scan to scan, and the full search runs again
MAX_AMBIGUITY_AGE_S = 3.0
#: hypotheses carried over at most this many scans; then the full search runs again (the true pose
#: may be none of them: along a street the first scan's candidates can all be metres off)
MAX_AMBIGUITY_SCANS = 10


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
        self.ambiguity: Ambiguity | None = None  # an ambiguous scan's hypotheses, waiting for the next

    def global_init(self, frame, hint_xy, hint_yaw, init_info: dict):
        """Global init of one frame (prepared as ``blockloc init`` does); records it in init_info.
        An ambiguity left by an earlier frame is tested with this one first (module docstring;
        ``init_info['second_scan']``). Returns (T_map_body or None when not verified, InitResult,
        stamp of the pose)."""
        if self.localizer is None:
            raise TrackingError("no global localizer: cannot initialize without a pose")
        s = self.settings
        scan = prepare_for_init(frame, self.imu, self.info)
        yaw_window = s.yaw_window_deg if hint_yaw is not None else 360.0
        t0 = time.perf_counter()
        with CompileClock() as jit:
            res = self._follow_up(scan.points_body, scan.gravity_body, scan.stamp, int(frame.index), init_info)
            if res is None:
                try:
                    res = self.localizer.localize(scan.points_body, scan.gravity_body, hint_xy, hint_yaw,
                                                  s.window_m, yaw_window if hint_xy is not None else 360.0)
                except GlobalInitError as exc:
                    # a scan the search cannot start from (open ground, a view blocked close by):
                    # no pose from it, as from an unverified search; a start goes on with the next
                    res = InitResult(None, 0.0, 0.0, [], False, 0.0, False, {"refused": str(exc)})
                    init_info["refused"] = str(exc)
                    init_info["refused_frames"] = init_info.get("refused_frames", 0) + 1
                    log.info("frame %d: global init cannot start from this scan: %s", int(frame.index), exc)
                else:
                    self._remember(res, scan.points_body, scan.stamp, int(frame.index))
        # a first run after install compiles the kernels inside the search: reported apart
        init_info.update(time_s=max(0.0, time.perf_counter() - t0 - jit.seconds), compile_s=jit.seconds,
                         verified=bool(res.verified),
                         fitness=float(res.fitness), score=float(res.score), ambiguous=bool(res.ambiguous),
                         frame=int(frame.index), stamp=scan.stamp)
        init_info["ambiguous_frames"] = init_info.get("ambiguous_frames", 0) + int(bool(res.ambiguous))
        ok = res.T_map_body is not None and res.verified
        if ok and self.ground_truth is not None:
            Tg = self.ground_truth.interpolate(np.array([scan.stamp]))[0]
            init_info["error_m"], init_info["error_deg"] = pose_error(np.asarray(res.T_map_body), Tg)
        return (np.asarray(res.T_map_body) if ok else None), res, scan.stamp

    def _follow_up(self, pts_body: np.ndarray, gravity_body: np.ndarray, stamp: float, frame: int,
                   info: dict | None = None):
        """The waiting ambiguity tested with this scan (module docstring): the InitResult when it
        settled the question (verified) or kept it open (ambiguous: the newer scan's hypotheses
        wait now); None when there was none, it was too old, the motion could not be registered
        or no hypothesis held (the caller searches afresh). ``info``: gets ``second_scan``."""
        amb, self.ambiguity = self.ambiguity, None
        if amb is None or not 0.0 < stamp - amb.stamp <= MAX_AMBIGUITY_AGE_S:
            return None
        try:
            res, what = follow_up(self.localizer, amb, pts_body, gravity_body, self._rotation_between(amb.stamp, stamp))
        except (GlobalInitError, RegistrationError, MapError) as exc:
            log.warning("the ambiguity of t=%.2f could not be tested at t=%.2f: %s", amb.stamp, stamp, exc)
            return None
        what.update(frame=frame, verified=bool(res is not None and res.verified),
                    ambiguous=bool(res is not None and res.ambiguous))
        if info is not None:
            info["second_scan"] = what
        if res is None:
            log.info("t=%.2f: the motion since the ambiguous scan of t=%.2f could not be registered (fitness %.2f)",
                     stamp, amb.stamp, what["motion_fitness"])
            return None
        if res.verified:
            log.info("t=%.2f: the ambiguity of t=%.2f settled by this scan (%d hypotheses, %d scans)", stamp,
                     amb.stamp, len(amb.hypotheses), amb.scans + 1)
            return res
        if res.ambiguous and amb.scans + 1 < MAX_AMBIGUITY_SCANS:
            self._remember(res, pts_body, stamp, frame, amb.scans + 1)
            return res
        return None

    def _remember(self, res, pts_body: np.ndarray, stamp: float, frame: int, scans: int = 1) -> None:
        """Keep an ambiguous result's hypotheses for the next scan (None otherwise)."""
        self.ambiguity = Ambiguity.of(res, self.localizer.params, pts_body, stamp, frame, scans) \
            if getattr(res, "ambiguous", False) else None

    def _rotation_between(self, t0: float, t1: float) -> Optional[np.ndarray]:
        """R_first_second (3, 3): the body's turn from t0 to t1 integrated from the gyro (bias
        neglected), or None without IMU samples over the interval."""
        if self.imu is None or len(self.imu) < 2:
            return None
        near = self.imu.between(t0 - 0.01, t1 + 0.01)
        if len(near) < 2:
            return None
        from blockloc.geometry import so3_exp

        R_body_imu = np.asarray(self.info.T_body_imu, float)[:3, :3]
        times = np.clip(near.t, t0, t1)
        R = np.eye(3)
        for k in range(len(times) - 1):  # zero-order hold of each sample's rate
            R = R @ so3_exp(R_body_imu @ near.gyro[k] * (times[k + 1] - times[k]))
        return R

    def relocalize(self, points_lidar: np.ndarray, hint: Optional[np.ndarray], gravity_body: np.ndarray,
                   stamp: float) -> Optional[np.ndarray]:
        """The tracker's recovery: global init of a scan (lidar frame) around ``hint``
        (T_map_body), and, when nothing there is verified, over the whole map (the place index:
        a kidnapped robot is outside any window around its last pose). An ambiguity left by an
        earlier attempt is tested with this scan first (module docstring). Only a verified pose is
        returned; a failed or impossible attempt returns None. Every attempt is in ``reloc_log``."""
        if self.localizer is None:
            return None
        pts_body = transform_points(self.info.T_body_lidar, points_lidar)
        if self.ambiguity is not None:
            g = self._gravity_at(stamp, gravity_body)
            t0 = time.perf_counter()
            what: dict = {}
            res = self._follow_up(pts_body, g, stamp, -1, what)
            if "second_scan" in what:
                self.log.append({"stamp": float(stamp), "hint": False,
                                 "verified": bool(res is not None and res.verified),
                                 "ambiguous": bool(res is not None and res.ambiguous),
                                 "fitness": float(res.fitness) if res is not None else 0.0,
                                 "time_s": time.perf_counter() - t0, "second_scan": what["second_scan"]})
            if res is not None and res.verified and res.T_map_body is not None:
                return np.asarray(res.T_map_body)
            if res is not None:
                return None  # still ambiguous: the next scan's evidence decides
        T, searched = self._relocalize_once(pts_body, hint, gravity_body, stamp)
        if T is None and searched and hint is not None and self.ambiguity is None:
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
        self._remember(res, pts_body, stamp, -1)
        if not res.verified or res.T_map_body is None:
            log.info("relocalization at t=%.2f%s: no verified match (best fitness %.2f)", stamp,
                     "" if hint is not None else " over the whole map", res.fitness)
            return None, True
        return np.asarray(res.T_map_body), True
