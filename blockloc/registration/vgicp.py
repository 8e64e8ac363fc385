"""small_gicp's voxelized GICP (VGICP) as a registration engine (``registration.method: vgicp``).

Target: the map points with per-point covariances (``target_num_neighbors`` nearest, by default
``num_neighbors``) inserted into a ``small_gicp.GaussianVoxelMap`` of leaf ``resolution_m``. Source: the scan with its own per-point
covariances, estimated at every ``align`` (part of its cost: about 10 ms for a 20k-point scan).
``small_gicp.align(..., registration_type="VGICP")`` returns ``H`` and ``b`` of its cost in the
GTSAM Pose3 tangent (rotation first, right perturbation of ``T_target_source``), which is what
the tracker's factors take.

Overlapping grids (``voxel_grids``, default 2): VGICP pairs each scan point with the one voxel it
falls in, so where a surface crosses a voxel border the pull depends on where the grid lies, a
bias that moves with the grid, not with the scene. As the first NDT (Biber and Strasser 2003)
did with four overlapping grids, the target holds ``voxel_grids`` voxel maps of the same points,
grid k offset by k * resolution / voxel_grids along every axis (the same per-point covariances,
inserted through a translation); the scan is aligned on the first, then on each next from the
first's result, and the results are fused: the mean of their poses weighted by their Hessians, in
the tangent of the first, along the directions they constrain (weak ones keep the first grid's
pose), leaving out a grid that settled more than half a voxel or 0.5 deg away. The fused ``H`` is the Hessians' mean (the grids see the same points:
their information is not independent). On 83 campus scans registered alone from ground truth
(``python -m bench.scan_errors``) two grids gave 4.95 cm translation RMS against one grid's 5.83 cm
and NDT's 5.21 cm, at 1.3x one grid's alignment time (the second starts from the first's result).

Fitness and score: VGICP counts as inliers the points with any voxel within
``max_correspondence_distance``, which depends on that distance and is looser than NDT's 99%
ellipsoid. So that health checks and global-init verification mean the same for every engine
(see :mod:`blockloc.registration.engines`), each target also holds NDT voxel Gaussians of the same
points (DIRECT1, one level), and ``fitness``/``score`` are that target's inlier ratio and NDT score
at the VGICP result. No VGICP target is updated in place: tile changes rebuild it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from blockloc.errors import RegistrationError
from blockloc.geometry import lever_arm_scaling, make_T, rotation_angle, so3_exp, so3_log

log = logging.getLogger(__name__)


@dataclass
class VgicpTarget:
    """A built target: the small_gicp voxel maps (grid k holds the points moved by ``-shifts[k]``),
    NDT Gaussians of the same points for fitness, and the tiles it was built from ({id: (N, 3)
    map frame}, or {None: points})."""

    voxelmaps: list
    shifts: np.ndarray  # (grids, 3) metres, map frame
    scoring: Any  # blockloc.registration.ndt.NdtTarget, one level, for fitness and score
    tiles: dict
    num_points: int

    @property
    def voxelmap(self):
        """The first grid's voxel map (offset 0)."""
        return self.voxelmaps[0]

    @property
    def nbytes(self) -> int:
        # per point: xyz + covariance (4 + 16 doubles) inside small_gicp, roughly
        return int(self.num_points * 20 * 8)


@dataclass
class VgicpResult:
    """Outcome of one VGICP alignment (the fields of the engine contract)."""

    T_target_source: np.ndarray
    converged: bool
    iterations: int
    fitness: float
    num_inliers: int
    num_points: int
    score: float
    error: float
    H: np.ndarray
    b: np.ndarray  # and ``error``: the first grid's, at its own pose (``T`` and ``H`` are fused)


