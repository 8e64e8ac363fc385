"""Normal Distributions Transform (NDT) scan-to-map registration with a GTSAM-ready Hessian.

Target: voxel Gaussians (Magnusson 2009): per voxel of edge ``resolution`` the mean and the sample
covariance of its points, eigenvalues clamped to >= 0.01 x the largest (and an absolute floor), kept
only with >= ``min_points_per_voxel`` points. Voxel grid aligned at the origin.

Score (Magnusson eq. 6.9, as ndt_omp): for a source point mapped into the target, ``x = T p``, and
each neighbour Gaussian (mean mu, inverse covariance C) ``s = -d1 exp(-d2/2 (x-mu)^T C (x-mu))``
with d1, d2 from the outlier ratio and the resolution. ``score`` = sum of s (maximized).

Cost and derivatives (the GTSAM convention, as small_gicp's ``H``, ``b``): ``error = -score``
(minimized), ``b`` = gradient and ``H`` = exact Hessian of ``error(T * Exp(xi))`` at xi = 0, with
``xi = (omega, v)`` rotation first (GTSAM Pose3 tangent order, right perturbation, SE(3)
exponential). ``gtsam.HessianFactor(key, H, -b, 2 * error)`` then has error
``error + b.xi + xi^T H xi / 2``, the local quadratic model whose minimizer is the Newton step.
``H`` is the exact Hessian (not made PSD): near a good optimum it is positive definite; far from it,
or where the map is degenerate, it can have small or negative eigenvalues. ``NdtResult`` exposes its
eigen-decomposition, ``degenerate_directions()`` and ``information(min_eigenvalue)`` (the PSD
version with clamped eigenvalues) for building factors.

Newton iterations: the step solves ``H' d = -b`` where ``H'`` is ``H`` with its eigenvalues replaced
by their absolute values, floored at 1e-6 x the largest (a descent direction even where ``H`` is
indefinite), capped to ``max_step_m`` / ``max_step_rad``, then a backtracking line search
(Armijo, halving up to 8 times) on the score. This is simpler than More-Thuente and, with the exact
Hessian, takes the full Newton step near the optimum (quadratic convergence). Stops when the step
norm ``|alpha * d|`` (rad and m together) < ``step_epsilon`` or after ``max_iterations``.

Threading: an ``NdtTarget`` holds its search structure in an immutable snapshot replaced as a
whole by ``add_tile`` / ``remove_tile`` (which serialize on a lock and use serial kernels);
``NdtRegistration.align`` reads the snapshot once, so a background thread may update a target
while another thread aligns against it: each alignment sees either the old or the new map.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Hashable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from blockloc.errors import RegistrationError

log = logging.getLogger(__name__)

NEIGHBORS = {"DIRECT1": 1, "DIRECT7": 7, "DIRECT27": 27}
# 99% quantile of chi-square with 3 degrees of freedom: a point is an inlier when some neighbour
# Gaussian has (x-mu)^T C (x-mu) <= this (it lies within that Gaussian's 99% ellipsoid).
INLIER_MAHALANOBIS_SQ = 11.345
MIN_SOURCE_POINTS = 10


def _kernels():
    from blockloc.registration import _ndt_kernels

    return _ndt_kernels


# --------------------------------------------------------------------------------------------
# SE(3) helpers (GTSAM Pose3 Expmap convention: xi = (omega, v))


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """(6,) tangent (rotation rad, translation m) -> (4, 4), GTSAM ``Pose3.Expmap``."""
    w = np.asarray(xi[:3], dtype=np.float64)
    v = np.asarray(xi[3:], dtype=np.float64)
    theta2 = float(w @ w)
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    W2 = W @ W
    if theta2 < 1e-12:
        A, B, C = 1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0, 1.0 / 6.0 - theta2 / 120.0
    else:
        theta = np.sqrt(theta2)
        A = np.sin(theta) / theta
        B = (1.0 - np.cos(theta)) / theta2
        C = (theta - np.sin(theta)) / (theta2 * theta)
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + A * W + B * W2
    T[:3, 3] = (np.eye(3) + B * W + C * W2) @ v
    return T


def _orthonormalize(T: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    out = T.copy()
    out[:3, :3] = R
    return out


# --------------------------------------------------------------------------------------------
# Input checks


def _as_points(points: Any, what: str, min_points: int) -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise RegistrationError(f"{what}: expected an (N, 3) array of points, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise RegistrationError(f"{what}: expected numeric points, got dtype {arr.dtype}")
    xyz = np.ascontiguousarray(arr[:, :3], dtype=np.float64)
    if len(xyz) < min_points:
        raise RegistrationError(f"{what}: {len(xyz)} points, expected at least {min_points}")
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise RegistrationError(f"{what}: {int(bad.sum())} of {len(xyz)} points are NaN or inf")
    return xyz


def _check_resolution(resolution: float) -> float:
    r = float(resolution)
    if not np.isfinite(r) or r <= 0.0:
        raise RegistrationError(f"resolution {resolution!r}: expected a positive number of metres")
    return r


def _check_T(T: Any, what: str = "T_init") -> np.ndarray:
    if T is None:
        return np.eye(4)
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4) or not np.isfinite(arr).all():
        raise RegistrationError(f"{what}: expected a finite (4, 4) transform, got shape {arr.shape}")
    R = arr[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1.0) > 1e-3:
        raise RegistrationError(f"{what}: rotation block is not orthonormal")
    return _orthonormalize(arr)


# --------------------------------------------------------------------------------------------
# Target


@dataclass(frozen=True)
class _TileStats:
    """Per-tile voxel sums (relative to each voxel's centre) and the tile's own Gaussians."""

    keys: np.ndarray  # (V,) int64
    count: np.ndarray  # (V,) int64
    sums: np.ndarray  # (V, 3)
    outer: np.ndarray  # (V, 6)
    means: np.ndarray  # (V, 3)
    icov: np.ndarray  # (V, 6)
    valid: np.ndarray  # (V,) bool
    num_points: int


@dataclass(frozen=True)
class _Snapshot:
    """Immutable search structure: valid voxel Gaussians and a hash table over their keys."""

    keys: np.ndarray  # (M,) int64
    gauss: np.ndarray  # (M, 9) mean (3), inverse covariance (6)
    counts: np.ndarray  # (M,) int64
    table_keys: np.ndarray  # (S,) int64
    table_vals: np.ndarray  # (S,) int64
    shift: int
    num_points: int


class NdtTarget:
    """Voxel Gaussians of a target (map) point cloud, built once and reused for many scans.

    Build with ``NdtTarget.build(points)`` or ``NdtTarget.from_tiles({key: points})``; tiled
    targets are updated with ``add_tile`` / ``remove_tile`` without re-voxelizing other tiles
    (per-tile voxel sums are kept and combined where voxels coincide).
    """

    def __init__(self, resolution: float = 1.0, min_points_per_voxel: int = 6,
                 eigenvalue_ratio: float = 0.01):
        self.resolution = _check_resolution(resolution)
        if int(min_points_per_voxel) < 3:
            raise RegistrationError(
                f"min_points_per_voxel {min_points_per_voxel!r}: expected an integer >= 3")
        self.min_points_per_voxel = int(min_points_per_voxel)
        self.eigenvalue_ratio = float(eigenvalue_ratio)
        # Absolute eigenvalue floor (m^2) for voxels whose points are (nearly) all identical.
        self.eigenvalue_floor = 1e-6 * self.resolution**2
        self._tiles: dict[Hashable, _TileStats] = {}
        self._lock = threading.Lock()
        self._snapshot: _Snapshot | None = None

    # construction ---------------------------------------------------------------------------
    @classmethod
    def build(cls, points: np.ndarray, resolution: float = 1.0, min_points_per_voxel: int = 6,
              eigenvalue_ratio: float = 0.01) -> NdtTarget:
        """Target from one cloud. points: (N, 3) float, target/map frame, metres.

        The cloud is stored as the single tile with key ``None``.
        """
        target = cls(resolution, min_points_per_voxel, eigenvalue_ratio)
        xyz = _as_points(points, "target points", 1)
        target._tiles[None] = target._tile_stats(xyz, parallel=True)
        target._rebuild(parallel=True)
        return target

    @classmethod
    def from_tiles(cls, tiles: Mapping[Hashable, np.ndarray], resolution: float = 1.0,
                   min_points_per_voxel: int = 6, eigenvalue_ratio: float = 0.01) -> NdtTarget:
        """Target from tiles ``{key: (N, 3) points in the map frame}``; keys are any hashable."""
        target = cls(resolution, min_points_per_voxel, eigenvalue_ratio)
        for key, pts in tiles.items():
            xyz = _as_points(pts, f"tile {key!r}", 1)
            target._tiles[key] = target._tile_stats(xyz, parallel=True)
        target._rebuild(parallel=True)
        return target

    def add_tile(self, key: Hashable, points: np.ndarray) -> None:
        """Add (or replace) a tile; rebuilds only the combined search structure.

        Thread-safe with respect to concurrent ``align`` calls and other updates.
        """
        xyz = _as_points(points, f"tile {key!r}", 1)
        stats = self._tile_stats(xyz, parallel=False)
        with self._lock:
            self._tiles[key] = stats
            self._rebuild(parallel=False)

    def remove_tile(self, key: Hashable) -> None:
        """Remove a tile (KeyError-free: a missing key raises RegistrationError)."""
        with self._lock:
            if key not in self._tiles:
                raise RegistrationError(f"tile {key!r}: not in this target")
            del self._tiles[key]
            self._rebuild(parallel=False)

    @property
    def tile_keys(self) -> list:
        return list(self._tiles.keys())

    # queries --------------------------------------------------------------------------------
    @property
    def num_voxels(self) -> int:
        """Number of voxels with a valid Gaussian."""
        snap = self._snapshot
        return 0 if snap is None else len(snap.keys)

    @property
    def num_points(self) -> int:
        snap = self._snapshot
        return 0 if snap is None else snap.num_points

    def gaussians(self) -> tuple[np.ndarray, np.ndarray]:
        """Means (M, 3) and regularized covariances (M, 3, 3) of the valid voxels, map frame."""
        snap = self._require()
        icov = _sym3(snap.gauss[:, 3:])
        return snap.gauss[:, :3].copy(), np.linalg.inv(icov)

    def voxel_counts(self) -> np.ndarray:
        """(M,) number of points in each valid voxel (order of ``gaussians()``)."""
        return self._require().counts.copy()

    def snapshot(self) -> _Snapshot:
        """The current immutable search structure (what one alignment uses)."""
        return self._require()

    # internals ------------------------------------------------------------------------------
    def _require(self) -> _Snapshot:
        snap = self._snapshot
        if snap is None or len(snap.keys) == 0:
            raise RegistrationError(
                f"NDT target: no voxel has >= {self.min_points_per_voxel} points at resolution "
                f"{self.resolution} m (too few or too sparse target points)")
        return snap

    def _tile_stats(self, xyz: np.ndarray, parallel: bool) -> _TileStats:
        k = _kernels()
        keys, count, sums, outer, skipped = k.voxel_stats(xyz, 1.0 / self.resolution,
                                                           self.resolution)
        if skipped:
            raise RegistrationError(
                f"target points: {skipped} points beyond +-{2**20 * self.resolution:.0f} m of the "
                f"origin at resolution {self.resolution} m")
        fn = k.gaussians_parallel if parallel else k.gaussians_serial
        means, icov, valid = fn(keys, count, sums, outer, self.resolution,
                                self.min_points_per_voxel, self.eigenvalue_ratio,
                                self.eigenvalue_floor)
        return _TileStats(keys, count, sums, outer, means, icov, valid, len(xyz))

    def _rebuild(self, parallel: bool) -> None:
        k = _kernels()
        tiles = list(self._tiles.values())
        num_points = sum(t.num_points for t in tiles)
        if not tiles:
            keys = np.empty(0, np.int64)
            gauss = np.empty((0, 9))
            counts = np.empty(0, np.int64)
        elif len(tiles) == 1:
            t = tiles[0]
            sel = t.valid
            keys = t.keys[sel]
            gauss = np.hstack([t.means[sel], t.icov[sel]])
            counts = t.count[sel]
        else:
            all_keys = np.concatenate([t.keys for t in tiles])
            all_count = np.concatenate([t.count for t in tiles])
            all_sums = np.concatenate([t.sums for t in tiles])
            all_outer = np.concatenate([t.outer for t in tiles])
            all_means = np.concatenate([t.means for t in tiles])
            all_icov = np.concatenate([t.icov for t in tiles])
            all_valid = np.concatenate([t.valid for t in tiles])
            ukeys, ucount, usums, uouter, first, contributors = k.merge_stats(
                all_keys, all_count, all_sums, all_outer)
            means = all_means[first]
            icov = all_icov[first]
            valid = all_valid[first]
            shared = np.flatnonzero(contributors > 1)
            if len(shared):
                # Voxels that straddle tiles: Gaussians from the summed statistics.
                m2, c2, v2 = k.gaussians_serial(ukeys[shared], ucount[shared], usums[shared],
                                                uouter[shared], self.resolution,
                                                self.min_points_per_voxel,
                                                self.eigenvalue_ratio, self.eigenvalue_floor)
                means[shared] = m2
                icov[shared] = c2
                valid[shared] = v2
            keys = ukeys[valid]
            gauss = np.hstack([means[valid], icov[valid]])
            counts = ucount[valid]
        size, shift = k.table_size_for(len(keys))
        table_keys, table_vals = k.build_table(keys, size, shift)
        self._snapshot = _Snapshot(keys, np.ascontiguousarray(gauss), counts, table_keys,
                                   table_vals, shift, num_points)
        log.debug("NDT target: %d voxels from %d tiles, %d points", len(keys), len(tiles),
                  num_points)


def _sym3(six: np.ndarray) -> np.ndarray:
    """(M, 6) xx xy xz yy yz zz -> (M, 3, 3)."""
    out = np.empty(six.shape[:-1] + (3, 3))
    out[..., 0, 0] = six[..., 0]
    out[..., 0, 1] = out[..., 1, 0] = six[..., 1]
    out[..., 0, 2] = out[..., 2, 0] = six[..., 2]
    out[..., 1, 1] = six[..., 3]
    out[..., 1, 2] = out[..., 2, 1] = six[..., 4]
    out[..., 2, 2] = six[..., 5]
    return out


# --------------------------------------------------------------------------------------------
# Result


@dataclass
class NdtResult:
    """Outcome of one NDT alignment.

    T_target_source: (4, 4) maps source points into the target (map) frame.
    converged: the last step was below ``step_epsilon`` (False: stopped at max_iterations).
    iterations: Newton iterations taken.
    score: NDT score (sum over points and neighbour Gaussians of -d1 exp(-d2 q / 2), maximized).
    error: ``-score`` (the minimized cost whose derivatives are ``b`` and ``H``).
    num_inliers: source points with some neighbour Gaussian within its 99% ellipsoid
        ((x-mu)^T C (x-mu) <= 11.345, chi-square 3 dof); fitness = num_inliers / num_points.
    H: (6, 6), b: (6,) exact Hessian and gradient of ``error(T * Exp(xi))`` at the result,
        xi = (rotation, translation) as GTSAM Pose3; ``HessianFactor(key, H, -b, 2 * error)``.
    eigenvalues: (6,) ascending eigenvalues of H; eigenvectors: (6, 6) columns.
    """

    T_target_source: np.ndarray
    converged: bool
    iterations: int
    score: float
    error: float
    fitness: float
    num_inliers: int
    num_points: int
    H: np.ndarray
    b: np.ndarray
    eigenvalues: np.ndarray = field(repr=False)
    eigenvectors: np.ndarray = field(repr=False)

    def degenerate_directions(self, threshold: float = 0.01) -> np.ndarray:
        """Tangent directions (K, 6) whose H eigenvalue < threshold x the largest (weak axes).

        Rows are unit eigenvectors in GTSAM Pose3 order (rotation, translation). Rotation and
        translation have different units, so the ratio is a heuristic per map resolution.
        """
        lam = self.eigenvalues
        top = max(float(lam[-1]), 0.0)
        sel = lam < threshold * top
        return self.eigenvectors[:, sel].T.copy()

    def information(self, min_eigenvalue: float = 0.0) -> np.ndarray:
        """(6, 6) PSD version of H: eigenvalues clamped to >= min_eigenvalue (>= 0)."""
        lam = np.maximum(self.eigenvalues, max(min_eigenvalue, 0.0))
        V = self.eigenvectors
        return (V * lam) @ V.T


# --------------------------------------------------------------------------------------------
# Registration


def ndt_constants(resolution: float, outlier_ratio: float) -> tuple[float, float]:
    """d1, d2 of the Gaussian-plus-uniform fit (Magnusson 2009 eq. 6.8, as ndt_omp / PCL)."""
    c1 = 10.0 * (1.0 - outlier_ratio)
    c2 = outlier_ratio / resolution**3
    d3 = -np.log(c2)
    d1 = -np.log(c1 + c2) - d3
    d2 = -2.0 * np.log((-np.log(c1 * np.exp(-0.5) + c2) - d3) / d1)
    return float(d1), float(d2)


@dataclass
class _Eval:
    score: float
    num_inliers: int
    b: np.ndarray | None
    H: np.ndarray | None


class NdtRegistration:
    """NDT aligner: settings only; reuse one instance and one target for many scans."""

    def __init__(self, neighbors: str = "DIRECT7", outlier_ratio: float = 0.55,
                 max_iterations: int = 30, step_epsilon: float = 1e-3,
                 max_step_m: float | None = None, max_step_rad: float = 0.2,
                 num_threads: int | None = None):
        if neighbors not in NEIGHBORS:
            raise RegistrationError(
                f"neighbors {neighbors!r}: expected one of {', '.join(NEIGHBORS)}")
        if not 0.0 < float(outlier_ratio) < 1.0:
            raise RegistrationError(f"outlier_ratio {outlier_ratio!r}: expected 0 < value < 1")
        if int(max_iterations) < 1:
            raise RegistrationError(f"max_iterations {max_iterations!r}: expected >= 1")
        self.neighbors = neighbors
        self.outlier_ratio = float(outlier_ratio)
        self.max_iterations = int(max_iterations)
        self.step_epsilon = float(step_epsilon)
        self.max_step_m = None if max_step_m is None else float(max_step_m)
        self.max_step_rad = float(max_step_rad)
        self.num_threads = num_threads

    @classmethod
    def from_config(cls, cfg) -> NdtRegistration:
        """From a ``blockloc.config.RegistrationConfig``."""
        return cls(neighbors=cfg.neighbors, outlier_ratio=cfg.outlier_ratio,
                   max_iterations=cfg.max_iterations, step_epsilon=cfg.step_epsilon,
                   num_threads=cfg.num_threads)

    # ---------------------------------------------------------------------------------------
    def evaluate(self, target: NdtTarget, source_points: np.ndarray, T_target_source: np.ndarray,
                 derivatives: bool = True) -> _Eval:
        """Score, inliers and (optionally) b, H of the cost -score at a pose, no optimization."""
        snap = target._require()
        src = _as_points(source_points, "source points", 1)
        T = _check_T(T_target_source, "T_target_source")
        return self._eval(snap, target.resolution, src, T, derivatives)

    def _eval(self, snap: _Snapshot, resolution: float, src: np.ndarray, T: np.ndarray,
              derivatives: bool) -> _Eval:
        k = _kernels()
        d1, d2 = ndt_constants(resolution, self.outlier_ratio)
        R = np.ascontiguousarray(T[:3, :3])
        t = np.ascontiguousarray(T[:3, 3])
        nchunks = max(1, min(64, len(src) // 256))
        acc = k.ndt_kernel(src, R, t, snap.table_keys, snap.table_vals, snap.shift, snap.gauss,
                           1.0 / resolution, NEIGHBORS[self.neighbors], d1, d2,
                           INLIER_MAHALANOBIS_SQ, derivatives, nchunks).sum(axis=0)
        score = float(acc[0])
        inliers = int(round(acc[1]))
        if not derivatives:
            return _Eval(score, inliers, None, None)
        b_left = acc[2:8]
        H_left = np.zeros((6, 6))
        H_left[k.TRI_I, k.TRI_J] = acc[8:29]
        H_left = H_left + np.triu(H_left, 1).T
        # left frame (u = R p) -> right perturbation: J_right = J_left diag(R, R)
        Rb = np.zeros((6, 6))
        Rb[:3, :3] = R
        Rb[3:, 3:] = R
        b = Rb.T @ b_left
        H = Rb.T @ H_left @ Rb
        return _Eval(score, inliers, b, 0.5 * (H + H.T))

    def align(self, target: NdtTarget, source_points: np.ndarray,
              T_init: np.ndarray | None = None) -> NdtResult:
        """Register source points to the target.

        target: an ``NdtTarget`` (map frame). source_points: (N, 3) float, sensor frame, metres
        (downsample beforehand, e.g. a 0.5 m voxel grid; extra columns after xyz are ignored).
        T_init: (4, 4) initial ``T_target_source`` (identity if None).
        """
        snap = target._require()
        src = _as_points(source_points, "source points", MIN_SOURCE_POINTS)
        T = _check_T(T_init)
        if self.num_threads:
            import numba

            numba.set_num_threads(min(int(self.num_threads), numba.config.NUMBA_NUM_THREADS))
        res = target.resolution
        max_step_m = self.max_step_m if self.max_step_m is not None else res
        converged = False
        iterations = 0
        ev = self._eval(snap, res, src, T, True)
        while iterations < self.max_iterations:
            d = _descent_direction(ev.H, ev.b)
            # cap the step so one Newton step cannot leap across many voxels
            scale = 1.0
            nr = np.linalg.norm(d[:3])
            nt = np.linalg.norm(d[3:])
            if nr > self.max_step_rad:
                scale = min(scale, self.max_step_rad / nr)
            if nt > max_step_m:
                scale = min(scale, max_step_m / nt)
            d = d * scale
            slope = float(ev.b @ d)  # directional derivative of the cost (< 0)
            alpha = 1.0
            accepted = None
            for _ in range(9):
                T_try = T @ se3_exp(alpha * d)
                trial = self._eval(snap, res, src, T_try, False)
                if -trial.score <= -ev.score + 1e-4 * alpha * slope:
                    accepted = T_try
                    break
                alpha *= 0.5
            iterations += 1
            if accepted is None:
                # no decrease along a descent direction: at the optimum to numerical precision
                converged = bool(np.linalg.norm(d) < 10 * self.step_epsilon or abs(slope) < 1e-9)
                break
            T = _orthonormalize(accepted)
            ev = self._eval(snap, res, src, T, True)
            if np.linalg.norm(alpha * d) < self.step_epsilon:
                converged = True
                break
        lam, V = np.linalg.eigh(ev.H)
        return NdtResult(
            T_target_source=T, converged=converged, iterations=iterations, score=ev.score,
            error=-ev.score, fitness=ev.num_inliers / len(src), num_inliers=ev.num_inliers,
            num_points=len(src), H=ev.H, b=ev.b, eigenvalues=lam, eigenvectors=V)


def _descent_direction(H: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Newton direction with |eigenvalues| of H (floored), a descent direction for any H."""
    lam, V = np.linalg.eigh(H)
    mag = np.abs(lam)
    floor = max(1e-6 * float(mag.max()), 1e-12)
    mag = np.maximum(mag, floor)
    return -(V @ ((V.T @ b) / mag))


def align(target_points: np.ndarray, source_points: np.ndarray,
          T_init: np.ndarray | None = None, resolution: float = 1.0,
          **options: Any) -> NdtResult:
    """One-shot NDT: build a target from ``target_points`` and register ``source_points``.

    target_points: (N, 3) map/target frame; source_points: (M, 3) sensor frame; metres.
    T_init: (4, 4) initial ``T_target_source``. options: ``min_points_per_voxel`` and any
    ``NdtRegistration`` keyword (neighbors, outlier_ratio, max_iterations, step_epsilon, ...).
    """
    min_pts = options.pop("min_points_per_voxel", 6)
    target = NdtTarget.build(target_points, resolution=resolution, min_points_per_voxel=min_pts)
    reg = NdtRegistration(**options)
    return reg.align(target, source_points, T_init)
