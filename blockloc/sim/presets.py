"""Simulator presets: world size, road layout, routes, sensor settings.

All lengths in metres, angles in radians unless named ``_deg``, rates in Hz.

IMU noise (MEMS unit of the Microstrain 3DM-GX3-25/45 class; NCLT's ``ms25`` is a 3DM-GX3-45).
Datasheet: accelerometer noise 80 ug/sqrt(Hz) (~0.0008 m/s^2/sqrt(Hz)), gyro noise
0.03 deg/s/sqrt(Hz) (~0.0005 rad/s/sqrt(Hz)), in-run bias stability 0.04 mg / 18 deg/h. On a
moving Segway vibration raises the accelerometer floor, so the simulator uses:

=========================  ==========  =================
acc_noise_density          0.002       m/s^2/sqrt(Hz)
gyro_noise_density         0.0005      rad/s/sqrt(Hz)
acc_bias_random_walk       0.0002      m/s^3/sqrt(Hz)
gyro_bias_random_walk      0.00002     rad/s^2/sqrt(Hz)
initial acc bias sigma     0.02        m/s^2  (per axis, drawn once per session)
initial gyro bias sigma    0.002       rad/s  (per axis, drawn once per session)
=========================  ==========  =================

Discrete white-noise sigma at rate f is ``density * sqrt(f)``; the bias walk step sigma is
``random_walk / sqrt(f)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from blockloc.errors import SimError


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise (see the module docstring for units and provenance)."""

    acc_noise_density: float = 0.002
    gyro_noise_density: float = 0.0005
    acc_bias_random_walk: float = 0.0002
    gyro_bias_random_walk: float = 0.00002
    acc_bias_init_sigma: float = 0.02
    gyro_bias_init_sigma: float = 0.002


@dataclass(frozen=True)
class LidarModel:
    """HDL-32E settings. ``azimuth_steps`` columns a revolution, 32 beams -30.67..+10.67 deg."""

    azimuth_steps: int = 2000
    rate_hz: float = 10.0
    max_range_m: float = 100.0
    min_range_m: float = 0.9
    range_noise_m: float = 0.02
    dropout_prob: float = 0.02
    grazing_dropout_cos: float = 0.08  # returns below this |cos(incidence)| are dropped half the time


@dataclass(frozen=True)
class Preset:
    """A world and its sessions.

    size_m: (x, y) extent of the world (centred on the origin), metres.
    road_spacing_m: mean spacing of the road grid lines; the lines are jittered by the seed.
    sessions: session names; the first is the mapping drive, the others localization drives.
    route_length_m: target driven length per session (routes follow the road graph).
    """

    name: str
    size_m: tuple[float, float]
    road_spacing_m: tuple[float, float]
    road_width_m: float = 7.0
    terrain_res_m: float = 2.0
    terrain_margin_m: float = 60.0
    terrain_amplitude_m: float = 1.2
    n_ramps: int = 3
    sessions: tuple[str, ...] = ("map", "loc")
    route_length_m: tuple[float, ...] = (200.0, 160.0)
    cruise_speed_mps: float = 1.3
    stop_prob: float = 0.15  # chance of a 2-5 s stop on a leg
    turn_in_place_prob: float = 0.5  # at a corner: stop and turn in place, else drive a curve
    lidar: LidarModel = field(default_factory=LidarModel)
    imu: ImuNoise = field(default_factory=ImuNoise)
    imu_rate_hz: float = 100.0
    gt_rate_hz: float = 100.0
    slam_error_m: float = 0.03  # std of the smooth offline-SLAM position error (map session)
    slam_error_rad: float = 0.002
    lidar_height_m: float = 1.05  # lidar centre above ground; sets the body origin height
    n_pedestrians: int = 12
    n_vehicles: int = 4
    movable_change: float = 0.25  # fraction of movable objects changed (moved/removed/added)


SMALL = Preset(
    name="small",
    size_m=(150.0, 150.0),
    road_spacing_m=(60.0, 50.0),
    terrain_res_m=1.5,
    sessions=("map", "loc"),
    route_length_m=(200.0, 140.0),
    cruise_speed_mps=1.5,
    stop_prob=0.1,
    # 32 beams x 200 columns (1.8 deg): ~5k returns a scan, so map + loc fit in < 300 MB.
    lidar=LidarModel(azimuth_steps=200),
    n_pedestrians=10,
    n_vehicles=3,
)

CAMPUS = Preset(
    name="campus",
    size_m=(1000.0, 600.0),
    road_spacing_m=(110.0, 120.0),
    terrain_res_m=3.0,
    terrain_amplitude_m=2.5,
    n_ramps=6,
    sessions=("map", "loc", "loc2"),
    route_length_m=(5200.0, 6300.0, 3200.0),
    cruise_speed_mps=1.3,
    lidar=LidarModel(azimuth_steps=2000),
    n_pedestrians=80,
    n_vehicles=25,
)

#: A tiny world for unit tests: same generator, short routes, few columns.
TINY = Preset(
    name="tiny",
    size_m=(100.0, 100.0),
    road_spacing_m=(50.0, 50.0),
    terrain_res_m=2.0,
    terrain_margin_m=40.0,
    n_ramps=2,
    sessions=("map", "loc"),
    route_length_m=(90.0, 70.0),
    cruise_speed_mps=1.4,
    lidar=LidarModel(azimuth_steps=360),
    n_pedestrians=6,
    n_vehicles=2,
)

PRESETS = {p.name: p for p in (SMALL, CAMPUS, TINY)}


def get_preset(name: str, **overrides) -> Preset:
    """The preset called ``name`` (small, campus, tiny), with field overrides
    (``azimuth_steps=...`` is applied to the LiDAR model)."""
    if name not in PRESETS:
        raise SimError(f"sim preset {name!r}: expected one of {', '.join(PRESETS)}")
    p = PRESETS[name]
    az = overrides.pop("azimuth_steps", None)
    if az is not None:
        if int(az) < 8:
            raise SimError(f"azimuth_steps={az}: expected an integer >= 8")
        p = replace(p, lidar=replace(p.lidar, azimuth_steps=int(az)))
    if overrides:
        p = replace(p, **overrides)
    return p