class VgicpEngine:
    """VGICP with ``resolution_m`` voxels; ``max_correspondence_distance_m`` defaults to it.

    num_neighbors: neighbours for the scan's per-point covariances (10: tracking hands in scans
    thinned to 0.5 m voxels, where 20 neighbours span metres; on the real HDL-32E pair at 0.5 m, 20
    gave 0.67 deg of rotation error and 10 gave 0.28 deg). target_num_neighbors: the map's (None:
    num_neighbors). A voxel's Gaussian is the mean of its points' covariances, so on a dense map
    (0.2 m voxels) few neighbours describe a patch much smaller than the voxel and a scan point
    is pulled toward the voxel's mean along the surface; blockloc/presets/sim.yaml gives what more map
    neighbours did on the campus. voxel_grids: overlapping voxel grids whose results are fused
    (see the module docstring; 1: small_gicp's single grid). max_iterations; num_threads.
    outlier_ratio and min_points_per_voxel shape the NDT Gaussians used for fitness.
    """

    name = "vgicp"
    incremental = False

    def __init__(self, *, resolution_m: float = 1.0, max_correspondence_distance_m: float | None = None,
                 num_neighbors: int = 10, target_num_neighbors: int | None = None,
                 voxel_grids: int = 2, max_iterations: int = 30, num_threads: int | None = 2,
                 outlier_ratio: float = 0.55, min_points_per_voxel: int = 6, **_unused: Any) -> None:
        from blockloc.registration.ndt import NdtRegistration

        if not float(resolution_m) > 0:
            raise RegistrationError(f"resolution {resolution_m!r}: expected a positive number of metres")
        self.resolution_m = float(resolution_m)
        self.max_correspondence_distance_m = float(max_correspondence_distance_m or resolution_m)
        self.num_neighbors = int(num_neighbors)
        self.target_num_neighbors = int(target_num_neighbors or num_neighbors)
        if int(voxel_grids) < 1:
            raise RegistrationError(f"voxel_grids {voxel_grids!r}: expected an integer >= 1")
        self.voxel_grids = int(voxel_grids)
        self.max_iterations = int(max_iterations)
        self.num_threads = int(num_threads or 1)
        self.min_points_per_voxel = int(min_points_per_voxel)
        self._scorer = NdtRegistration(neighbors="DIRECT1", outlier_ratio=outlier_ratio)

    # ------------------------------------------------------------------ targets
    def build_target(self, points: np.ndarray) -> VgicpTarget:
        return self.build_tiled_target({None: points})

    def build_tiled_target(self, tiles) -> VgicpTarget:
        import small_gicp

        from blockloc.registration.ndt import NdtTarget

        parts = [np.asarray(p, dtype=np.float64)[:, :3] for p in tiles.values() if len(p)]
        if not parts:
            raise RegistrationError("VGICP target: no points")
        points = np.ascontiguousarray(np.concatenate(parts))
        cloud = small_gicp.PointCloud(points)
        small_gicp.estimate_covariances(cloud, num_neighbors=self.target_num_neighbors, num_threads=self.num_threads)
        shifts = np.outer(np.arange(self.voxel_grids) / self.voxel_grids, np.full(3, self.resolution_m))
        voxelmaps = []
        for shift in shifts:
            voxelmap = small_gicp.GaussianVoxelMap(self.resolution_m)
            voxelmap.insert(cloud, make_T(np.eye(3), -shift))  # covariances unchanged by a translation
            voxelmaps.append(voxelmap)
        scoring = NdtTarget.build(points, self.resolution_m, self.min_points_per_voxel, coarse_levels=0)
        return VgicpTarget(voxelmaps, shifts, scoring, dict(tiles), len(points))

    def update_tiles(self, target: VgicpTarget, add, remove) -> VgicpTarget:
        tiles = {k: v for k, v in target.tiles.items() if k not in set(remove)}
        tiles.update(add)
        return self.build_tiled_target(tiles)

    # ------------------------------------------------------------------ alignment
    def align(self, target: VgicpTarget, source_points: np.ndarray, T_init: np.ndarray | None = None) -> VgicpResult:
        import small_gicp

        src = np.ascontiguousarray(np.asarray(source_points, dtype=np.float64)[:, :3])
        if len(src) < 10 or not np.isfinite(src).all():
            raise RegistrationError(f"source points: {len(src)} points (finite, at least 10 expected)")
        T0 = np.eye(4) if T_init is None else np.asarray(T_init, dtype=np.float64)
        cloud = small_gicp.PointCloud(src)
        small_gicp.estimate_covariances(cloud, num_neighbors=self.num_neighbors, num_threads=self.num_threads)
        T, H, b, error, converged, iterations = self._align_grid(target, 0, cloud, T0)
        if self.voxel_grids > 1 and converged:
            # the other grids from the first's result; fused where they converged too
            found = [(T, H)]
            for k in range(1, len(target.voxelmaps)):
                Tk, Hk, _, _, ok, it = self._align_grid(target, k, cloud, T)
                iterations += it
                if ok and _near(T, Tk, 0.5 * self.resolution_m, _FUSE_MAX_ROT_RAD):
                    found.append((Tk, Hk))
            T, H = _fuse(found)
        ev = self.evaluate(target, src, T)
        lam, V = np.linalg.eigh(0.5 * (H + H.T))
        H = (V * np.maximum(lam, 0.0)) @ V.T  # PSD for GTSAM
        return VgicpResult(T, converged and ev.num_inliers > 0, iterations,
                           ev.num_inliers / len(src), int(ev.num_inliers), len(src), float(ev.score),
                           error, H, b)

    def _align_grid(self, target: VgicpTarget, k: int, cloud, T_map_source: np.ndarray):
        """small_gicp's VGICP on grid ``k`` from ``T_map_source``: (T_map_source (4, 4), H, b,
        error, converged, iterations), H and b in the tangent of ``T_map_source`` (a grid's
        offset is a translation on the left: the right-perturbation tangent is the same)."""
        import small_gicp

        to_grid, from_grid = make_T(np.eye(3), -target.shifts[k]), make_T(np.eye(3), target.shifts[k])
        kw = dict(max_correspondence_distance=self.max_correspondence_distance_m,
                  num_threads=self.num_threads, max_iterations=self.max_iterations)
        r = small_gicp.align(target.voxelmaps[k], cloud, to_grid @ T_map_source, **kw)
        iterations = int(r.iterations)
        if not r.converged and np.isfinite(np.asarray(r.T_target_source)).all():
            # Out of iterations on its way (a large correction, or correspondences switching
            # between voxels): go on from where it stopped once (as global init does with NDT); it stays
            # unconverged (and the tracker rejects the scan) if it still does not settle.
            r = small_gicp.align(target.voxelmaps[k], cloud, np.asarray(r.T_target_source, dtype=np.float64), **kw)
            iterations += int(r.iterations)
        T = from_grid @ np.asarray(r.T_target_source, dtype=np.float64)
        return (T, np.asarray(r.H, dtype=np.float64), np.asarray(r.b, dtype=np.float64).reshape(6),
                float(r.error), bool(r.converged), iterations)

    def evaluate(self, target: VgicpTarget, source_points: np.ndarray, T_target_source: np.ndarray):
        return self._scorer.evaluate(target.scoring, source_points, T_target_source, derivatives=False)


