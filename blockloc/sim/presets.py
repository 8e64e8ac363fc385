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
scale factor error         0.3 %       per axis, once per unit
axis misalignment          1.5 mrad    per off-diagonal term, once per unit
bias instability           0.002 m/s^2, 8e-5 rad/s (18 deg/h)  Gauss-Markov, tau 120 s
LiDAR-IMU time offset      4 ms        the IMU's stamps lag (not told to the estimator)
lost samples               0.2 %       plus ~0.3 bursts of 3-12 samples a minute
=========================  ==========  =================

Discrete white-noise sigma at rate f is ``density * sqrt(f)``; the bias walk step sigma is
``random_walk / sqrt(f)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from blockloc.errors import SimError


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise and the unit's errors (module docstring: units, provenance).

    Beyond white noise and bias walk, a real unit has per-axis scale-factor errors, axes a little
    off orthogonal and off the body axes, a bias that wanders on minutes (bias instability, a
    first-order Gauss-Markov process), a clock a few ms off the LiDAR's and lost samples. Each
    is switched off by setting it to 0.
    """

    acc_noise_density: float = 0.002
    gyro_noise_density: float = 0.0005
    acc_bias_random_walk: float = 0.0002
    gyro_bias_random_walk: float = 0.00002
    acc_bias_init_sigma: float = 0.02
    gyro_bias_init_sigma: float = 0.002
    scale_factor_sigma: float = 0.003  # per axis, drawn once per unit
    misalignment_sigma_rad: float = 0.0015  # per off-diagonal term, drawn once per unit
    acc_bias_instability: float = 0.002  # m/s^2, Gauss-Markov sigma
    gyro_bias_instability: float = 8e-5  # rad/s, Gauss-Markov sigma
    bias_instability_tau_s: float = 120.0
    time_offset_s: float = 0.004  # IMU stamps lag the true sampling instant (LiDAR clock = truth)
    drop_prob: float = 0.002  # single lost samples; plus rare bursts (drop_burst_per_min)
    drop_burst_per_min: float = 0.3


@dataclass(frozen=True)
class LidarModel:
    """HDL-32E model. ``azimuth_steps`` columns a revolution (2170: the real 0.166 deg at 10 Hz),
    32 beams -30.67..+10.67 deg.

    Errors (each off at 0 / False): per-laser range offset and elevation / azimuth offsets drawn
    once per sensor (the driver computes points from the nominal angles); Gaussian range noise
    with a heavy (Laplace) tail; mixed pixels at depth discontinuities (the footprint straddles
    the edge: the return lies between the two surfaces); random and weak-signal dropouts (dark,
    far, grazing returns are lost); returns from the vehicle itself; intensity from
    reflectance, incidence and range with a per-laser gain and speckle.
    """

    azimuth_steps: int = 2170
    rate_hz: float = 10.0
    max_range_m: float = 100.0
    min_range_m: float = 0.9
    range_noise_m: float = 0.012
    range_tail_prob: float = 0.05
    range_tail_scale_m: float = 0.06
    dropout_prob: float = 0.02
    grazing_dropout_cos: float = 0.08  # returns below this |cos(incidence)| are dropped half the time
    laser_range_offset_m: float = 0.015
    laser_angle_offset_deg: float = 0.08
    mixed_pixel_prob: float = 0.6
    mixed_pixel_gap_m: float = 0.3
    weak_return_dropout: bool = True
    self_hits: bool = True
    laser_gain_sigma: float = 0.45  # log-normal sigma of the per-laser intensity gain
    intensity_speckle: float = 0.3  # log-normal sigma of the per-return intensity
    # Intensity = scale x gain x reflectance-and-incidence power x speckle, falling as
    # (knee / range) ** exponent beyond the knee. Fitted to the real HDL-32E pair's profile by
    # range (bench.realism's range table: the share of returns <= 3 rises from ~12% within 5 m to
    # ~27% at 5-20 m, the median falls from 28 to ~11); the earlier 230 / 12 m / 0.8 read brightest
    # at 10-20 m and gave a third of the real dark share.
    intensity_scale: float = 400.0
    intensity_knee_m: float = 3.0
    intensity_exponent: float = 1.0


@dataclass(frozen=True)
class WorldDetail:
    """What makes the world as rough as a real campus (each off at False / 0).

    volumetric_vegetation: crowns, bushes and hedges are volumes a ray may stop anywhere in,
    pass through (then hitting the trunk or what lies behind) (False: crowns as solid spheres).
    ground_relief: grass layer and micro relief off the roads, kerbs a few cm high.
    facade_detail: windows (glass: lost, or a return from inside), pilasters, floor ledges.
    retroreflectors: rare plates on poles and cars that return at full intensity.
    foliage_change: how far a crown's density may differ between days (0: the same).
    layout: curving footpaths over quads and lots, passages under buildings, an indoor corridor.
    crowds: articulated pedestrians in groups (False: single rigid boxes).
    """

    volumetric_vegetation: bool = True
    ground_relief: bool = True
    facade_detail: bool = True
    retroreflectors: bool = True
    foliage_change: float = 0.5
    layout: bool = True
    crowds: bool = True


@dataclass(frozen=True)
class PlatformModel:
    """The Segway's attitude beyond the terrain (each off at 0 / False).

    balance_pitch: it leans by atan(a / g) to accelerate at a, through an underdamped balance
    loop (natural frequency, damping): overshoot and rocking after each speed change.
    wobble_deg: slow random balancing sway (pitch, half as much roll). vibration_deg /
    vibration_z_m: speed-proportional high-frequency shake at cruise speed.
    """

    balance_pitch: bool = True
    pitch_natural_hz: float = 0.8
    pitch_damping: float = 0.3
    wobble_deg: float = 0.3
    vibration_deg: float = 0.05
    vibration_z_m: float = 0.0015


@dataclass(frozen=True)
class Preset:
    """A world and its sessions.

    size_m: (x, y) extent of the world (centred on the origin), metres.
    road_spacing_m: mean spacing of the road grid lines; the lines are jittered by the seed.
    sessions: session names; mapping drives are named ``map`` or ``map<k>`` (each covers its
    ``map_regions`` share of the road graph), the others are localization drives.
    route_length_m: target driven length per session (routes follow the road graph).
    extrinsic_error_m / _deg: the true LiDAR mounting differs from the nominal one (which the
    written sessions carry) by this much (drawn once per robot, i.e. per seed).
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
    detail: WorldDetail = field(default_factory=WorldDetail)
    platform: PlatformModel = field(default_factory=PlatformModel)
    imu_rate_hz: float = 100.0
    gt_rate_hz: float = 100.0
    slam_error_m: float = 0.03  # std of the smooth offline-SLAM position error (map session)
    slam_error_rad: float = 0.002
    lidar_height_m: float = 1.05  # lidar centre above ground; sets the body origin height
    n_pedestrians: int = 12
    n_vehicles: int = 4
    movable_change: float = 0.25  # fraction of movable objects changed (moved/removed/added)
    extrinsic_error_m: float = 0.01
    extrinsic_error_deg: float = 0.3
    max_building_height_m: float = 18.0
    scene_window_m: float = 0.0  # > 0: ray-cast a window of this half-size around the robot
    map_regions: int = 1  # mapping sessions split the road graph into this many strips
    vegetation: float = 1.0  # share of the trees, shrub clumps and hedges that grow (same places)

    def is_mapping(self, session: str) -> bool:
        """Mapping drives (offline-SLAM poses, the base day of movables, no moving people)."""
        return session == self.sessions[0] or (session.startswith("map") and session[3:].isdigit())


