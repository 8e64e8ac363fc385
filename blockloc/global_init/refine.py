"""6-DoF refinement of 2D candidates with NDT, and verification by fitness.

A 2D candidate fixes x, y and yaw in the levelled frame; roll and pitch come from gravity (the
levelling rotation) and z from the map's local ground under the candidate plus the body's height
above the ground seen in the scan. The registration engine (NDT by default, see
:mod:`blockloc.registration.engines`) then refines all six degrees of freedom against the map
points around the candidates; the target is built once per search and reused for every
candidate. A candidate is verified when registration converged and its fitness (inlier ratio)
reaches ``min_fitness``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class RefineResult:
    """T_map_body: (4, 4) refined pose; fitness: inlier ratio in [0, 1]; converged: NDT's flag;
    ndt_score: the engine's score per source point (higher is better)."""

    T_map_body: np.ndarray
    fitness: float
    converged: bool
    iterations: int = 0
    ndt_score: float = 0.0


class Refiner:
    """A registration target built once from map points (M, 3), map frame, metres, by ``engine``
    (a :class:`blockloc.registration.engines.Registration`); refines and verifies many candidates."""

    def __init__(self, engine, map_points: np.ndarray):
        self.engine = engine
        self._target = engine.build_target(np.asarray(map_points, dtype=np.float64).reshape(-1, 3))

    def inlier_ratio(self, points_body: np.ndarray, T_map_body: np.ndarray) -> float:
        """Share of points (N, 3), body frame, that are inliers of the target at ``T_map_body``."""
        from blockloc.registration.engines import inlier_ratio

        return inlier_ratio(self.engine, self._target, points_body, T_map_body)

    def align(self, source_body: np.ndarray, T_init: np.ndarray) -> RefineResult:
        """Refine ``T_init`` (4, 4) T_map_body for scan points (N, 3), body frame, metres."""
        res = self.engine.align(self._target, np.asarray(source_body, dtype=np.float64), T_init)
        return RefineResult(np.asarray(res.T_target_source), float(res.fitness), bool(res.converged),
                            int(res.iterations), float(res.score) / max(int(res.num_points), 1))
