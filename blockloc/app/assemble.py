"""Config -> objects: every factory that reads a config section lives here.

The core classes take explicit parameters (arrays, numbers, small parameter dataclasses); this
module is the one place that turns sections of a :class:`blockloc.config.Config` into them:

    engine = build_engine(cfg.registration)                   # NDT or VGICP
    store = open_store(path, cfg.map)                         # local or remote map store
    provider = make_provider(store, "block", cfg.map, engine) # policy + provider
    localizer = make_localizer(store, gravity_map, cfg)       # global init
    session = build_session(cfg, seq, store)                  # all of it, ready to run

Heavy libraries (numba kernels, gtsam, small_gicp) load when an engine, a tracker or a localizer
is built (the core modules import them inside the functions that need them), not when this
module is imported.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any, Sequence


from blockloc.app.session import GlobalInitSettings, Session
from blockloc.config import Config, GlobalInitConfig, MapConfig, RegistrationConfig
from blockloc.global_init.relocalize import GlobalLocalizer, InitParams
from blockloc.maps.mounting import with_map_mounting
from blockloc.maps.policies import make_policy
from blockloc.maps.provider import MapProvider
from blockloc.maps.remote import DEFAULT_CACHE_BYTES, RetryPolicy
from blockloc.maps.store import MapStore, open_map
from blockloc.registration.engines import engine_from_settings
from blockloc.registration.ndt import NdtRegistration
from blockloc.tracking.imu import ImuNoise
from blockloc.tracking.params import ScanParams, TrackerSettings
from blockloc.tracking.tracker import Estimator, make_tracker as make_estimator

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- registration
#: The ``registration`` fields each engine takes (``method`` names the engine).
ENGINE_FIELDS = {
    "ndt": ("resolution_m", "min_points_per_voxel", "coarse_levels", "neighbors", "outlier_ratio",
            "max_iterations", "step_epsilon", "coarse_to_fine", "num_threads"),
    "vgicp": ("resolution_m", "num_neighbors", "target_num_neighbors", "voxel_grids", "max_iterations",
              "num_threads", "outlier_ratio", "min_points_per_voxel"),
}


def engine_settings(rc: RegistrationConfig) -> dict[str, Any]:
    """The ``registration`` section as the keywords of the engine ``rc.method`` (and ``method``);
    an engine without an entry in :data:`ENGINE_FIELDS` gets every field."""
    names = ENGINE_FIELDS.get(rc.method) or tuple(f.name for f in dataclasses.fields(rc) if f.name != "method")
    return {"method": rc.method, **{name: getattr(rc, name) for name in names}}


def build_engine(rc: RegistrationConfig, resolution_m: float | None = None):
    """The registration engine ``rc.method`` with the section's settings; ``resolution_m``
    replaces ``rc.resolution_m`` (global init refines at ``global_init.ndt_resolution_m``)."""
    overrides = {} if resolution_m is None else {"resolution_m": resolution_m}
    return engine_from_settings(engine_settings(rc), **overrides)


def ndt_registration(rc: RegistrationConfig):
    """A bare :class:`~blockloc.registration.ndt.NdtRegistration` with the section's settings."""
    return NdtRegistration(neighbors=rc.neighbors, outlier_ratio=rc.outlier_ratio,
                           max_iterations=rc.max_iterations, step_epsilon=rc.step_epsilon,
                           coarse_to_fine=rc.coarse_to_fine, num_threads=rc.num_threads)


def ndt_target_options(rc: RegistrationConfig) -> dict[str, Any]:
    """Keywords of ``NdtTarget.build`` / ``from_tiles``: ``NdtTarget.build(points, **ndt_target_options(rc))``."""
    return {"resolution": rc.resolution_m, "min_points_per_voxel": rc.min_points_per_voxel,
            "coarse_levels": rc.coarse_levels}


