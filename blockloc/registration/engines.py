"""Registration engines: one protocol, chosen by name (``registration.method``).

Everything that registers a scan against a map (tracking, global-init refinement and
verification, relocalization, the map provider that builds targets) holds an engine and calls
only the methods of :class:`Registration`. Engines hold settings only; targets are opaque objects
the engine builds and reads, so one engine instance serves many targets and threads.

The contract (every engine, tested in ``tests/registration/test_engines.py``):

- ``build_target(points)``: points (N, 3) map frame, metres -> target.
- ``build_tiled_target(tiles)``: ``{tile_id: (N, 3) points}`` -> target; ``update_tiles(target,
  add, remove)`` returns the target with tiles added/removed (the same object when the engine is
  ``incremental``, a rebuilt one otherwise). Targets have ``num_points`` and ``nbytes``.
- ``align(target, source_points, T_init)`` with source (N, 3) in the sensor frame and ``T_init``
  (4, 4) the initial ``T_target_source`` -> a result with ``T_target_source`` (4, 4),
  ``converged``, ``iterations``, ``fitness`` (share of source points that are inliers of the
  target's voxel Gaussians, within their 99% ellipsoid: the same measure for every engine, so
  health checks and verification thresholds mean one thing), ``num_inliers``, ``num_points``,
  ``score`` (higher is better, comparable between poses of one scan), ``H`` (6, 6) and ``b`` (6,)
  of the engine's cost at the result in GTSAM's Pose3 tangent (rotation first, right
  perturbation of ``T_target_source``; H PSD), and ``error``.
- ``evaluate(target, source_points, T_target_source)`` -> an object with ``score`` and
  ``num_inliers`` at a pose, without optimizing (verification).

Adding an engine is one new module with a class meeting this contract plus one line in
``ENGINES``. Constructors take keyword settings (``resolution_m``, ``max_iterations``,
``num_threads``, ...) with defaults and ignore the ones they do not use, so
:func:`make_engine` can pass every ``registration`` setting to any engine.
"""

from __future__ import annotations

import importlib
from collections.abc import Hashable, Iterable, Mapping
from typing import Any, Protocol, runtime_checkable

import numpy as np

from blockloc.errors import RegistrationError

#: Engines by ``registration.method``: "module:Class", imported when first made.
ENGINES = {
    "ndt": "blockloc.registration.engines:NdtEngine",
    "vgicp": "blockloc.registration.vgicp:VgicpEngine",
}


@runtime_checkable
class Registration(Protocol):
    """What tracking, global init and the map provider need from a registration engine."""

    name: str
    incremental: bool  # targets are updated in place by tile (else rebuilt)

    def build_target(self, points: np.ndarray) -> Any: ...

    def build_tiled_target(self, tiles: Mapping[Hashable, np.ndarray]) -> Any: ...

    def update_tiles(self, target: Any, add: Mapping[Hashable, np.ndarray],
                     remove: Iterable[Hashable]) -> Any: ...

    def align(self, target: Any, source_points: np.ndarray, T_init: np.ndarray | None = None) -> Any: ...

    def evaluate(self, target: Any, source_points: np.ndarray, T_target_source: np.ndarray) -> Any: ...


def make_engine(method: str, **settings: Any) -> Registration:
    """The engine ``method`` (``ndt`` | ``vgicp``) with ``settings`` (see the module docstring)."""
    spec = ENGINES.get(method)
    if spec is None:
        raise RegistrationError(f"registration method {method!r}: expected one of {', '.join(ENGINES)}")
    module, cls = spec.split(":")
    return getattr(importlib.import_module(module), cls)(**settings)


def engine_from_settings(settings: Mapping[str, Any], **overrides: Any) -> Registration:
    """The engine named by ``settings["method"]`` with the other settings (e.g. the ``registration``
    config section as a dict) and ``overrides`` (e.g. another ``resolution_m``)."""
    rest = {k: v for k, v in settings.items() if k != "method"}
    return make_engine(str(settings.get("method", "ndt")), **{**rest, **overrides})


