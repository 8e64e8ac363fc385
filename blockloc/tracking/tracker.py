"""Building a tracker: :func:`make_tracker` picks the estimator variant, IMU
(:class:`blockloc.tracking.imu_tracker.ImuTracker`) or LiDAR-only
(:class:`blockloc.tracking.lidar_only.LidarOnlyTracker`); both share the frame step of
:class:`blockloc.tracking.estimator.Estimator`. The config is read by the application layer
(``blockloc.app.assemble.make_tracker``), never here.

The names callers used from this module before the split (``Estimate``, ``Diagnostics``,
``REJECT_REASONS``, ``reject_reason``) are re-exported here.
"""

from __future__ import annotations

import numpy as np

from blockloc.tracking.estimator import Estimator, Relocalizer
from blockloc.tracking.imu import ImuNoise
from blockloc.tracking.params import FixedParams, ScanParams, TrackerSettings, TrackingParams
from blockloc.tracking.results import REJECT_REASONS, Diagnostics, Estimate, reject_reason

__all__ = ["REJECT_REASONS", "Diagnostics", "Estimate", "FixedParams", "ScanParams", "Estimator",
           "TrackerSettings", "TrackingParams", "make_tracker", "reject_reason"]


def make_tracker(*, imu: bool, map_provider, registration, T_body_lidar: np.ndarray, T_body_imu: np.ndarray,
                 gravity_map: np.ndarray, settings: TrackerSettings = TrackerSettings(),
                 imu_noise: ImuNoise = ImuNoise(), relocalize: Relocalizer | None = None) -> Estimator:
    """The IMU estimator when ``imu`` (the sequence has an IMU and it is to be used), else the
    LiDAR-only one. T_body_lidar, T_body_imu: (4, 4); gravity_map: (3,) m/s^2 in the map frame."""
    common = dict(map_provider=map_provider, registration=registration, T_body_lidar=T_body_lidar,
                  gravity_map=gravity_map, settings=settings, relocalize=relocalize)
    if imu:
        from blockloc.tracking.imu_tracker import ImuTracker

        return ImuTracker(T_body_imu=T_body_imu, imu_noise=imu_noise, **common)
    from blockloc.tracking.lidar_only import LidarOnlyTracker

    return LidarOnlyTracker(**common)
