"""6-DoF refinement of 2D candidates with NDT, and verification by fitness.

A 2D candidate fixes x, y and yaw in the levelled frame; roll and pitch come from gravity (the
levelling rotation) and z from the map's local ground under the candidate plus the body's height
above the ground seen in the scan. NDT (``blockloc.registration.ndt``) then refines all six degrees
of freedom against the map points around the candidates; the target is built once per search and
reused for every candidate. A candidate is verified when NDT converged and its fitness (inlier
ratio) reaches ``min_fitness``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class RefineResult:
    """T_map_body: (4, 4) refined pose; fitness: inlier ratio in [0, 1]; converged: NDT's flag;
    ndt_score: NDT score per source point (higher is better)."""

    T_map_body: np.ndarray
    fitness: float
    converged: bool
    iterations: int = 0
    ndt_score: float = 0.0


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N, 3) -> (M, 3): one point (the first) per voxel of side ``voxel_m``."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if voxel_m <= 0 or len(pts) == 0:
        return pts
    keys = np.floor(pts / voxel_m).astype(np.int64)
    _, idx = np.unique(keys, axis=0, return_index=True)
    return pts[np.sort(idx)]


class Refiner:
    """NDT target built once from map points (M, 3), map frame, metres; aligns many candidates."""

    def __init__(self, map_points: np.ndarray, resolution_m: float = 1.0, num_threads: int = 2,
                 max_iterations: int = 30):
        self.resolution_m = resolution_m
        self.num_threads = num_threads
        self.max_iterations = max_iterations
        self._map = np.asarray(map_points, dtype=np.float64).reshape(-1, 3)
        from blockloc.registration.ndt import NdtRegistration, NdtTarget

        self._target = NdtTarget.build(self._map, resolution_m)
        self._reg = NdtRegistration(max_iterations=max_iterations, num_threads=num_threads)

    def inlier_ratio(self, points_body: np.ndarray, T_map_body: np.ndarray) -> float:
        """Share of points (N, 3), body frame, that are NDT inliers of the target at ``T_map_body``."""
        pts = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return 0.0
        ev = self._reg.evaluate(self._target, pts, T_map_body, derivatives=False)
        return float(ev.num_inliers) / len(pts)

    def align(self, source_body: np.ndarray, T_init: np.ndarray) -> RefineResult:
        """Refine ``T_init`` (4, 4) T_map_body for scan points (N, 3), body frame, metres."""
        res = self._reg.align(self._target, np.asarray(source_body, dtype=np.float64), T_init)
        return RefineResult(np.asarray(res.T_target_source), float(res.fitness), bool(res.converged),
                            int(res.iterations), float(res.score) / max(int(res.num_points), 1))