def inlier_ratio(engine: Registration, target: Any, points: np.ndarray, T_target_source: np.ndarray) -> float:
    """Share of ``points`` (N, 3), source frame, that are inliers of ``target`` at a pose."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return 0.0
    return float(engine.evaluate(target, pts, T_target_source).num_inliers) / len(pts)


class NdtEngine:
    """The Normal Distributions Transform (:mod:`blockloc.registration.ndt`), the default.

    resolution_m: voxel edge of the finest level; min_points_per_voxel; coarse_levels: extra
    levels at 2x, 4x ... for coarse-to-fine; the remaining keywords go to
    :class:`~blockloc.registration.ndt.NdtRegistration` (neighbors, outlier_ratio,
    max_iterations, step_epsilon, coarse_to_fine, num_threads). Targets are tiled
    (``NdtTarget.add_tile``/``remove_tile``): ``incremental``.
    """

    name = "ndt"
    incremental = True

    def __init__(self, *, resolution_m: float = 1.0, min_points_per_voxel: int = 6,
                 coarse_levels: int = 1, neighbors: str = "DIRECT7", outlier_ratio: float = 0.55,
                 max_iterations: int = 30, step_epsilon: float = 1e-3, coarse_to_fine: bool = True,
                 num_threads: int | None = None, **_unused: Any) -> None:
        from blockloc.registration.ndt import NdtRegistration

        self.target_options = {"resolution": float(resolution_m),
                               "min_points_per_voxel": int(min_points_per_voxel),
                               "coarse_levels": int(coarse_levels)}
        self.registration = NdtRegistration(neighbors=neighbors, outlier_ratio=outlier_ratio,
                                            max_iterations=max_iterations, step_epsilon=step_epsilon,
                                            coarse_to_fine=coarse_to_fine, num_threads=num_threads)

    def build_target(self, points):
        from blockloc.registration.ndt import NdtTarget

        return NdtTarget.build(points, **self.target_options)

    def build_tiled_target(self, tiles):
        from blockloc.registration.ndt import NdtTarget

        return NdtTarget.from_tiles(tiles, **self.target_options)

    def tile_stats(self, points):
        """Voxel statistics of points (N, 3) at this engine's target settings, reusable across
        targets (``target_from_tile_stats``; global init keeps them per map entry)."""
        from blockloc.registration.ndt import NdtTarget

        return NdtTarget(**self.target_options).tile_stats(points)

    def tile_stats_from_arrays(self, arrays):
        """The statistics ``stats.to_arrays()`` gave (e.g. read back from a file), checked against
        this engine's levels; raises ValueError or KeyError on arrays of another shape."""
        from blockloc.registration.ndt import TileStats

        return TileStats.from_arrays(arrays, self.target_options["coarse_levels"] + 1)

    def target_from_tile_stats(self, tiles):
        """The target of ``{key: tile_stats}`` (``NdtTarget.from_tile_stats``): the same target as
        ``build_tiled_target`` of the points they were computed from."""
        from blockloc.registration.ndt import NdtTarget

        return NdtTarget.from_tile_stats(tiles, **self.target_options)

    def update_tiles(self, target, add, remove):
        for key in remove:
            target.remove_tile(key)
        for key, points in add.items():
            target.add_tile(key, points)
        return target

    def align(self, target, source_points, T_init=None):
        return self.registration.align(target, source_points, T_init)

    def align_from_prediction(self, target, source_points, T_pred):
        """:meth:`align` from a tracker's prediction: the fine level alone first
        (:meth:`NdtRegistration.align_from_prediction`)."""
        return self.registration.align_from_prediction(target, source_points, T_pred)

    def evaluate(self, target, source_points, T_target_source):
        return self.registration.evaluate(target, source_points, T_target_source, derivatives=False)

    def inliers_per_group(self, target, source_points, starts, T_target_source):
        """:meth:`NdtRegistration.inliers_per_group` (an engine without it is asked group by group)."""
        return self.registration.inliers_per_group(target, source_points, starts, T_target_source)
