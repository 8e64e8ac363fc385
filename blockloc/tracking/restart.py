"""How an estimator restarts at a verified pose a search found while it tracked (a relocalization,
a new initial pose): :class:`Restarts`, a base of :class:`blockloc.tracking.estimator.Estimator`.
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger("blockloc.tracking.estimator")


class Restarts:
    """The restart path of an estimator (it provides ``initialize``, ``map_provider``, ``window``,
    ``_last_good_motion``, ``_preprocess``, ``_predict_and_deskew``, ``_align``, ``_gates``)."""

    def restart(self, T_map_body: np.ndarray, stamp: float, scan=None):
        """Restart the window at a verified pose a search found while tracking (a relocalization,
        a new initial pose), at ``stamp`` (the keyframe time). scan: (points (N, 3) lidar frame,
        time offsets (N,) s, frame stamp s) of the sweep the pose was found on, as the tracker
        prepared it, or None. Returns the map provider's local map there (or None).

        The diverged state's velocity and biases are not to be trusted (seen: 6 m/s and 0.9 m/s^2
        of accelerometer bias after a kidnapped start). Restart from the last accepted keyframe's:
        its velocity in the body frame turned into the new pose (a robot drives on the way it
        faces; zero instead made the next scans 0.25-0.35 m off, reported ok: the prediction and
        the deskew of the first scans a whole speed wrong), held loosely, and its biases (they
        change slowly), held by the initial bias prior; zero velocity without one.

        The pose itself came from a scan deskewed with the diverged motion, or with the gyro only
        (seen: 0.13 m off at 1.5 m/s, 0.35 m at 5 m/s, reported ok): the scan is deskewed again
        with the restarted motion and registered from it, and the window restarts there when the
        fit is healthy (a tight pose prior and an NDT factor that far apart leave the estimate at
        the prior: the NDT factor's robust loss discounts it)."""
        T = np.asarray(T_map_body, dtype=np.float64)
        v_body, bias = self._last_good_motion if self._last_good_motion is not None else (np.zeros(3), None)
        v_map = T[:3, :3] @ v_body
        sigma = self.settings.fixed.recover_sigma_vel_m_s
        self.initialize(T, stamp, velocity_map=v_map, bias=bias, sigma_vel_m_s=sigma)
        # The next scan registers against the map where the robot is now, not where it was.
        relocate = getattr(self.map_provider, "relocate", None)
        local = None if relocate is None else relocate(T[:3, 3].copy(), v_map.copy(), stamp)
        if scan is not None and local is not None:
            T_ndt = self._register_restart(local, *scan, stamp)
            if T_ndt is not None:
                self.initialize(T_ndt, stamp, velocity_map=v_map, bias=bias, sigma_vel_m_s=sigma)
        return local

    def restart_on(self, frame, T_map_body: np.ndarray):
        """:meth:`restart` at ``frame.stamp`` with that frame (a LidarFrame) prepared as the tracker prepares scans."""
        points, offsets = self._preprocess(frame)
        return self.restart(T_map_body, float(frame.stamp), (points, offsets, float(frame.stamp)))

    def _register_restart(self, local, points, offsets, stamp, t_key) -> np.ndarray | None:
        """T_map_body registered from the restarted state's prediction, or None (no map, too few
        points, an unhealthy fit)."""
        target = getattr(local, "target", None)
        if target is None or len(points) < self.settings.scan.min_points:
            return None
        T_pred, _, pts = self._predict_and_deskew(points, offsets, stamp, t_key, t_key, self.window.latest)
        try:
            T_ndt, _, _, _, _, reason = self._align(target, pts, T_pred, T_pred, self._gates(0.0))
        except Exception as exc:  # noqa: BLE001 - the restart stands on the search's pose alone
            log.debug("no refinement of the restart pose: %s", exc)
            return None
        return None if reason else T_ndt