SMALL = Preset(
    name="small",
    size_m=(150.0, 150.0),
    road_spacing_m=(60.0, 50.0),
    terrain_res_m=1.5,
    sessions=("map", "loc"),
    route_length_m=(200.0, 140.0),
    cruise_speed_mps=1.5,
    stop_prob=0.1,
    n_pedestrians=24,
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
    n_pedestrians=200,
    n_vehicles=25,
    max_building_height_m=25.0,
    # lawns with trees rather than woods: with every plant the generator places, 33-37% of the
    # non-ground returns are scattered against the real HDL-32E scans' 19% (issue 15's band 8-30%)
    vegetation=0.35,
)

#: Issue 19's city: 3.2 x 3.2 km of streets, campus-like blocks and parks; five mapping drives
#: (each covering a strip of the city, overlapping its neighbours) sharing one map frame, and a
#: localization drive across all of them. Ray-cast in a moving window, scans streamed.
CITY = Preset(
    name="city",
    size_m=(3200.0, 3200.0),
    road_spacing_m=(130.0, 130.0),
    terrain_res_m=4.0,
    terrain_margin_m=60.0,
    terrain_amplitude_m=4.0,
    n_ramps=14,
    sessions=("map1", "map2", "map3", "map4", "map5", "loc"),
    route_length_m=(8500.0, 8500.0, 8500.0, 8500.0, 8500.0, 6000.0),
    cruise_speed_mps=2.5,
    n_pedestrians=600,
    n_vehicles=120,
    max_building_height_m=40.0,
    scene_window_m=260.0,
    map_regions=5,
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
    lidar=LidarModel(azimuth_steps=360),  # unit tests only: 360 columns keep them fast
    n_pedestrians=6,
    n_vehicles=2,
)

