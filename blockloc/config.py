"""One typed config tree, a section per stage, loaded from YAML.

Every field has a default (the values of ``configs/default.yaml``); a preset file only names what
differs. Loading checks every key, type and range and names the file, the key and what was
expected: numbers must be finite, and a field declared ``bounded(default, BOUNDS)`` must lie in
its bounds (``POSITIVE`` sizes and rates, ``COUNT`` integers >= 1, ``PROBABILITY`` in (0, 1), ...).
Stages take explicit arguments; ``from_config`` factories at the boundaries read these sections.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from blockloc.errors import ConfigError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


@dataclass(frozen=True)
class Bounds:
    """The range a config value must lie in: ``low`` / ``high`` (None: unbounded), each open
    (excluded) or closed. Tuples are checked value by value."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def contains(self, value: float) -> bool:
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return not (self.high is not None and (value >= self.high if self.high_open else value > self.high))

    def __str__(self) -> str:
        if self.high is None:
            return f"{'>' if self.low_open else '>='} {self.low:g}"
        return (f"in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}"
                f"{')' if self.high_open else ']'}")


POSITIVE = Bounds(0.0, low_open=True)  # sizes, rates, noise densities
NON_NEGATIVE = Bounds(0.0)  # distances where 0 switches a feature off, retries, extra levels
COUNT = Bounds(1.0)  # integer counts of at least one
PROBABILITY = Bounds(0.0, 1.0, low_open=True, high_open=True)
FRACTION = Bounds(0.0, 1.0)
ANGLE_WINDOW = Bounds(0.0, 360.0, low_open=True)  # degrees


def bounded(default: Any, bounds: Bounds):
    """A dataclass field with ``default`` whose loaded values must lie in ``bounds``."""
    return field(default=default, metadata={"bounds": bounds})


@dataclass
class DatasetConfig:
    data_root: str = ""  # empty: $BLOCKLOC_DATA, then ./data
    lidar_topic: str = "/velodyne_points"
    imu_topic: str = "/imu"
    use_hits_times: bool = True  # NCLT: per-point times from velodyne_hits.bin when present
    min_range_m: float = bounded(1.0, NON_NEGATIVE)
    max_range_m: float = bounded(100.0, POSITIVE)


@dataclass
class ImuConfig:
    rate_hz: float = bounded(100.0, POSITIVE)
    # Continuous-time noise densities and bias random walks (Microstrain 3DM-GX3-25 class).
    acc_noise_density: float = bounded(0.004, POSITIVE)  # m/s^2/sqrt(Hz)
    gyro_noise_density: float = bounded(0.0003, POSITIVE)  # rad/s/sqrt(Hz)
    acc_bias_random_walk: float = bounded(0.0002, POSITIVE)  # m/s^3/sqrt(Hz)
    gyro_bias_random_walk: float = bounded(0.00002, POSITIVE)  # rad/s^2/sqrt(Hz)
    integration_sigma: float = bounded(1e-4, POSITIVE)
    # Per-axis densities (x, y, z, imu frame) replacing the scalars above when given: a vibrating
    # platform is noisier along some axes (configs/sim.yaml says what was measured).
    acc_noise_density_axes: tuple[float, ...] = ()  # m/s^2/sqrt(Hz); [] = acc_noise_density on every axis
    gyro_noise_density_axes: tuple[float, ...] = ()  # rad/s/sqrt(Hz); [] = gyro_noise_density on every axis
    gravity_m_s2: float = bounded(9.81, POSITIVE)


@dataclass
class LidarConfig:
    rate_hz: float = bounded(10.0, POSITIVE)
    deskew: bool = True
    voxel_size_m: float = bounded(0.5, NON_NEGATIVE)  # scan downsampling before registration
    max_points: int = bounded(20000, COUNT)