# ----------------------------------------------------------------------------- maps
def remote_options(mc: Any) -> dict[str, Any]:
    """``RemoteMapFiles`` options from a ``MapConfig`` (fields read when present, else defaults):
    ``remote_cache_dir`` (str, "" = default), ``remote_cache_mb``, ``remote_timeout_s``,
    ``remote_retries``, ``remote_backoff_s``."""
    d = RetryPolicy()
    cache_dir = getattr(mc, "remote_cache_dir", "") or None
    cache_mb = float(getattr(mc, "remote_cache_mb", DEFAULT_CACHE_BYTES / 2**20))
    retry = RetryPolicy(timeout_s=float(getattr(mc, "remote_timeout_s", d.timeout_s)),
                        retries=int(getattr(mc, "remote_retries", d.retries)),
                        backoff_s=float(getattr(mc, "remote_backoff_s", d.backoff_s)))
    return {"cache_dir": cache_dir, "cache_bytes": int(cache_mb * 2**20), "retry": retry}


def open_store(path, mc: MapConfig) -> MapStore:
    """:func:`blockloc.maps.store.open_map` with the remote-store options of ``mc``."""
    return open_map(path, **remote_options(mc))


def policy_settings(mc: MapConfig) -> dict[str, Any]:
    """The keywords of the map policies (each policy takes the ones it knows)."""
    return {"switch_hysteresis_m": mc.switch_hysteresis_m, "block_blend_m": mc.block_blend_m,
            "grid_n": mc.grid_n, "grid_k": mc.grid_k, "srt_radius_m": mc.srt_radius_m,
            "srt_rebuild_period_s": mc.srt_rebuild_period_s}


def make_provider(store: MapStore, backend: str, mc: MapConfig, engine) -> MapProvider:
    """The map policy ``backend`` (block | grid | srt | global) for ``store`` and its provider."""
    policy = make_policy(backend, store, **policy_settings(mc))
    return MapProvider(store, policy, engine=engine, prefetch=mc.prefetch, lookahead_s=mc.prefetch_lookahead_s,
                       cache_mb=mc.cache_mb, retry_missing_s=mc.retry_missing_s)


def check_backend(store: MapStore, backend: str, mc: MapConfig) -> None:
    """MapError, before any work, unless the map policy ``backend`` can serve ``store`` (a block
    map for ``block``, a grid map for ``grid`` / ``srt``): what :func:`build_session` would raise
    on a live source's first scan."""
    make_policy(backend, store, **policy_settings(mc))


# ----------------------------------------------------------------------------- global init
def init_params(gi: GlobalInitConfig, rc: RegistrationConfig | None = None):
    """The global localizer's parameters (``InitParams``) from the ``global_init`` section."""
    return InitParams.from_config(gi, rc)


def place_index_params(gi: GlobalInitConfig):
    """The place index's parameters from the ``global_init`` section."""
    return init_params(gi).place_index_params


def init_settings(gi: GlobalInitConfig) -> GlobalInitSettings:
    """The session's search windows of global init."""
    return GlobalInitSettings(gi.window_m, gi.yaw_window_deg)


def make_localizer(store: MapStore, gravity_map, cfg: Config, engine=None):
    """The global localizer of ``store`` (refining with ``engine``, default the configured engine
    at ``global_init.ndt_resolution_m``)."""
    gi, rc = cfg.global_init, cfg.registration
    if engine is None:
        engine = build_engine(rc, resolution_m=gi.ndt_resolution_m)
    return GlobalLocalizer.for_store(store, gravity_map, init_params(gi, rc), engine=engine)


# ----------------------------------------------------------------------------- tracking
def imu_noise(imu_cfg) -> ImuNoise:
    """The IMU's noise model from the ``imu`` section."""
    return ImuNoise(imu_cfg.acc_noise_density, imu_cfg.gyro_noise_density, imu_cfg.acc_bias_random_walk,
                    imu_cfg.gyro_bias_random_walk, imu_cfg.integration_sigma,
                    tuple(imu_cfg.acc_noise_density_axes), tuple(imu_cfg.gyro_noise_density_axes))


