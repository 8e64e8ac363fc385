"""One typed config tree, a section per stage, loaded from YAML.

Every field has a default (the values of ``configs/default.yaml``); a preset file only names what
differs. Loading checks every key and type and names the file, the key and what was expected.
Stages take explicit arguments; ``from_config`` factories at the boundaries read these sections.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from blockloc.errors import ConfigError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


@dataclass
class DatasetConfig:
    data_root: str = ""  # empty: $BLOCKLOC_DATA, then ./data
    lidar_topic: str = "/velodyne_points"
    imu_topic: str = "/imu"
    use_hits_times: bool = True  # NCLT: per-point times from velodyne_hits.bin when present
    min_range_m: float = 1.0
    max_range_m: float = 100.0


@dataclass
class ImuConfig:
    rate_hz: float = 100.0
    # Continuous-time noise densities and bias random walks (Microstrain 3DM-GX3-25 class).
    acc_noise_density: float = 0.004  # m/s^2/sqrt(Hz)
    gyro_noise_density: float = 0.0003  # rad/s/sqrt(Hz)
    acc_bias_random_walk: float = 0.0002  # m/s^3/sqrt(Hz)
    gyro_bias_random_walk: float = 0.00002  # rad/s^2/sqrt(Hz)
    integration_sigma: float = 1e-4
    gravity_m_s2: float = 9.81


@dataclass
class LidarConfig:
    rate_hz: float = 10.0
    deskew: bool = True
    voxel_size_m: float = 0.5  # scan downsampling before registration
    max_points: int = 20000


@dataclass
class MapConfig:
    backend: str = "block"  # block | grid | srt | global
    path: str = ""
    voxel_size_m: float = 0.2
    # block maps (Feng et al.)
    block_size_m: float = 100.0
    keyframe_distance_m: float = 1.0
    keyframe_angle_deg: float = 15.0
    switch_hysteresis_m: float = 5.0
    # Also serve the nearest other block with a keyframe this close (0: one block, as the paper).
    # 15 m: campus, first 1.1 km, ATE 0.063 -> 0.040 m (max 0.55 -> 0.11 m), resident map 59 -> 87 MB.
    block_blend_m: float = 15.0
    # grid puzzle tiles (Byeon et al.)
    tile_size_m: float = 20.0
    # n = 2: a (2n+1)s = 100 m window. With n = 1 (60 m) a straight street between long walls left
    # the window without a feature along the street and tracking slid (campus bench, issue 8).
    grid_n: int = 2
    grid_k: int = 1
    # SRT-PM (Kim et al.)
    srt_radius_m: float = 60.0
    srt_rebuild_period_s: float = 10.0
    # provider
    cache_mb: float = 1024.0
    prefetch: bool = True
    prefetch_lookahead_s: float = 5.0  # prefetch the region needed after this much motion
    retry_missing_s: float = 5.0  # rebuild a region whose entries failed to load this often
    # maps read from http(s):// or s3:// (blockloc.maps.remote)
    remote_cache_dir: str = ""  # empty: $BLOCKLOC_MAP_CACHE or ~/.cache/blockloc/remote-maps
    remote_cache_mb: float = 2048.0
    remote_timeout_s: float = 10.0
    remote_retries: int = 3
    remote_backoff_s: float = 0.25


@dataclass
class RegistrationConfig:
    method: str = "ndt"
    resolution_m: float = 1.0
    neighbors: str = "DIRECT7"  # DIRECT1 | DIRECT7 | DIRECT27
    outlier_ratio: float = 0.55
    min_points_per_voxel: int = 6
    max_iterations: int = 30
    step_epsilon: float = 1e-3
    num_threads: int = 2
    coarse_levels: int = 1  # NDT target grids at 2x, 4x ... resolution (from the fine voxel sums)
    coarse_to_fine: bool = True  # align on the coarse levels first (wider basin of convergence)


@dataclass
class GlobalInitConfig:
    window_m: float = 40.0
    yaw_window_deg: float = 360.0
    resolution_m: float = 0.5  # 2D cell of the branch and bound (NDT refines afterwards)
    pyramid_levels: int = 6  # top level: a sliding max over 2^5 cells = 16 m
    height_band_m: tuple[float, float] = (0.3, 3.0)  # projected points: height above local ground
    projection: str = "band"  # band (height band above local ground) | all (plain occupancy)
    max_range_m: float = 60.0  # scan cells used by the 2D search (sets the angular step)
    top_k: int = 5
    use_s0: bool = True  # greedy initial score S0 (block-map paper); False: plain BBS
    s0_ratio: float = 0.9  # prune below this fraction of S0
    min_fitness: float = 0.75  # NDT inlier ratio for a verified match (sim: true 0.8-0.97, false <= 0.61)
    min_structure_fitness: float = 0.6  # same for the above-ground points alone (true >= 0.9, false <= 0.37)
    ambiguity_distance_m: float = 0.5  # a rival NDT optimum this far away that fits as well: ambiguous
    ndt_resolution_m: float = 1.0
    reloc_window_m: float = 100.0  # regions of the no-hint relocalization (the place index's fallback)
    # No-hint relocalization through the map's place index (blockloc/global_init/place_index.py).
    use_place_index: bool = True
    place_candidates: tuple[int, ...] = (32, 256)  # places whose windows are searched, stage by stage
    place_window_m: float = 12.0  # window around each place (x, y), metres
    place_yaw_window_deg: float = 16.0  # around each place's yaw guess
    place_band_m: tuple[float, float] = (2.0, 4.0)  # static band: above people, cars and fences
    place_max_range_m: float = 63.0
    place_spacing_m: float = 3.0  # grid of places over the drivable area
    place_tolerance_m: float = 1.5  # a scan this far from a place still matches it
    place_max_offset_m: float = 20.0  # grid places within this of a mapping keyframe
    whole_map_fallback: bool = True  # then the regions of reloc_window_m, as without an index
    # Verification at the refined pose, in the static band (both the hinted and the no-hint path).
    min_coverage: float = 0.9  # scan structure the map covers (true poses: >= 0.91 on campus)
    max_see_through: float = 0.35  # share of the map's visible structure the scan saw through (true: <= 0.25)
    ambiguity_z: float = 2.5  # a rival is no ambiguity when the best fits this significantly better


@dataclass
class TrackingConfig:
    window_size: int = 20  # N_a: keyframes inside a block
    window_size_on_switch: int = 5  # N_r: keyframes kept when the map switches
    keyframe_distance_m: float = 0.0  # 0: every scan is a keyframe
    ndt_information_scale: float = 1.0
    degeneracy_eigenvalue_ratio: float = 0.01
    robust_loss: str = "huber"
    min_fitness: float = 0.4
    max_innovation_m: float = 1.0
    use_odometry_factor: bool = False
    max_innovation_deg: float = 10.0
    max_bad_frames: int = 3  # rejected scans in a row before relocalizing around the last good pose
    ndt_min_sigma_trans_m: float = 0.02  # floor of the NDT factor's standard deviations
    ndt_min_sigma_rot_deg: float = 0.1
    huber_k: float = 1.345
    lm_iterations: int = 6
    imu_noise_inflation: float = 1.0


@dataclass
class EvaluationConfig:
    align: bool = False
    rpe_deltas_m: tuple[float, ...] = (1.0, 10.0, 100.0)
    max_time_diff_s: float = 0.02
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
        elif current is not None:
            kwargs[f.name] = current
    return cls(**kwargs)


def merge(base: Config, data: dict[str, Any], source: str = "<dict>") -> Config:
    """A new Config: ``base`` overridden by the nested mapping ``data``."""
    try:
        return _build(Config, data or {}, "", base)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> Config:
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
        cfg = merge(cfg, overrides, "overrides")
    return cfg


def preset_for_sequence(seq: str) -> str | None:
    """The preset that fits a ``--seq`` value: 'sim' for simulated sessions (``sim:...`` or a
    path written by ``blockloc sim``, which leaves ``sim.json`` beside its sessions), 'nclt' for
    ``nclt_N`` and NCLT-layout directories, 'm2dgr' for ``m2dgr_N``; None otherwise."""
    if seq.startswith("sim:"):
        return "sim"
    if seq.startswith("nclt_"):
        return "nclt"
    if seq.startswith("m2dgr_"):
        return "m2dgr"
    path = Path(seq)
    if (path.parent / "sim.json").is_file():
        return "sim"
    if (path / "velodyne_sync").is_dir():
        return "nclt"
    return None


def load_config_for_sequence(seq: str, config: str | Path | None = None) -> Config:
    """``config`` (a file or preset name) when given, else the preset that fits ``seq``."""
    return load_config(config or preset_for_sequence(seq))


def save_config(cfg: Config, path: str | Path) -> None:
    """Write ``cfg`` as YAML, atomically."""
    import yaml

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    tmp.replace(path)
