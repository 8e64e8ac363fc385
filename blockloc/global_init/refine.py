"""6-DoF refinement of 2D candidates with NDT, and verification by fitness.

A 2D candidate fixes x, y and yaw in the levelled frame; roll and pitch come from gravity (the
levelling rotation) and z from the map's local ground under the candidate plus the body's height
above the ground seen in the scan. The registration engine (NDT by default, see
:mod:`blockloc.registration.engines`) then refines all six degrees of freedom against the map
points around the candidates; the target is built once per search and reused for every
candidate. A candidate is verified when registration converged and its fitness (inlier ratio)
reaches ``min_fitness``.

Scored on what overlaps: with a footprint (``footprint_cell_m``), the inlier ratios count only
the scan points that fall where the target holds map data (levelled 2D cells of that side with a
share of the typical cell's map points, :class:`Footprint`): a robot at the map's edge, or in a part built since,
sees much the map cannot explain, which is no evidence against the pose. ``overlap`` (the share of
the scan inside the footprint) says how much of the scan was judged; verification asks a floor.
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
    overlap: float = 1.0  # share of the scan points inside the target's footprint (1 without one)


class Footprint:
    """Where map points (M, 3), map frame, are: levelled 2D cells of ``cell_m`` (``R_L_map`` (3, 3)
    levels the map frame) holding at least ``min_share`` of the median count of the non-empty
    cells (and 3): relative, so that a map voxelized coarser or finer means the same (ground seen
    well, not a few returns from afar)."""

    def __init__(self, map_points: np.ndarray, R_L_map: np.ndarray, cell_m: float, min_share: float):
        self.R = np.asarray(R_L_map, float).reshape(3, 3)
        self.cell_m = float(cell_m)
        keys, counts = np.unique(self._keys_map(map_points), return_counts=True)
        floor = max(3.0, min_share * float(np.median(counts))) if len(counts) else 3.0
        self.keys = keys[counts >= floor]  # sorted

    def _codes(self, xy_L: np.ndarray) -> np.ndarray:
        c = np.floor(np.asarray(xy_L, float).reshape(-1, 2) / self.cell_m).astype(np.int64)
        return (c[:, 0] << 32) + (c[:, 1] & 0xFFFFFFFF)

    def _keys_map(self, points_map: np.ndarray) -> np.ndarray:
        return self._codes((np.asarray(points_map, float).reshape(-1, 3) @ self.R.T)[:, :2])

    def contains_L(self, xy_L: np.ndarray) -> np.ndarray:
        """(N,) bool: levelled-frame points (N, 2), metres, inside the footprint."""
        codes = self._codes(xy_L)
        i = np.clip(np.searchsorted(self.keys, codes), 0, max(len(self.keys) - 1, 0))
        return (self.keys[i] == codes) if len(self.keys) else np.zeros(len(codes), bool)

    def contains(self, points_map: np.ndarray) -> np.ndarray:
        """(N,) bool: map-frame points (N, 3) inside the footprint."""
        return self.contains_L((np.asarray(points_map, float).reshape(-1, 3) @ self.R.T)[:, :2])


class Refiner:
    """A registration target built once from map points (M, 3), map frame, metres, by ``engine``
    (a :class:`blockloc.registration.engines.Registration`); refines and verifies many candidates."""

    def __init__(self, engine, map_points: np.ndarray, R_L_map: np.ndarray | None = None,
                 footprint_cell_m: float = 0.0, footprint_min_share: float = 0.25):
        self.engine = engine
        pts = np.asarray(map_points, dtype=np.float64).reshape(-1, 3)
        self._target = engine.build_target(pts)
        self.footprint = (Footprint(pts, np.eye(3) if R_L_map is None else R_L_map, footprint_cell_m,
                                    footprint_min_share) if footprint_cell_m > 0 else None)

    def overlapping(self, points_body: np.ndarray, T_map_body: np.ndarray) -> np.ndarray:
        """(N,) bool: the points (N, 3), body frame, that fall inside the footprint at ``T_map_body``
        (all of them without a footprint)."""
        pts = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
        if self.footprint is None:
            return np.ones(len(pts), bool)
        if not np.all(np.isfinite(T_map_body)):
            return np.zeros(len(pts), bool)
        return self.footprint.contains(pts @ T_map_body[:3, :3].T + T_map_body[:3, 3])

    def inlier_ratio(self, points_body: np.ndarray, T_map_body: np.ndarray) -> float:
        """Share of points (N, 3), body frame, inside the footprint that are inliers of the target at
        ``T_map_body`` (0 when none is inside)."""
        from blockloc.registration.engines import inlier_ratio

        pts = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
        return inlier_ratio(self.engine, self._target, pts[self.overlapping(pts, T_map_body)], T_map_body)

    def align(self, source_body: np.ndarray, T_init: np.ndarray) -> RefineResult:
        """Refine ``T_init`` (4, 4) T_map_body for scan points (N, 3), body frame, metres; fitness and
        overlap over the footprint (module docstring)."""
        src = np.asarray(source_body, dtype=np.float64)
        res = self.engine.align(self._target, src, T_init)
        T = np.asarray(res.T_target_source)
        fitness, overlap = float(res.fitness), 1.0
        if self.footprint is not None:
            inside = self.overlapping(src, T)
            overlap = float(inside.mean()) if len(src) else 0.0
            fitness = self.inlier_ratio(src, T)
        return RefineResult(T, fitness, bool(res.converged), int(res.iterations),
                            float(res.score) / max(int(res.num_points), 1), overlap)
