"""Building a tracker: :func:`make_tracker` picks the estimator variant, IMU
(:class:`blockloc.tracking.imu_tracker.ImuTracker`) or LiDAR-only
(:class:`blockloc.tracking.lidar_only.LidarOnlyTracker`); both share the frame step of
:class:`blockloc.tracking.estimator.Estimator`. :func:`tracker_from_config` is the boundary that
reads the config; ``Tracker.from_config`` is the name the session calls it by (until the
application layer's assemble takes it over).

The names callers used from this module before the split (``Estimate``, ``Diagnostics``,
``REJECT_REASONS``, ``reject_reason``) are re-exported here.
"""

from __future__ import annotations

import numpy as np

from blockloc.tracking.estimator import Estimator, Relocalizer
from blockloc.tracking.imu import ImuNoise
from blockloc.tracking.params import FixedParams, ScanParams, TrackerSettings, TrackingParams
from blockloc.tracking.results import REJECT_REASONS, Diagnostics, Estimate, reject_reason

__all__ = ["REJECT_REASONS", "Diagnostics", "Estimate", "FixedParams", "ScanParams", "Estimator", "Tracker",
           "TrackerSettings", "TrackingParams", "make_tracker", "reject_reason", "tracker_from_config"]


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


def settings_from_config(cfg) -> TrackerSettings:
    """The tracker's settings from a ``blockloc.config.Config``: the ``tracking`` section as is,
    the scan cut from the ``lidar`` and ``dataset`` sections field by field."""
    lc, dc = cfg.lidar, cfg.dataset
    scan = ScanParams(voxel_size_m=lc.voxel_size_m, max_points=lc.max_points, min_range_m=dc.min_range_m,
                      max_range_m=dc.max_range_m, deskew=lc.deskew)
    return TrackerSettings(tracking=cfg.tracking, scan=scan)


def tracker_from_config(cfg, info, *, map_provider, registration, relocalize=None,
                        use_imu: bool | None = None) -> Estimator:
    """From a ``blockloc.config.Config`` and a ``SequenceInfo``.

    use_imu: whether to use the IMU, e.g. ``len(seq.imu()) > 0 and cfg.tracking.use_imu`` (the
    caller knows whether the sequence has one); None: ``cfg.tracking.use_imu``.
    """
    imu = cfg.tracking.use_imu if use_imu is None else bool(use_imu)
    return make_tracker(imu=imu, map_provider=map_provider, registration=registration,
                        T_body_lidar=info.T_body_lidar, T_body_imu=info.T_body_imu, gravity_map=info.gravity_map,
                        settings=settings_from_config(cfg), imu_noise=ImuNoise.from_config(cfg.imu),
                        relocalize=relocalize)


class Tracker:
    """``Tracker.from_config``: :func:`tracker_from_config` under the name the session calls."""

    from_config = staticmethod(tracker_from_config)