def tracker_settings(cfg: Config) -> TrackerSettings:
    """The tracker's settings: the ``tracking`` section as is (it is the tracker's own dataclass),
    the scan cut from the ``lidar`` and ``dataset`` sections field by field."""
    lc, dc = cfg.lidar, cfg.dataset
    scan = ScanParams(voxel_size_m=lc.voxel_size_m, max_points=lc.max_points, min_range_m=dc.min_range_m,
                      max_range_m=dc.max_range_m, deskew=lc.deskew)
    return TrackerSettings(tracking=cfg.tracking, scan=scan)


def make_tracker(cfg: Config, info, *, map_provider, registration, relocalize=None,
                 use_imu: bool | None = None) -> Estimator:
    """The tracker (sliding-window smoother) from the ``tracking``, ``imu``, ``lidar`` and
    ``dataset`` sections and a ``SequenceInfo`` (extrinsics, gravity): the IMU estimator or the
    LiDAR-only one.

    use_imu: whether to use the IMU, e.g. ``len(seq.imu()) > 0 and cfg.tracking.use_imu`` (the
    caller knows whether the sequence has one); None: ``cfg.tracking.use_imu``."""
    imu = cfg.tracking.use_imu if use_imu is None else bool(use_imu)
    return make_estimator(imu=imu, map_provider=map_provider, registration=registration,
                          T_body_lidar=info.T_body_lidar, T_body_imu=info.T_body_imu, gravity_map=info.gravity_map,
                          settings=tracker_settings(cfg), imu_noise=imu_noise(cfg.imu), relocalize=relocalize)


def evaluation_options(cfg: Config) -> dict[str, Any]:
    """Keywords of the accuracy evaluation (``evaluate_trajectories``)."""
    ev = cfg.evaluation
    return {"align": ev.align, "max_time_diff_s": ev.max_time_diff_s, "rpe_deltas_m": ev.rpe_deltas_m}


def map_facts(store: MapStore) -> dict[str, str]:
    """What a run records of the map it tracks in (its ``metrics.json``), for ``map changes`` and
    ``map update`` to tell whether a run was tracked in the map they are given: ``map_path``
    (absolute, or the URL) and ``map_id``, the store's identity, the same wherever it was moved
    or copied to and through its updates (:func:`blockloc.maps.changes.versions.map_identity`;
    left out for a store without one)."""
    from pathlib import Path

    from blockloc.maps.changes.versions import map_identity

    facts = {"map_path": store.path if store.files.is_remote else str(Path(store.path).resolve())}
    identity = map_identity(store)
    if identity is not None:
        facts["map_id"] = identity
    return facts


def build_session(cfg: Config, seq, store: MapStore, *, backend: str | None = None, observers: Sequence = (),
                  out_dir=None, keep_estimates: bool = False, facts: dict | None = None) -> Session:
    """All parts of a :class:`Session` from a config: the engine ``registration.method``, the map
    policy ``backend`` (default ``map.backend``) and its provider, the global localizer (refining
    with the same engine at ``global_init.ndt_resolution_m``) and the tracker."""
    backend = backend or cfg.map.backend
    rc, mc, gi = cfg.registration, cfg.map, cfg.global_init
    seq = with_map_mounting(seq, store, mc.use_map_mounting)
    engine = build_engine(rc)
    provider = make_provider(store, backend, mc, engine)
    try:
        localizer = make_localizer(store, seq.info.gravity_map, cfg)
        session = Session(seq, None, provider, localizer=localizer, store=store, init_settings=init_settings(gi),
                          observers=observers, out_dir=out_dir, keep_estimates=keep_estimates,
                          evaluation=evaluation_options(cfg), plots=cfg.evaluation.plots,
                          facts={"backend": backend, "registration": rc.method, **map_facts(store),
                                 **(facts or {})},
                          config=cfg.to_dict())
        session.tracker = make_tracker(cfg, seq.info, map_provider=provider, registration=engine,
                                       relocalize=session.relocalize,
                                       use_imu=len(session.imu) > 0 and cfg.tracking.use_imu)
    except BaseException:
        provider.close()
        raise
    return session
