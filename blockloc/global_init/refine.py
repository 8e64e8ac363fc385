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
    """T_map_body: (4, 4) refined pose; fitness: inlier ratio in [0, 1]; converged: NDT's flag."""

    T_map_body: np.ndarray
    fitness: float
    converged: bool
    iterations: int = 0


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
        self._ndt = None
        try:
            from blockloc.registration import ndt  # noqa: F401

            self._ndt = ndt
        except ImportError:  # the NDT engine has not landed: development stand-in only
            log.warning("blockloc.registration.ndt not available; refining with small_gicp GICP")
        if self._ndt is not None:
            self._target = self._ndt.NdtTarget.build(self._map, resolution_m)
            self._reg = self._ndt.NdtRegistration(max_iterations=max_iterations,
                                                  num_threads=num_threads)
        else:
            import small_gicp

            self._target, self._tree = small_gicp.preprocess_points(self._map, 0.25, 20, num_threads)

    def align(self, source_body: np.ndarray, T_init: np.ndarray) -> RefineResult:
        """Refine ``T_init`` (4, 4) T_map_body for scan points (N, 3), body frame, metres."""
        src = np.asarray(source_body, dtype=np.float64)
        if self._ndt is not None:
            res = self._reg.align(self._target, src, T_init)
            return RefineResult(np.asarray(res.T_target_source), float(res.fitness), bool(res.converged),
                                int(getattr(res, "iterations", 0)))
        import small_gicp

        source, _ = small_gicp.preprocess_points(src, 0.25, 20, self.num_threads)
        res = small_gicp.align(self._target, source, self._tree, T_init, registration_type="GICP",
                               max_correspondence_distance=1.0, num_threads=self.num_threads,
                               max_iterations=self.max_iterations)
        return RefineResult(np.asarray(res.T_target_source), float(res.num_inliers) / max(source.size(), 1),
                            bool(res.converged), int(res.iterations))
