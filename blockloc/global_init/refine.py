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

from blockloc.global_init.projection import levelled_xy

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
    well, not a few returns from afar).

    Held as a dense boolean grid over the points' cell box (a refinement box of 100 m at 1 m is
    10^4 cells), counted in one compiled pass (sorting the cell codes of a million points took
    ~0.3 s CPU a refinement target, as long as the NDT target itself); a box of more than ``MAX_DENSE_CELLS`` cells (points spread far
    apart) falls back to the sorted codes of the occupied cells.
    """

    MAX_DENSE_CELLS = 1 << 24

    def __init__(self, map_points: np.ndarray, R_L_map: np.ndarray, cell_m: float, min_share: float):
        self.R = np.asarray(R_L_map, float).reshape(3, 3)
        self.cell_m = float(cell_m)
        self._lo = np.zeros(2, np.int64)
        self._grid = None  # (NX, NY) bool, cells [lo, lo + shape)
        self.keys = np.zeros(0, np.int64)  # sorted codes of the footprint's cells (fallback)
        from blockloc.global_init import _kernels as K

        pts = np.asarray(map_points).reshape(-1, 3)
        if pts.dtype not in (np.float32, np.float64):
            pts = pts.astype(np.float64)
        pts = np.ascontiguousarray(pts)
        if len(pts) == 0:
            return
        R2 = np.ascontiguousarray(self.R[:2])
        lo0, lo1, hi0, hi1 = K.cell_bounds(pts, R2, self.cell_m)
        nx, ny = hi0 - lo0 + 1, hi1 - lo1 + 1
        if nx * ny <= self.MAX_DENSE_CELLS:
            counts = K.cell_counts(pts, R2, self.cell_m, lo0, lo1, nx, ny)
            floor = max(3.0, min_share * float(np.median(counts[counts > 0])))
            self._lo, self._grid = np.array([lo0, lo1], np.int64), counts >= floor
        else:
            keys, counts = np.unique(self._codes(self._cells(levelled_xy(pts, self.R))), return_counts=True)
            floor = max(3.0, min_share * float(np.median(counts)))
            self.keys = keys[counts >= floor]

    @classmethod
    def from_counts(cls, R_L_map: np.ndarray, cell_m: float, min_share: float, lo: np.ndarray,
                    counts: np.ndarray) -> "Footprint":
        """The footprint of map points counted per levelled cell: ``counts`` (NX, NY) over cells
        [lo, lo + (NX, NY)) (``lo`` (2,) int): the same as built from the points themselves."""
        fp = cls(np.zeros((0, 3)), R_L_map, cell_m, min_share)
        counts = np.asarray(counts)
        if counts.size and counts.any():
            floor = max(3.0, min_share * float(np.median(counts[counts > 0])))
            fp._lo, fp._grid = np.asarray(lo, np.int64).reshape(2), counts >= floor
        return fp

    def _cells(self, xy_L: np.ndarray) -> np.ndarray:
        return np.floor(np.asarray(xy_L, float).reshape(-1, 2) / self.cell_m).astype(np.int64)

    @staticmethod
    def _codes(cells: np.ndarray) -> np.ndarray:
        return (cells[:, 0] << 32) + (cells[:, 1] & 0xFFFFFFFF)

    def contains_L(self, xy_L: np.ndarray) -> np.ndarray:
        """(N,) bool: levelled-frame points (N, 2), metres, inside the footprint."""
        c = self._cells(xy_L)
        if self._grid is not None:
            i = c - self._lo
            nx, ny = self._grid.shape
            inside = (i[:, 0] >= 0) & (i[:, 0] < nx) & (i[:, 1] >= 0) & (i[:, 1] < ny)
            out = np.zeros(len(c), bool)
            out[inside] = self._grid[i[inside, 0], i[inside, 1]]
            return out
        codes = self._codes(c)
        k = np.clip(np.searchsorted(self.keys, codes), 0, max(len(self.keys) - 1, 0))
        return (self.keys[k] == codes) if len(self.keys) else np.zeros(len(codes), bool)

    def contains(self, points_map: np.ndarray) -> np.ndarray:
        """(N,) bool: map-frame points (N, 3) inside the footprint."""
        return self.contains_L(levelled_xy(points_map, self.R))


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

    @classmethod
    def from_target(cls, engine, target, footprint: Footprint | None) -> "Refiner":
        """A refiner of a target ``engine`` built already (``targets.TargetCache``), with its
        footprint (None: every point counts)."""
        ref = cls.__new__(cls)
        ref.engine, ref._target, ref.footprint = engine, target, footprint
        return ref

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

    def block_inlier_ratios(self, points_body: np.ndarray, T_map_body: np.ndarray, block: np.ndarray,
                            num_blocks: int) -> np.ndarray:
        """(num_blocks,) float: :meth:`inlier_ratio` of each block's points, ``block`` (N,) int in
        [0, num_blocks) the block of each point (N, 3), body frame; the same values, with one
        pass over the points where the engine counts inliers per group (NDT)."""
        pts = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
        block = np.asarray(block, np.int64).reshape(-1)
        per_group = getattr(self.engine, "inliers_per_group", None)
        if per_group is None:
            return np.array([self.inlier_ratio(pts[block == k], T_map_body) for k in range(num_blocks)], float)
        sel = np.flatnonzero(self.overlapping(pts, T_map_body))
        order = sel[np.argsort(block[sel], kind="stable")]  # each block's points in their order
        counts = np.bincount(block[sel], minlength=num_blocks)
        starts = np.concatenate([[0], np.cumsum(counts)])
        if len(order) == 0:
            return np.zeros(num_blocks)
        inliers = per_group(self._target, pts[order], starts, T_map_body)
        return np.where(counts > 0, inliers / np.maximum(counts, 1), 0.0)

    def align_settled(self, source_body: np.ndarray, T_init: np.ndarray) -> RefineResult:
        """:meth:`align`, and once more from where it stopped when it ran out of iterations on its
        way (sliding along a corridor, or on to another optimum): an optimum is where the second run
        stops; one still sliding after it stays unconverged."""
        r = self.align(source_body, T_init)
        if not r.converged and np.all(np.isfinite(r.T_map_body)):
            r = self.align(source_body, r.T_map_body)
        return r

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


class WholeScan:
    """The scan's whole reach for the last decisions of a search: ``points`` (K, 3), body frame (one
    per ``whole_scan_voxel_m`` voxel, every range), aligned against the map ``range_m`` around a
    pose, where the search refines a sample within ``max_range_m`` against ``refine_range_m``.

    ``refiner_over(xy_L (2,), d)``: the refiner of the map in the levelled box xy_L +- d (the
    localizer's, from its target cache), or None; ``R_L_map`` (3, 3) levels the map frame. One target
    is kept while the poses asked about stay within ``reuse_m`` of its centre (a best and its
    rivals nearby): the map is then at least ``range_m - reuse_m`` around each.
    """

    def __init__(self, points: np.ndarray, refiner_over, R_L_map: np.ndarray, range_m: float,
                 reuse_m: float = 2.0):
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self._refiner_over = refiner_over
        self._R = np.asarray(R_L_map, float).reshape(3, 3)
        self.range_m = float(range_m)
        self.reuse_m = float(reuse_m)
        self._kept: tuple[np.ndarray, Refiner | None] | None = None

    def refiner_at(self, T_map_body: np.ndarray) -> Refiner | None:
        """The refiner of the map ``range_m`` around the pose T_map_body (4, 4), or None (no map there)."""
        xy = (self._R @ np.asarray(T_map_body, float)[:3, 3])[:2]
        if self._kept is None or np.max(np.abs(xy - self._kept[0])) > self.reuse_m:
            self._kept = (xy, self._refiner_over(xy, self.range_m))
        return self._kept[1]

    def release(self) -> None:
        """Drop the kept target (a decision that stands needs it no more; a new pose builds one)."""
        self._kept = None

    def align(self, T_map_body: np.ndarray) -> RefineResult | None:
        """``Refiner.align_settled`` of the points from T_map_body (4, 4) against :meth:`refiner_at`'s
        target, or None (no points, or no map there)."""
        ref = self.refiner_at(T_map_body) if len(self.points) else None
        return None if ref is None else ref.align_settled(self.points, T_map_body)