PRESETS = {p.name: p for p in (SMALL, CAMPUS, CITY, TINY)}


def ideal(p: Preset) -> Preset:
    """``p`` with every error source off: exact sensor, smooth solid world, level platform,
    ideal IMU (white noise and bias walk only, as before issue 15), exact extrinsic."""
    lidar = replace(p.lidar, range_tail_prob=0.0, laser_range_offset_m=0.0,
                    laser_angle_offset_deg=0.0, mixed_pixel_prob=0.0, weak_return_dropout=False,
                    self_hits=False, laser_gain_sigma=0.0, intensity_speckle=0.0)
    imu = replace(p.imu, scale_factor_sigma=0.0, misalignment_sigma_rad=0.0,
                  acc_bias_instability=0.0, gyro_bias_instability=0.0, time_offset_s=0.0,
                  drop_prob=0.0, drop_burst_per_min=0.0)
    detail = WorldDetail(volumetric_vegetation=False, ground_relief=False, facade_detail=False,
                         retroreflectors=False, foliage_change=0.0, layout=p.detail.layout,
                         crowds=False)
    platform = PlatformModel(balance_pitch=False, wobble_deg=0.0, vibration_deg=0.0,
                             vibration_z_m=0.0)
    return replace(p, lidar=lidar, imu=imu, detail=detail, platform=platform,
                   extrinsic_error_m=0.0, extrinsic_error_deg=0.0)


def get_preset(name: str, **overrides) -> Preset:
    """The preset called ``name`` (small, campus, city, tiny), with field overrides
    (``azimuth_steps=...`` is applied to the LiDAR model; ``ideal=True`` switches every error
    source off, see ``ideal``)."""
    if name not in PRESETS:
        raise SimError(f"sim preset {name!r}: expected one of {', '.join(PRESETS)}")
    p = PRESETS[name]
    if overrides.pop("ideal", False):
        p = ideal(p)
    az = overrides.pop("azimuth_steps", None)
    if az is not None:
        if int(az) < 8:
            raise SimError(f"azimuth_steps={az}: expected an integer >= 8")
        p = replace(p, lidar=replace(p.lidar, azimuth_steps=int(az)))
    if overrides:
        p = replace(p, **overrides)
    return p