@dataclass
class MapConfig:
    backend: str = "block"  # block | grid | srt | global
    path: str = ""
    voxel_size_m: float = bounded(0.2, NON_NEGATIVE)
    # block maps (Feng et al.)
    block_size_m: float = bounded(100.0, POSITIVE)
    keyframe_distance_m: float = bounded(1.0, NON_NEGATIVE)
    keyframe_angle_deg: float = bounded(15.0, NON_NEGATIVE)
    # Estimate the LiDAR mounting from the mapping drive's scans before building
    # (blockloc.maps.mounting): poses from a dataset's ground truth or a body-frame SLAM carry the
    # robot's mounting error into the map otherwise. Small world, block/NDT, track --init gt
    # (docs/bench/accuracy_seeds.md): seed 2 ATE 0.032 m / 0.55 deg nominal, 0.040 m / 0.10 deg
    # estimated; seed 3 0.056 m / 0.24 deg, 0.039 m / 0.09 deg. Drives whose poses are the LiDAR's
    # own (T_body_lidar = I) and drives the estimate fails on keep their mounting. It reads up to
    # 400 more scans: map build 2.3-2.8x the nominal build's wall time there.
    calibrate_mounting: bool = True
    # Track with the mounting the map's build estimated (the same robot recorded both drives);
    # false: the sequence's own T_body_lidar (a warning when the two differ).
    use_map_mounting: bool = True
    switch_hysteresis_m: float = bounded(5.0, NON_NEGATIVE)
    # Also serve the nearest other block with a keyframe this close (0: one block, as the paper).
    # 15 m: campus, first 1.1 km, ATE 0.063 -> 0.040 m (max 0.55 -> 0.11 m), resident map 59 -> 87 MB.
    block_blend_m: float = bounded(15.0, NON_NEGATIVE)
    # grid puzzle tiles (Byeon et al.)
    tile_size_m: float = bounded(20.0, POSITIVE)
    # n = 2: a (2n+1)s = 100 m window. With n = 1 (60 m) a straight street between long walls left
    # the window without a feature along the street and tracking slid (campus bench, issue 8).
    grid_n: int = bounded(2, NON_NEGATIVE)
    grid_k: int = bounded(1, NON_NEGATIVE)
    # SRT-PM (Kim et al.)
    srt_radius_m: float = bounded(60.0, POSITIVE)
    srt_rebuild_period_s: float = bounded(10.0, POSITIVE)
    # provider
    cache_mb: float = bounded(1024.0, POSITIVE)
    prefetch: bool = True
    prefetch_lookahead_s: float = bounded(5.0, NON_NEGATIVE)  # prefetch the region needed after this much motion
    retry_missing_s: float = bounded(5.0, NON_NEGATIVE)  # rebuild a region whose entries failed to load this often
    # maps read from http(s):// or s3:// (blockloc.maps.remote)
    remote_cache_dir: str = ""  # empty: $BLOCKLOC_MAP_CACHE or ~/.cache/blockloc/remote-maps
    remote_cache_mb: float = bounded(2048.0, POSITIVE)
    remote_timeout_s: float = bounded(10.0, POSITIVE)
    remote_retries: int = bounded(3, NON_NEGATIVE)
    remote_backoff_s: float = bounded(0.25, NON_NEGATIVE)


@dataclass
class RegistrationConfig:
    method: str = "ndt"
    resolution_m: float = bounded(1.0, POSITIVE)
    neighbors: str = "DIRECT7"  # DIRECT1 | DIRECT7 | DIRECT27
    outlier_ratio: float = bounded(0.55, PROBABILITY)
    min_points_per_voxel: int = bounded(6, COUNT)
    max_iterations: int = bounded(30, COUNT)
    step_epsilon: float = bounded(1e-3, POSITIVE)
    num_threads: int = bounded(2, COUNT)
    # NDT target grids at 2x, 4x ... resolution (from the fine voxel sums)
    coarse_levels: int = bounded(1, NON_NEGATIVE)
    coarse_to_fine: bool = True  # align on the coarse levels first (wider basin of convergence)
    # vgicp only: neighbours of the scan's per-point covariances, and of the map's (0: the scan's);
    # configs/sim.yaml says why it sets 20 and 80. On the real HDL-32E pair as tracking sees it (map
    # at 0.2 m voxels, scan at 0.5 m), 30 starts within 0.2 m / 1 deg: 10/10 aligns 30 within
    # 5 cm / 0.5 deg, 20/20 30, 20/80 (sim.yaml's) 17; against the raw 69k-point target 20/20
    # aligns none (1.0 deg off, all "converged"), 10/10 all 30 (issue 41; tests/registration/
    # test_engines.py holds every preset's defaults to 30/30).
    num_neighbors: int = bounded(10, COUNT)
    target_num_neighbors: int = bounded(0, NON_NEGATIVE)
    # vgicp only: voxel grids offset by resolution / grids along each axis, aligned in turn and
    # their results fused (1: small_gicp's single grid; see blockloc/registration/vgicp.py)
    voxel_grids: int = bounded(2, COUNT)


