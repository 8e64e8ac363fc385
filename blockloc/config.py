"""One typed config tree, a section per stage, loaded from YAML.

Every field has a default (the values of ``blockloc/presets/default.yaml``); a preset file only names what
differs. Loading checks every key, type and range and names the file, the key and what was
expected: numbers must be finite, and a field declared ``bounded(default, BOUNDS)`` must lie in
its bounds (``POSITIVE`` sizes and rates, ``COUNT`` integers >= 1, ``PROBABILITY`` in (0, 1), ...).
Stages take explicit arguments; ``from_config`` factories at the boundaries read these sections.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
import types
import typing
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path
from typing import Any

from blockloc.bounds import (  # noqa: F401  (re-exported: presets and tests name them from here)
    ANGLE_WINDOW,
    COUNT,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    PROBABILITY,
    Bounds,
    bounded,
)
from blockloc.errors import ConfigError
from blockloc.global_init.params import GlobalInitParams
from blockloc.tracking.params import TrackingParams

log = logging.getLogger(__name__)

#: The presets shipped inside the package (``--config NAME``): ``blockloc/presets/<NAME>.yaml``.
PRESET_DIR = Path(__file__).resolve().parent / "presets"


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
    # platform is noisier along some axes (blockloc/presets/sim.yaml says what was measured).
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
    # (docs/bench/accuracy_seeds.md, 2026-12-05): seed 2 ATE 0.032 m / 0.55 deg nominal, 0.040 m / 0.10 deg
    # estimated (translation too); seed 3 0.056 m / 0.24 deg, 0.039 m / 0.09 deg. Drives whose poses are the LiDAR's
    # own (T_body_lidar = I) and drives the estimate fails on keep their mounting. It reads up to
    # 400 more scans: map build 2.3-2.8x the nominal build's wall time there.
    calibrate_mounting: bool = True
    # The estimate's translation replaces the nominal one only on the body axes the drive
    # determines to this (metres; a block jackknife along the drive, blockloc.maps.mounting); its
    # rotation always does. 0: the estimated translation on every observed axis (before issue 41).
    # Small world seeds 2 and 3: the translation was 11-22 mm off (jackknife 8-18 mm), and kept
    # nominal ATE is 0.030 / 0.027 m against 0.040 / 0.039 m (docs/bench/accuracy_seeds.md).
    mounting_translation_tolerance_m: float = bounded(0.005, NON_NEGATIVE)
    # Track with the mounting the map's build estimated (the same robot recorded both drives);
    # false: the sequence's own T_body_lidar (a warning when the two differ).
    use_map_mounting: bool = True
    # Refine each mapping drive's keyframe poses against its own scans before the blocks are
    # written (blockloc.maps.pose_refine: NDT scan to scan, then against local maps of neighbouring
    # keyframes and of the other pass at revisits, a pose graph with the given poses as priors; the
    # mounting's rotation and forward translation estimated with them). Small world seeds 1-5
    # (docs/bench/accuracy_seeds.md): the body poses' error vs the truth 5.2-6.2 -> 2.4-2.8 cm RMSE;
    # tracked ATE 0.037/0.030/0.027/0.028/0.035 -> 0.020/0.028/0.028/0.023/0.028 m (seed 3 1 mm
    # worse); the real walk 0.0153 -> 0.0167 m; the build 1.6-2.0x the CPU. On (true) it refines the
    # drives whose mounting the build estimated (poses of the body: the simulator, NCLT's ground
    # truth), where it buys the mounting's forward translation; drives with LiDAR poses (most SLAM
    # outputs, the real walk) are left as they came. --refine-poses: every drive.
    refine_poses: bool = True
    # Leave moving objects out of the map built from a drive (blockloc.maps.dynamic_removal: voxels
    # the drive's own scans see through around each keyframe). Off: a drive without pedestrians or
    # traffic loses a few percent of its static points to it (SA 96.7-97.6% on the DynamicMap
    # stretches of docs/bench/dynamic.md) for nothing.
    remove_dynamic: bool = False
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
    # blockloc/presets/sim.yaml says why it sets 20 and 80. On the real HDL-32E pair as tracking
    # sees it (map at 0.2 m voxels, scan at 0.5 m), 30 starts within 0.2 m / 1 deg: 10/10 aligns
    # 30 within 5 cm / 0.5 deg, 20/20 30, 20/80 (sim.yaml's) 17; against the raw 69k-point target 20/20
    # aligns none (1.0 deg off, all "converged"), 10/10 all 30 (issue 41; tests/registration/
    # test_engines.py holds every preset's defaults to 30/30).
    num_neighbors: int = bounded(10, COUNT)
    target_num_neighbors: int = bounded(0, NON_NEGATIVE)
    # vgicp only: voxel grids offset by resolution / grids along each axis, aligned in turn and
    # their results fused (1: small_gicp's single grid; see blockloc/registration/vgicp.py)
    voxel_grids: int = bounded(2, COUNT)


# The global_init section is global initialization's own parameter dataclass.
GlobalInitConfig = GlobalInitParams

# The tracking section is the tracker's own parameter dataclass: each knob declared once.
TrackingConfig = TrackingParams


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


#: A number written in decimal, with or without an exponent: ``5e-1``, ``1E-6``, ``1e3``, ``-.5``.
#: YAML 1.1 (PyYAML) reads a float only with a dot and a signed exponent, so these reach a field as
#: strings (``--set tracking.min_fitness=5e-1``, ``voxel_size_m: 1e-6``).
_DECIMAL = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?")


def _number(value: Any) -> int | float | None:
    """``value`` as the number it is or spells (a string in :data:`_DECIMAL`'s forms, or one of
    float()'s names of nan and infinity); None for anything else (bools included)."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        return value
    if isinstance(value, str) and _DECIMAL.fullmatch(value):
        return float(value)  # '1e999' is inf: refused as not finite
    if isinstance(value, str) and value.strip().lower().lstrip("+-") in ("nan", "inf", "infinity"):
        return float(value)
    return None


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Check ``value`` against annotation ``tp``. A float field takes an int or a number written as
    text (``5e-1``: see :func:`_number`), finite; an int field takes an integer in any notation
    (``20000``, ``2e4``, ``2.0e+4``) and refuses a fraction (``2.5``, ``1e-3``)."""
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
        number = _number(value)
        if number is None:
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(number):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return float(number)
    if tp is int:
        number = _number(value)
        if isinstance(number, int):
            return number
        if number is not None and math.isfinite(number):
            exact = Decimal(value) if isinstance(value, str) else Decimal(number)  # '1e3', or the float read
            if exact == exact.to_integral_value() and abs(exact) < 2**63:
                return int(exact)
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
            if not where:  # the top level: its keys are the config's sections
                raise ConfigError(f"unknown section '{key}' (expected one of: {', '.join(sorted(names))})")
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


def preset_names() -> list[str]:
    """The names of the shipped presets (``default``, ``sim``, ``nclt``, ...), sorted."""
    return sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))


def preset_path(name: str) -> Path:
    """The file of the preset ``name``; ConfigError listing the presets when there is none."""
    file = PRESET_DIR / f"{name}.yaml"
    if not file.is_file():
        raise ConfigError(f"{name}: no such preset (presets: {', '.join(preset_names())})")
    return file


def looks_like_path(text: str) -> bool:
    """A config given as a path has a slash or an extension (``./mine``, ``my.yaml``); a bare
    word names a preset. No guessing from what the current directory holds."""
    return "/" in text or os.sep in text or bool(os.altsep and os.altsep in text) or Path(text).suffix != ""


def config_file(source: str | Path) -> Path:
    """The YAML file ``--config`` names: a path (see :func:`looks_like_path`; a ``Path`` object is
    always one) must be a file; a bare word is a preset, and wins over a file or directory of the
    same name in the current directory (one warning line says so)."""
    text = str(source)
    if isinstance(source, Path) or looks_like_path(text):
        file = Path(text).expanduser()
        if file.is_dir():
            raise ConfigError(f"{text}: a directory, expected a YAML config file")
        if not file.is_file():
            raise ConfigError(f"{text}: no such config file (presets: {', '.join(preset_names())}, given by name)")
        return file
    file = PRESET_DIR / f"{text}.yaml"
    if not file.is_file():
        hint = f"; to read the file ./{text}, give it as ./{text}" if Path(text).exists() else ""
        raise ConfigError(f"{text}: no such preset (presets: {', '.join(preset_names())}; a config file is "
                          f"given as a path, with a slash or an extension){hint}")
    if Path(text).exists():
        log.warning("config %r: the preset %s is used, not ./%s of the current directory (give ./%s to read that)",
                    text, file.name, text, text)
    return file


def _read_config_file(file: Path) -> dict[str, Any]:
    """The top-level mapping of the YAML config ``file``; ConfigError naming the file and saying a
    YAML config was expected when it cannot be read, is binary (a PCD, a bag), is empty, is not
    YAML or holds something else than a mapping of sections (a list, a bare word). A file of
    comments only is the defaults."""
    import yaml

    expected = "expected a YAML config file (a mapping of sections such as 'map:')"
    try:
        raw = file.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{file}: cannot be read ({exc.strerror or exc}), {expected}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{file}: binary bytes (not UTF-8 text at byte {exc.start}), {expected}") from None
    if not text.strip():
        raise ConfigError(f"{file}: empty, {expected}; '{{}}' for the defaults")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{file}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if data is None:  # comments only: nothing differs from the defaults
        return {}
    if not isinstance(data, dict):
        kind = "a list" if isinstance(data, list) else f"a single value ({str(data)[:40]!r})"
        raise ConfigError(f"{file}: {kind} at the top level, expected a mapping of sections (a YAML config "
                          "file, sections such as 'map:')")
    return data


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None,
                overrides_source: str = "overrides", *, preset: str | None = None) -> Config:
    """Defaults, then the YAML file ``path`` (a path, or a preset name such as 'nclt': see
    :func:`config_file`) or else the preset named ``preset`` (never a file), then overrides."""
    cfg = Config()
    file = config_file(path) if path else (preset_path(preset) if preset else None)
    if file is not None:
        cfg = merge(cfg, _read_config_file(file), str(file))
    if overrides:
        cfg = merge(cfg, overrides, overrides_source)
    return cfg


def save_config(cfg: Config, path: str | Path) -> None:
    """Write ``cfg`` as YAML, atomically."""
    import yaml

    from blockloc.fileio import atomic_write_text

    atomic_write_text(path, yaml.safe_dump(cfg.to_dict(), sort_keys=False))