#: a grid's result farther than half a voxel or this rotation from the first grid's went to another
#: minimum (the grids see the same points), not to the first's from another side: left out
_FUSE_MAX_ROT_RAD = np.deg2rad(0.5)
#: directions of the summed Hessian below this ratio of its largest eigenvalue (rotation scaled to
#: metres by the residuals' lever arm) are kept at the first grid's pose: the tracker's own
#: weak-direction cut (NdtFactorParams.degeneracy_ratio), below which a mean is pulled by noise
_FUSE_MIN_RATIO = 1e-2


def _near(T_a: np.ndarray, T_b: np.ndarray, max_trans_m: float, max_rot_rad: float) -> bool:
    """Whether the poses (4, 4) differ by at most ``max_trans_m`` and ``max_rot_rad``."""
    D = np.linalg.inv(T_a) @ T_b
    return bool(np.linalg.norm(D[:3, 3]) <= max_trans_m and rotation_angle(D[:3, :3]) <= max_rot_rad)


def _fuse(found: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """The Hessian-weighted mean of poses [(T (4, 4), H (6, 6)), ...] in the tangent of the
    first (GTSAM's Pose3 tangent: rotation first, right perturbation), and the mean Hessian.

    Only along the directions the grids constrain together: the summed Hessian's eigen-directions
    at or above :data:`_FUSE_MIN_RATIO` of the largest, compared with rotation scaled to metres (as
    :func:`blockloc.tracking.factors.ndt_information` does). Along the others (a corridor's axis,
    where two grids' nearly flat Hessians differ by a little) the first grid's pose stays: there
    a pseudo-inverse would divide noise by a tiny eigenvalue and move the pose by metres."""

    T0 = found[0][0]
    H_sum = sum(H for _, H in found)
    g = np.zeros(6)
    for T, H in found[1:]:
        D = np.linalg.inv(T0) @ T
        g += H @ np.r_[so3_log(D[:3, :3]), D[:3, 3]]
    Hs = 0.5 * (H_sum + H_sum.T)
    d = lever_arm_scaling(Hs)  # xi = d * xi', H' = D H D, g' = D g
    lam, V = np.linalg.eigh(Hs * np.outer(d, d))
    keep = lam >= _FUSE_MIN_RATIO * lam.max() if lam.max() > 0 else np.zeros(6, bool)
    xi = d * ((V[:, keep] / lam[keep]) @ (V[:, keep].T @ (d * g)))
    step = np.eye(4)
    step[:3, :3] = so3_exp(xi[:3])
    step[:3, 3] = xi[3:]
    return T0 @ step, H_sum / len(found)