@dataclass
class GlobalInitConfig:
    window_m: float = bounded(40.0, POSITIVE)
    yaw_window_deg: float = bounded(360.0, ANGLE_WINDOW)
    resolution_m: float = bounded(0.5, POSITIVE)  # 2D cell of the branch and bound (NDT refines afterwards)
    pyramid_levels: int = bounded(6, COUNT)  # top level: a sliding max over 2^5 cells = 16 m
    height_band_m: tuple[float, float] = (0.3, 3.0)  # projected points: height above local ground
    projection: str = "band"  # band (height band above local ground) | all (plain occupancy)
    max_range_m: float = bounded(60.0, POSITIVE)  # scan cells used by the 2D search (sets the angular step)
    top_k: int = bounded(5, COUNT)
    use_s0: bool = True  # greedy initial score S0 (block-map paper); False: plain BBS
    s0_ratio: float = bounded(0.9, FRACTION)  # prune below this fraction of S0
    # NDT inlier ratio for a verified match (sim: true 0.8-0.97, false <= 0.61)
    min_fitness: float = bounded(0.75, PROBABILITY)
    # same for the above-ground points alone (true >= 0.9, false <= 0.37)
    min_structure_fitness: float = bounded(0.6, PROBABILITY)
    ambiguity_distance_m: float = bounded(0.5, NON_NEGATIVE)  # rivals farther than this (NDT merges closer ones)
    ndt_resolution_m: float = bounded(1.0, POSITIVE)
    reloc_window_m: float = bounded(100.0, POSITIVE)  # regions of the no-hint relocalization (the place index's fallback)
    # No-hint relocalization through the map's place index (blockloc/global_init/place_index.py).
    use_place_index: bool = True
    place_candidates: tuple[int, ...] = (8, 64, 256)  # places whose windows are searched, stage by stage
    place_window_m: float = bounded(12.0, POSITIVE)  # window around each place (x, y), metres
    place_yaw_window_deg: float = bounded(16.0, ANGLE_WINDOW)  # around each place's yaw guess
    place_band_m: tuple[float, float] = (2.0, 4.0)  # static band: above people, cars and fences
    place_max_range_m: float = bounded(63.0, POSITIVE)
    place_spacing_m: float = bounded(3.0, POSITIVE)  # grid of places over the drivable area
    place_tolerance_m: float = bounded(1.5, POSITIVE)  # a scan this far from a place still matches it
    place_max_offset_m: float = bounded(20.0, POSITIVE)  # grid places within this of a mapping keyframe
    whole_map_fallback: bool = True  # then the regions of reloc_window_m, as without an index
    # no-hint search budget, seconds (0: none); then "not found" (verified false) rather than minutes
    max_search_s: float = bounded(10.0, NON_NEGATIVE)
    # Verification at the refined pose, in the static band (both the hinted and the no-hint path).
    min_coverage: float = bounded(0.9, FRACTION)  # scan structure the map covers (true poses: >= 0.91 on campus)
    max_see_through: float = bounded(0.35, FRACTION)  # share of the map's visible structure the scan saw through (true: <= 0.25)
    ambiguity_z: float = bounded(2.5, NON_NEGATIVE)  # a rival is no ambiguity when the best fits this significantly better
    # The structure test on the static band (>= place_band_m[0] above ground: above people and cars)
    # when the scan has enough of it; false: on the projection band (height_band_m) always (indoors,
    # configs/handheld.yaml says why).
    structure_from_static: bool = True


@dataclass
class TrackingConfig:
    window_size: int = bounded(20, COUNT)  # N_a: keyframes inside a block
    window_size_on_switch: int = bounded(5, COUNT)  # N_r: keyframes kept when the map switches
    keyframe_distance_m: float = bounded(0.0, NON_NEGATIVE)  # 0: every scan is a keyframe
    ndt_information_scale: float = bounded(1.0, POSITIVE)
    degeneracy_eigenvalue_ratio: float = bounded(0.01, FRACTION)
    robust_loss: str = "huber"
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


@dataclass
class EvaluationConfig:
    align: bool = False
    rpe_deltas_m: tuple[float, ...] = bounded((1.0, 10.0, 100.0), POSITIVE)
    max_time_diff_s: float = bounded(0.02, POSITIVE)
    plots: bool = True


