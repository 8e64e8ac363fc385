"""The tracker's settings, each declared once.

:class:`TrackingParams` IS the config's ``tracking`` section (``blockloc.config`` imports it): the
YAML keys are its fields, with their defaults and bounds; the estimators read it directly.
:class:`ScanParams` holds what the tracker takes from the ``lidar`` and ``dataset`` sections (the
app layer copies those field by field), :class:`FixedParams` what no config exposes (priors of a
first keyframe, LiDAR odometry noise, retry cadence).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from blockloc.bounds import COUNT, FRACTION, NON_NEGATIVE, POSITIVE, bounded


@dataclass
class TrackingParams:
    """The ``tracking`` section: sliding window, scan acceptance, NDT factor, LiDAR-only prior."""

    window_size: int = bounded(20, COUNT)  # N_a: keyframes inside a block
    window_size_on_switch: int = bounded(5, COUNT)  # N_r: keyframes kept when the map switches
    # Not used by any estimator (every scan is a keyframe); kept so existing configs load.
    keyframe_distance_m: float = bounded(0.0, NON_NEGATIVE)
    ndt_information_scale: float = bounded(1.0, POSITIVE)
    degeneracy_eigenvalue_ratio: float = bounded(0.01, FRACTION)
    robust_loss: str = "huber"  # huber | anything else: no robust loss on the NDT factor
    min_fitness: float = bounded(0.4, FRACTION)
    max_innovation_m: float = bounded(1.0, POSITIVE)
    use_odometry_factor: bool = False
    max_innovation_deg: float = bounded(10.0, POSITIVE)
    # rejected scans in a row before relocalizing around the last good pose
    max_bad_frames: int = bounded(3, COUNT)
    ndt_min_sigma_trans_m: float = bounded(0.02, POSITIVE)  # floor of the NDT factor's standard deviations
    ndt_min_sigma_rot_deg: float = bounded(0.1, POSITIVE)
    huber_k: float = bounded(1.345, POSITIVE)
    lm_iterations: int = bounded(6, COUNT)
    imu_noise_inflation: float = bounded(1.0, POSITIVE)
    # LiDAR-only tracking (no IMU in the sequence, or use_imu false): a constant-velocity prior on
    # SE(3) between keyframes, white-noise acceleration of these densities (body frame, per axis).
    use_imu: bool = True  # true: the IMU when the sequence has one; false: ignore it (--no-imu)
    # Measured on the real walk (held-out half, 2 Hz): 0.5 m/s^2 doubled the ATE (0.019 -> 0.036 m),
    # 0.5 rad/s^2 lost the track (its prediction gate narrows to 29 deg); 2 rad/s^2 changed nothing.
    motion_sigma_acc_m_s2: float = bounded(1.0, POSITIVE)  # m/s^2/sqrt(s)
    motion_sigma_acc_rad_s2: float = bounded(1.0, POSITIVE)  # rad/s^2/sqrt(s)
    init_sigma_rate_rad_s: float = bounded(1.0, POSITIVE)  # angular-rate prior of the first keyframe (starts at zero)
    # LiDAR-only innovation gates: max(max_innovation_*, this many sigmas of the prior's prediction)
    lidar_only_gate_sigmas: float = bounded(5.0, POSITIVE)
    # LiDAR-only: when registration from the prediction fails its health check, these rotated
    # predictions are tried in turn (yaw about the vertical, then roll and pitch), before the
    # scan counts as rejected.
    rotation_retry_yaw_deg: tuple[float, ...] = (15.0, -15.0, 30.0, -30.0, 45.0, -45.0)
    rotation_retry_tilt_deg: tuple[float, ...] = (15.0, -15.0)
    # ... and one is accepted only with this fraction of the recent scans' fitness
    rotation_retry_fitness_ratio: float = bounded(0.8, FRACTION)

    def ndt_factor_params(self):
        """The NDT factor's :class:`blockloc.tracking.factors.NdtFactorParams` (radians)."""
        import numpy as np

        from blockloc.tracking.factors import NdtFactorParams

        return NdtFactorParams(information_scale=self.ndt_information_scale,
                               degeneracy_ratio=self.degeneracy_eigenvalue_ratio,
                               min_sigma_rot_rad=np.deg2rad(self.ndt_min_sigma_rot_deg),
                               min_sigma_trans_m=self.ndt_min_sigma_trans_m,
                               huber_k=self.huber_k if self.robust_loss == "huber" else 0.0)

    def motion_noise(self):
        """The LiDAR-only constant-velocity prior's :class:`blockloc.tracking.motion.MotionNoise`."""
        from blockloc.tracking.motion import MotionNoise

        return MotionNoise(self.motion_sigma_acc_rad_s2, self.motion_sigma_acc_m_s2)


@dataclass(frozen=True)
class ScanParams:
    """How a sweep is cut down before registration (from the ``lidar`` and ``dataset`` sections).

    Ranges in metres from the lidar; ``voxel_size_m`` 0 keeps every point; ``min_points``: fewer
    points after the cut and the scan is not registered (the motion model carries the pose).
    """

    voxel_size_m: float = 0.5
    max_points: int = 20000
    min_range_m: float = 1.0
    max_range_m: float = 100.0
    deskew: bool = True
    min_points: int = 100


@dataclass(frozen=True)
class FixedParams:
    """Tracker settings no config exposes."""

    relocalize_every: int = 5  # while lost, frames between relocalization attempts
    odometry_sigma_rot_rad: float = math.radians(0.5)
    odometry_sigma_trans_m: float = 0.05
    compute_covariance: bool = True
    # first keyframe priors
    init_sigma_rot_rad: float = math.radians(1.0)
    init_sigma_trans_m: float = 0.1
    init_sigma_vel_m_s: float = 1.0
    recover_sigma_vel_m_s: float = 1.5  # velocity prior after a relocalization (around the last good one)
    init_sigma_acc_bias: float = 0.2
    init_sigma_gyro_bias: float = 0.01


@dataclass(frozen=True)
class TrackerSettings:
    """The three groups an estimator takes, so tests and callers hand over one object."""

    tracking: TrackingParams = field(default_factory=TrackingParams)
    scan: ScanParams = field(default_factory=ScanParams)
    fixed: FixedParams = field(default_factory=FixedParams)

    @classmethod
    def of(cls, **kwargs) -> "TrackerSettings":
        """From flat keyword arguments, each routed to the group that declares it (tests)."""
        groups = {name: {} for name in ("tracking", "scan", "fixed")}
        owners = {f: g for g, c in (("tracking", TrackingParams), ("scan", ScanParams), ("fixed", FixedParams))
                  for f in c.__dataclass_fields__}
        for key, value in kwargs.items():
            if key not in owners:
                raise TypeError(f"no tracker setting named {key!r}")
            groups[owners[key]][key] = value
        return cls(TrackingParams(**groups["tracking"]), ScanParams(**groups["scan"]),
                   FixedParams(**groups["fixed"]))