@dataclass
class Config:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    map: MapConfig = field(default_factory=MapConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    global_init: GlobalInitConfig = field(default_factory=GlobalInitConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)

    def to_dict(self) -> dict[str, Any]:
        return _to_plain(self)


def _to_plain(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        return {f.name: _to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple):
        return [_to_plain(v) for v in obj]
    return obj


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Check ``value`` against annotation ``tp``; int is accepted where float is expected."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping (section), got {type(value).__name__}")
        return _build(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        errors = []
        for arg in typing.get_args(tp):
            try:
                return _coerce(value, arg, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected a list of {len(args)} values, got {value!r}")
        return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if tp is type(None):
        if value is None:
            return None
        raise ConfigError(f"{where}: expected null, got {value!r}")
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):
                raise ConfigError(f"{where}: expected a finite number, got {value!r}")
            return float(value)
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{where}: expected a string, got {value!r}")
    raise ConfigError(f"{where}: unsupported type {_type_name(tp)}")


def _build(cls: type, data: dict[str, Any], where: str, base: Any = None) -> Any:
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for key in data:
        if key not in names:
            raise ConfigError(f"{where}: unknown key '{key}' (expected one of: {', '.join(sorted(names))})")
    kwargs = {}
    for f in dataclasses.fields(cls):
        sub_where = f"{where}.{f.name}" if where else f.name
        current = getattr(base, f.name) if base is not None else None
        if f.name in data:
            if dataclasses.is_dataclass(hints[f.name]) and current is not None:
                if not isinstance(data[f.name], dict):
                    raise ConfigError(f"{sub_where}: expected a mapping (section), got {data[f.name]!r}")
                kwargs[f.name] = _build(hints[f.name], data[f.name], sub_where, current)
            else:
                kwargs[f.name] = _coerce(data[f.name], hints[f.name], sub_where)
                _check_bounds(kwargs[f.name], f.metadata.get("bounds"), sub_where)
        elif current is not None:
            kwargs[f.name] = current
    return cls(**kwargs)


def _check_bounds(value: Any, bounds: Bounds | None, where: str) -> None:
    if bounds is None:
        return
    for v in (value if isinstance(value, tuple) else (value,)):
        if not bounds.contains(v):
            raise ConfigError(f"{where}: expected a value {bounds}, got {v!r}")


def merge(base: Config, data: dict[str, Any], source: str = "<dict>") -> Config:
    """A new Config: ``base`` overridden by the nested mapping ``data``."""
    try:
        return _build(Config, data or {}, "", base)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None,
                overrides_source: str = "overrides") -> Config:
    """Defaults, then the YAML file ``path`` (a path or a preset name such as 'nclt'), then overrides."""
    import yaml

    cfg = Config()
    if path:
        file = Path(path)
        if not file.exists() and (CONFIG_DIR / f"{path}.yaml").exists():
            file = CONFIG_DIR / f"{path}.yaml"
        if not file.exists():
            presets = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
            raise ConfigError(f"{path}: no such config file or preset (presets: {', '.join(presets)})")
        try:
            data = yaml.safe_load(file.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{file}: not valid YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{file}: expected a mapping of sections at the top level")
        cfg = merge(cfg, data, str(file))
    if overrides:
        cfg = merge(cfg, overrides, overrides_source)
    return cfg


def preset_for_sequence(seq: str) -> str | None:
    """The preset that fits a ``--seq`` value (``blockloc.datasets.refs.SequenceRef.preset``):
    'sim' for simulated sessions, 'nclt' for NCLT, 'm2dgr' for M2DGR, None otherwise (also for
    a value that names nothing: opening it will say why)."""
    from blockloc.datasets.refs import SequenceRef
    from blockloc.errors import DatasetError

    try:
        return SequenceRef.parse(seq).preset
    except DatasetError:
        return None


def load_config_for_sequence(seq: str, config: str | Path | None = None) -> Config:
    """``config`` (a file or preset name) when given, else the preset that fits ``seq``."""
    return load_config(config or preset_for_sequence(seq))


def save_config(cfg: Config, path: str | Path) -> None:
    """Write ``cfg`` as YAML, atomically."""
    import yaml

    from blockloc.fileio import atomic_write_text

    atomic_write_text(path, yaml.safe_dump(cfg.to_dict(), sort_keys=False))
