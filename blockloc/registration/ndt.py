"""Normal Distributions Transform (NDT) scan-to-map registration with a GTSAM-ready Hessian.

Target: voxel Gaussians (Magnusson 2009): per voxel of edge ``resolution`` the mean and the sample
covariance of its points, eigenvalues clamped to >= 0.01 x the largest (and an absolute floor), kept
only with >= ``min_points_per_voxel`` points. Voxel grid aligned at the origin.

Score (Magnusson eq. 6.9, as ndt_omp): for a source point mapped into the target, ``x = T p``, and
each neighbour Gaussian (mean mu, inverse covariance C) ``s = -d1 exp(-d2/2 (x-mu)^T C (x-mu))``
with d1, d2 from the outlier ratio and the resolution. ``score`` = sum of s (maximized); pairs with
d2/2 (x-mu)^T C (x-mu) > 30 (weight < 1e-13) are skipped.

Cost and derivatives (the GTSAM convention, as small_gicp's ``H``, ``b``): ``error = -score``
(minimized; negative, which GTSAM accepts as the factor's constant term), ``b`` = gradient and
``H_exact`` = exact Hessian of ``error(T * Exp(xi))`` at xi = 0, with ``xi = (omega, v)``
rotation first (GTSAM Pose3 tangent order, right perturbation, SE(3) exponential, the chart of
``gtsam.Pose3.Expmap``). ``gtsam.HessianFactor(key, H, -b, 2 * error)`` then has error
``error + b.xi + xi^T H xi / 2``, the local quadratic model whose minimizer is the Newton step.
The exact Hessian (``NdtResult.H_exact``, tested against finite differences) is positive definite
near a good optimum; far from it, or where the map is degenerate, it can have small or negative
eigenvalues. ``NdtResult.H`` is its PSD projection (negative eigenvalues set to 0, so GTSAM never
sees an indefinite factor); ``eigenvalues``/``eigenvectors``, ``degenerate_directions()`` and
``information(min_eigenvalue)`` serve down-weighting weak directions.

Iterations (``step``): NDT's exact Hessian is indefinite far from the optimum (and, on real scans,
sometimes near it). The default ``step="newton"`` solves ``H d = -b`` with the exact Hessian where
it is positive definite and otherwise with the Gauss-Newton / IRLS matrix ``H_gn = sum a J^T C J``
(a = -d1 d2 exp(-d2 q / 2) > 0; always PSD, so ``d`` is a descent direction; a modified Newton
step with |eigenvalues| crawls there instead). ``step="gauss_newton"`` always uses ``H_gn`` and
evaluates the exact Hessian once at the end for the result (measured slightly slower: more
iterations). The step is capped to ``max_step_m`` / ``max_step_rad``, then a backtracking line
search (Armijo, halving up to 8 times; a Newton step under 10 x epsilon with a positive-definite
Hessian stops halving below epsilon: no decrease there is convergence) on the score: simpler
than More-Thuente and enough with descent directions of the right scale (measured: on the real HDL-32E pair, 100/100 random starts
within +-1 m, +-5 deg yaw, +-2 deg roll/pitch end within 5 cm / 0.5 deg with coarse-to-fine).
A level stops when the next step ``|d|`` (rad and m together) is below its epsilon, without
taking it (the pose then lies within about epsilon of the minimum of the quadratic model that b
and H at that pose describe, and the evaluation after the step is saved), or when the step just
taken is, or after ``max_iterations``.

Stages of ``align`` (defaults): each coarse level (DIRECT1 at 2 m on every k-th point, <= 1500
points, epsilon 10 x ``step_epsilon``), then the fine level: a DIRECT1 search (``search_neighbors``,
epsilon 10 x ``step_epsilon``; one Gaussian per point, so about half the cost of a DIRECT7 pass)
and the DIRECT7 polish (``neighbors``, ``step_epsilon``), whose evaluation at the result gives
score, b and H. On the real pair the polish ends at DIRECT7 alone's optimum (within 0.1 mm /
0.002 deg when both converge tightly, tests/registration); with the default epsilon a tight
DIRECT7 run from the result moves it by 0.3 mm / 0.005 deg (median over the bench's 60 starts;
at most about step_epsilon), far below the scan's error against the reference (about 2 cm /
0.13 deg).

Kernels (``_ndt_kernels``): an alignment makes one Python -> numba call, ``ndt_level``, per stage
(default: 3, coarse + search + polish), each running its stage's whole Newton loop; inside, every
iteration is one ``ndt_evaluate`` pass over the stage's points (plus one score-only pass per
line-search halving and a derivative pass after it, and a Gauss-Newton pass where the exact
Hessian is indefinite: after an indefinite one, exact and Gauss-Newton matrices come from the
same pass). Counted on the real pair (docs/bench/ndt.md): median 5 coarse (1.5k points), 2
search and 2 polish passes (10.8k points) from tracking starts, 10, 2 and 2 from wide starts
(the former DIRECT7-only fine level: 3). Passes of <= 2048 points run serially, larger ones in
parallel. The
source array is used in place (a C-contiguous float64 (N, 3) array is not copied; coarse levels
read it with a stride); per-point voxel look-ups are memoized per level for the alignment.

Threading: an ``NdtTarget`` holds its search structure in an immutable snapshot replaced as a
whole by ``add_tile`` / ``remove_tile`` (which serialize on a lock and use serial kernels that
release the GIL); ``NdtRegistration.align`` reads the snapshot once, so a background thread may
update a target while another thread aligns against it: each alignment sees either the old or
the new map, never a mix. ``NdtRegistration`` holds settings only and is shareable too.
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


_THREAD_CAP = threading.local()


def cap_threads(n: int | None) -> None:
    """Cap at ``n`` the numba threads of the calling thread's parallel kernels: its alignments
    (whatever ``NdtRegistration.num_threads`` asks) and every other kernel (numba's setting for
    the thread). None: no cap (numba's setting is left as it is).

    Why: workers that align side by side (``global_init``'s refinement threads) with every core
    each run more numba threads than there are cores, and a parallel region waits for its
    slowest, descheduled thread (docs/bench/ndt.md). A worker pool calls this in each thread."""
    _THREAD_CAP.n = None if n is None else max(1, int(n))
    _set_threads(_THREAD_CAP.n)


def _set_threads(num_threads: int | None) -> None:
    """numba's threads for the calling thread's next kernels: ``num_threads`` (None: as they are),
    at most the thread's cap (:func:`cap_threads`)."""
    cap = getattr(_THREAD_CAP, "n", None)
    n = num_threads if cap is None else min(num_threads or cap, cap)
    if n:
        import numba

        numba.set_num_threads(min(int(n), numba.config.NUMBA_NUM_THREADS))


# --------------------------------------------------------------------------------------------
# SE(3) helpers (GTSAM Pose3 Expmap convention: xi = (omega, v))


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """(6,) tangent (rotation rad, translation m) -> (4, 4), GTSAM ``Pose3.Expmap``."""
    xi = np.ascontiguousarray(xi, dtype=np.float64)
    if xi.shape != (6,):
        raise RegistrationError(f"se3_exp: expected a (6,) tangent vector, got shape {xi.shape}")
    return _kernels().se3_exp(xi)


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
        raise RegistrationError(
            f"{what}: expected an (N, 3) array of points, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise RegistrationError(f"{what}: expected numeric points, got dtype {arr.dtype}")
    xyz = np.ascontiguousarray(arr[:, :3], dtype=np.float64)
    if len(xyz) < min_points:
        raise RegistrationError(f"{what}: {len(xyz)} points, expected at least {min_points}")
    if not np.isfinite(xyz).all():  # one flat reduction; the per-row count only on failure
        bad = ~np.isfinite(xyz).all(axis=1)
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
        raise RegistrationError(
            f"{what}: expected a finite (4, 4) transform, got shape {arr.shape}")
    R = arr[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1.0) > 1e-3:
        raise RegistrationError(f"{what}: rotation block is not orthonormal")
    return _orthonormalize(arr)


# --------------------------------------------------------------------------------------------
# Target


@dataclass(frozen=True)
class _LevelStats:
    """One tile at one resolution: voxel sums (relative to each voxel's centre) and the tile's
    own Gaussians (reused as they are for voxels no other tile touches)."""

    keys: np.ndarray  # (V,) int64
    count: np.ndarray  # (V,) int64
    sums: np.ndarray  # (V, 3)
    outer: np.ndarray  # (V, 6)
    means: np.ndarray  # (V, 3)
    icov: np.ndarray  # (V, 6)
    valid: np.ndarray  # (V,) bool


@dataclass(frozen=True)
class _TileStats:
    levels: tuple[_LevelStats, ...]  # finest first, resolution doubling per level
    num_points: int

    def select_columns(self, lo: np.ndarray, hi: np.ndarray) -> _TileStats:
        """The voxels whose finest-level column (ix, iy) lies in [lo, hi) ((2,) int each, finest
        voxel indices, multiples of 2**coarse_levels so that every coarse voxel is kept whole or
        dropped whole): statistics and Gaussians as they are, ``num_points`` their points."""
        lo = np.asarray(lo, np.int64).reshape(2)
        hi = np.asarray(hi, np.int64).reshape(2)
        if np.any(lo % (1 << (len(self.levels) - 1))) or np.any(hi % (1 << (len(self.levels) - 1))):
            raise RegistrationError(f"voxel columns [{lo}, {hi}): expected multiples of "
                                    f"{1 << (len(self.levels) - 1)} (whole coarse voxels)")
        levels = []
        for level, lv in enumerate(self.levels):
            ijk = _kernels().unpack_keys(lv.keys)
            a, b = lo >> level, hi >> level
            keep = np.flatnonzero((ijk[:, 0] >= a[0]) & (ijk[:, 0] < b[0])
                                  & (ijk[:, 1] >= a[1]) & (ijk[:, 1] < b[1]))
            # rows by index, found once for the seven arrays (a boolean mask is counted again for
            # each: ~4x slower)
            levels.append(_LevelStats(*(np.take(getattr(lv, f), keep, axis=0) for f in _LEVEL_FIELDS)))
        return _TileStats(tuple(levels), int(levels[0].count.sum()) if levels else 0)

    @property
    def nbytes(self) -> int:
        return sum(getattr(lv, f).nbytes for lv in self.levels for f in _LEVEL_FIELDS)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The statistics as named arrays (``l<level>_<field>``), for ``np.savez``; read back by
        :meth:`from_arrays`."""
        return {f"l{level}_{f}": getattr(lv, f) for level, lv in enumerate(self.levels) for f in _LEVEL_FIELDS}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], num_levels: int) -> _TileStats:
        """The statistics :meth:`to_arrays` gave, checked: ``num_levels`` levels (the target's
        ``coarse_levels + 1``), each field's rows and columns as the tile statistics have them.
        Raises ValueError (or KeyError for a missing array) on anything else."""
        levels = []
        for level in range(int(num_levels)):
            lv = _LevelStats(*(np.asarray(arrays[f"l{level}_{f}"]) for f in _LEVEL_FIELDS))
            n = len(lv.keys)
            for f, cols, kind in _LEVEL_SHAPES:
                a = getattr(lv, f)
                if a.dtype.kind != kind or len(a) != n or a.shape[1:] != cols:
                    raise ValueError(f"level {level} {f}: {a.dtype} {a.shape}, expected {n} rows of {cols} ({kind})")
            levels.append(lv)
        if f"l{int(num_levels)}_keys" in arrays:
            raise ValueError(f"more than {num_levels} levels")
        return cls(tuple(levels), int(levels[0].count.sum()) if levels else 0)


_LEVEL_FIELDS = ("keys", "count", "sums", "outer", "means", "icov", "valid")
# (field, shape after the rows, dtype kind) of a level's arrays
_LEVEL_SHAPES = (("keys", (), "i"), ("count", (), "i"), ("sums", (3,), "f"), ("outer", (6,), "f"),
                 ("means", (3,), "f"), ("icov", (6,), "f"), ("valid", (), "b"))


#: The voxel statistics of one tile at every level (``NdtTarget.tile_stats``).
TileStats = _TileStats


@dataclass(frozen=True)
class _Snapshot:
    """Immutable search structure of one level: valid voxel Gaussians and a hash table."""

    resolution: float
    keys: np.ndarray  # (M,) int64
    gauss: np.ndarray  # (M, 9) mean (3), inverse covariance (6: xx xy xz yy yz zz)
    counts: np.ndarray  # (M,) int64
    table_keys: np.ndarray  # (S,) int64
    table_vals: np.ndarray  # (S,) int64
    shift: int
    num_points: int
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def neighbor_table(self) -> tuple:
        """DIRECT1/7 neighbour lists (built on first use, then cached; immutable afterwards).

        Two threads racing here both build the same table; either result is kept.
        """
        table = self._cache.get("nbr7")
        if table is None:
            _, ntk, ntv, nshift, nbr = _kernels().build_neighbor_table(
                self.keys, self.table_keys, self.table_vals, self.shift)
            table = (ntk, ntv, nshift, nbr)
            self._cache["nbr7"] = table
        return table

    def kernel_level(self) -> tuple:
        """This level as the ``level`` tuple of the alignment kernels (see ``ndt_evaluate``)."""
        level = self._cache.get("level")
        if level is None:
            ntk, ntv, nshift, nbr = self.neighbor_table()
            level = (self.table_keys, self.table_vals, self.shift, self.gauss,
                     1.0 / self.resolution, ntk, ntv, nshift, nbr)
            self._cache["level"] = level
        return level


class NdtTarget:
    """Voxel Gaussians of a target (map) point cloud, built once and reused for many scans.

    Build with ``NdtTarget.build(points)`` or ``NdtTarget.from_tiles({key: points})``; tiled
    targets are updated with ``add_tile`` / ``remove_tile`` without re-voxelizing other tiles
    (per-tile voxel sums are kept and combined where voxels coincide, so a voxel cut by a tile
    edge gets the Gaussian of all its points).

    ``coarse_levels`` extra grids at 2x, 4x, ... the resolution are derived from the fine voxel
    sums (no second pass over the points); ``NdtRegistration`` aligns coarse-to-fine, which
    widens the basin of convergence (on the real HDL-32E pair, +-1 m / +-5 deg starts: 100/100
    with one coarse level against about 90/100 without).
    """

    def __init__(self, resolution: float = 1.0, min_points_per_voxel: int = 6,
                 eigenvalue_ratio: float = 0.01, coarse_levels: int = 1):
        self.resolution = _check_resolution(resolution)
        if int(min_points_per_voxel) < 3:
            raise RegistrationError(
                f"min_points_per_voxel {min_points_per_voxel!r}: expected an integer >= 3")
        if not 0 <= int(coarse_levels) <= 4:
            raise RegistrationError(f"coarse_levels {coarse_levels!r}: expected 0 to 4")
        self.min_points_per_voxel = int(min_points_per_voxel)
        self.eigenvalue_ratio = float(eigenvalue_ratio)
        self.coarse_levels = int(coarse_levels)
        self._tiles: dict[Hashable, _TileStats] = {}
        self._lock = threading.Lock()
        self._levels: tuple[_Snapshot, ...] = ()

    # construction ---------------------------------------------------------------------------
    @classmethod
    def build(cls, points: np.ndarray, resolution: float = 1.0, min_points_per_voxel: int = 6,
              eigenvalue_ratio: float = 0.01, coarse_levels: int = 1) -> NdtTarget:
        """Target from one cloud. points: (N, 3) float, target/map frame, metres.

        The cloud is stored as the single tile with key ``None``.
        """
        target = cls(resolution, min_points_per_voxel, eigenvalue_ratio, coarse_levels)
        xyz = _as_points(points, "target points", 1)
        target._tiles[None] = target._tile_stats(xyz)
        target._rebuild()
        return target

    @classmethod
    def from_tiles(cls, tiles: Mapping[Hashable, np.ndarray], resolution: float = 1.0,
                   min_points_per_voxel: int = 6, eigenvalue_ratio: float = 0.01,
                   coarse_levels: int = 1) -> NdtTarget:
        """Target from tiles ``{key: (N, 3) points in the map frame}``; keys are any hashable."""
        target = cls(resolution, min_points_per_voxel, eigenvalue_ratio, coarse_levels)
        for key, pts in tiles.items():
            xyz = _as_points(pts, f"tile {key!r}", 1)
            target._tiles[key] = target._tile_stats(xyz)
        target._rebuild()
        return target

    @classmethod
    def from_tile_stats(cls, tiles: Mapping[Hashable, _TileStats], resolution: float = 1.0,
                        min_points_per_voxel: int = 6, eigenvalue_ratio: float = 0.01,
                        coarse_levels: int = 1) -> NdtTarget:
        """Target from tiles' statistics (``tile_stats`` of a target with the same settings, or
        ``TileStats.select`` of them): the voxels that several tiles share get the Gaussian of their
        summed statistics, as ``from_tiles`` does; nothing is voxelized again."""
        target = cls(resolution, min_points_per_voxel, eigenvalue_ratio, coarse_levels)
        for key, stats in tiles.items():
            if len(stats.levels) != target.coarse_levels + 1:
                raise RegistrationError(f"tile {key!r}: {len(stats.levels)} levels, expected "
                                        f"{target.coarse_levels + 1}")
            target._tiles[key] = stats
        target._rebuild()
        return target

    def tile_stats(self, points: np.ndarray) -> _TileStats:
        """The voxel statistics of points (N, 3), map frame, metres, at this target's settings
        (every level), for ``from_tile_stats``."""
        return self._tile_stats(_as_points(points, "tile points", 1))

    def add_tile(self, key: Hashable, points: np.ndarray) -> None:
        """Add (or replace) a tile: voxelizes only its points, then swaps in a new search
        structure. Safe to call from a background thread while other threads align."""
        xyz = _as_points(points, f"tile {key!r}", 1)
        stats = self._tile_stats(xyz)
        with self._lock:
            self._tiles[key] = stats
            self._rebuild()

    def remove_tile(self, key: Hashable) -> None:
        """Remove a tile (a key not in the target raises RegistrationError)."""
        with self._lock:
            if key not in self._tiles:
                raise RegistrationError(f"tile {key!r}: not in this target")
            del self._tiles[key]
            self._rebuild()

    @property
    def tile_keys(self) -> list:
        return list(self._tiles.keys())

    # queries --------------------------------------------------------------------------------
    @property
    def num_voxels(self) -> int:
        """Number of voxels with a valid Gaussian at the finest level."""
        levels = self._levels
        return len(levels[0].keys) if levels else 0

    @property
    def num_points(self) -> int:
        levels = self._levels
        return levels[0].num_points if levels else 0

    def gaussians(self, level: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Means (M, 3) and regularized covariances (M, 3, 3) of the valid voxels, map frame."""
        snap = self.snapshot(level)
        icov = _sym3(snap.gauss[:, 3:])
        return snap.gauss[:, :3].copy(), np.linalg.inv(icov)

    def voxel_counts(self, level: int = 0) -> np.ndarray:
        """(M,) number of points in each valid voxel (order of ``gaussians()``)."""
        return self.snapshot(level).counts.copy()

    def snapshot(self, level: int = 0) -> _Snapshot:
        """The current immutable search structure of a level (0: finest)."""
        return self.levels()[level]

    def levels(self) -> tuple[_Snapshot, ...]:
        """All levels' current snapshots, finest first (one consistent set)."""
        levels = self._levels
        if not levels or len(levels[0].keys) == 0:
            raise RegistrationError(
                f"NDT target: no voxel has >= {self.min_points_per_voxel} points at resolution "
                f"{self.resolution} m (too few or too sparse target points)")
        return levels

    # internals ------------------------------------------------------------------------------
    def _level_gaussians(self, keys, count, sums, outer, res):
        # Serial on purpose: ~0.5 us per voxel, and a parallel region stalls badly when the
        # cores are shared (measured: slower than serial under load).
        return _kernels().gaussians_serial(keys, count, sums, outer, res,
                                           self.min_points_per_voxel, self.eigenvalue_ratio,
                                           1e-6 * res**2)  # absolute floor (m^2)

    def _tile_stats(self, xyz: np.ndarray) -> _TileStats:
        k = _kernels()
        res = self.resolution
        keys, count, sums, outer, skipped = k.voxel_stats(xyz, 1.0 / res, res)
        if skipped:
            raise RegistrationError(
                f"target points: {skipped} points beyond +-{2**20 * res:.0f} m of the "
                f"origin at resolution {res} m")
        levels = []
        for level in range(self.coarse_levels + 1):
            if level:
                pkeys, psums, pouter = k.coarsen_stats(keys, count, sums, outer, res)
                keys, count, sums, outer, _, _ = k.merge_stats(pkeys, count, psums, pouter)
                res = 2.0 * res
            means, icov, valid = self._level_gaussians(keys, count, sums, outer, res)
            levels.append(_LevelStats(keys, count, sums, outer, means, icov, valid))
        return _TileStats(tuple(levels), len(xyz))

    def _rebuild(self) -> None:
        tiles = list(self._tiles.values())
        num_points = sum(t.num_points for t in tiles)
        levels = tuple(
            self._combine([t.levels[level] for t in tiles], self.resolution * 2**level,
                          num_points)
            for level in range(self.coarse_levels + 1))
        # neighbour lists now (in the updating thread), not in the first align
        for snap in levels:
            snap.kernel_level()
        self._levels = levels
        log.debug("NDT target: %d voxels from %d tiles, %d points", self.num_voxels,
                  len(tiles), num_points)

    def _combine(self, parts: list[_LevelStats], res: float, num_points: int) -> _Snapshot:
        k = _kernels()
        if not parts:
            keys = np.empty(0, np.int64)
            gauss = np.empty((0, 9))
            counts = np.empty(0, np.int64)
        elif len(parts) == 1:
            t = parts[0]
            sel = np.flatnonzero(t.valid)  # rows by index: found once, not once per array
            keys = np.take(t.keys, sel)
            gauss = np.hstack([np.take(t.means, sel, axis=0), np.take(t.icov, sel, axis=0)])
            counts = np.take(t.count, sel)
        else:
            ukeys, ucount, usums, uouter, first, contributors = k.merge_stats(
                np.concatenate([t.keys for t in parts]), np.concatenate([t.count for t in parts]),
                np.concatenate([t.sums for t in parts]), np.concatenate([t.outer for t in parts]))
            means = np.concatenate([t.means for t in parts])[first]
            icov = np.concatenate([t.icov for t in parts])[first]
            valid = np.concatenate([t.valid for t in parts])[first]
            shared = np.flatnonzero(contributors > 1)
            if len(shared):
                # Voxels cut by tile edges: Gaussians from the summed statistics.
                m2, c2, v2 = self._level_gaussians(ukeys[shared], ucount[shared], usums[shared],
                                                   uouter[shared], res)
                means[shared] = m2
                icov[shared] = c2
                valid[shared] = v2
            sel = np.flatnonzero(valid)
            keys = np.take(ukeys, sel)
            gauss = np.hstack([np.take(means, sel, axis=0), np.take(icov, sel, axis=0)])
            counts = np.take(ucount, sel)
        size, shift = k.table_size_for(len(keys))
        table_keys, table_vals = k.build_table(keys, size, shift)
        return _Snapshot(res, keys, np.ascontiguousarray(gauss), counts, table_keys, table_vals,
                         shift, num_points)


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
    converged: the next (or the last) step was below ``step_epsilon`` (False: stopped at
        max_iterations, or no source point matched any Gaussian).
    iterations: Newton iterations on the finest level (search and polish); coarse_iterations:
        on coarser levels. passes: passes of the kernels over the source points, all levels.
    score: NDT score (sum over points and neighbour Gaussians of -d1 exp(-d2 q / 2), maximized).
    error: ``-score`` (the minimized cost whose derivatives are ``b`` and ``H``).
    num_inliers: source points with some neighbour Gaussian within its 99% ellipsoid
        ((x-mu)^T C (x-mu) <= 11.345, chi-square 3 dof); fitness = num_inliers / num_points.
    b: (6,) gradient of ``error(T * Exp(xi))`` at xi = 0, xi = (rotation, translation) as GTSAM
        Pose3 (right perturbation). H_exact: (6, 6) its exact Hessian. H: ``H_exact`` with
        negative eigenvalues set to 0 (PSD; equal to ``H_exact`` whenever that is PSD, as at a
        converged optimum), for ``gtsam.HessianFactor(key, H, -b, 2 * error)``.
    eigenvalues: (6,) ascending eigenvalues of ``H_exact`` (negative: a non-converged or
        ill-posed result); eigenvectors: (6, 6) matching unit columns.
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
    H_exact: np.ndarray = field(repr=False, default=None)
    coarse_iterations: int = 0
    passes: int = 0

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
        """(6, 6) ``H_exact`` with eigenvalues clamped to >= min_eigenvalue (>= 0): with a
        positive floor, a full-rank information matrix for a prior-style factor."""
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
class NdtEvaluation:
    """Score, inlier count and (when asked) gradient ``b`` (6,) and Hessian ``H`` (6, 6) of
    ``error = -score`` at one pose, conventions as ``NdtResult`` (H exact, not projected)."""

    score: float
    num_inliers: int
    b: np.ndarray | None
    H: np.ndarray | None


class NdtRegistration:
    """NDT aligner: settings only; reuse one instance and one target for many scans.

    neighbors: DIRECT1 | DIRECT7 | DIRECT27, the voxel containing the transformed point, plus its 6
    face neighbours, plus all 26 neighbours: the objective of the finest level, whose score, H and
    b the result reports. search_neighbors (default DIRECT1; None or equal to ``neighbors``: no
    search stage): the finest level first iterates with these (cheaper) neighbours to 10 x
    ``step_epsilon``, then polishes with ``neighbors``; the iteration counts of both share
    ``max_iterations``. coarse_to_fine: when the target has coarse levels, first align on them
    (``coarse_neighbors``, stopping at 10 x ``step_epsilon``, with every k-th source point so
    that at most about ``coarse_max_points`` are used). step: "newton" (default) or
    "gauss_newton", see the module doc. step_epsilon: stop when the next step (rad and m
    together) is shorter. max_step_m (default: the level's resolution) and max_step_rad cap
    one step. num_threads: numba threads of the alignment kernels, set for the calling thread
    (None: numba's current setting; at most the thread's :func:`cap_threads`). On cores shared
    with other busy processes or threads, 1 thread has a much better median latency than 2 (a
    parallel region waits for its slowest, descheduled worker): see docs/bench/ndt.md. Source
    points in scan order (spatially coherent) run faster than shuffled ones.

    ``stage_observer`` (None, or a callable set after construction): told every kernel stage an
    alignment runs, ``(neighbors, resolution_m, stride, passes)`` (passes: (iterations,) array of
    the kernel's passes over the points); for measurement (``python -m bench ndt``).
    """

    stage_observer = None

    def __init__(self, neighbors: str = "DIRECT7", outlier_ratio: float = 0.55,
                 max_iterations: int = 30, step_epsilon: float = 1e-3,
                 coarse_to_fine: bool = True, coarse_neighbors: str = "DIRECT1",
                 coarse_max_points: int = 1500, step: str = "newton",
                 max_step_m: float | None = None, max_step_rad: float = 0.2,
                 num_threads: int | None = None, search_neighbors: str | None = "DIRECT1"):
        for name, value in (("neighbors", neighbors), ("coarse_neighbors", coarse_neighbors),
                            ("search_neighbors", search_neighbors or neighbors)):
            if value not in NEIGHBORS:
                raise RegistrationError(
                    f"{name} {value!r}: expected one of {', '.join(NEIGHBORS)}")
        if not 0.0 < float(outlier_ratio) < 1.0:
            raise RegistrationError(f"outlier_ratio {outlier_ratio!r}: expected 0 < value < 1")
        if int(max_iterations) < 1:
            raise RegistrationError(f"max_iterations {max_iterations!r}: expected >= 1")
        if not float(step_epsilon) > 0.0:
            raise RegistrationError(f"step_epsilon {step_epsilon!r}: expected > 0")
        self.neighbors = neighbors
        self.search_neighbors = search_neighbors
        self.coarse_neighbors = coarse_neighbors
        self.outlier_ratio = float(outlier_ratio)
        self.max_iterations = int(max_iterations)
        self.step_epsilon = float(step_epsilon)
        self.coarse_to_fine = bool(coarse_to_fine)
        if step not in ("newton", "gauss_newton"):
            raise RegistrationError(f"step {step!r}: expected 'newton' or 'gauss_newton'")
        self.step = step
        self.coarse_max_points = max(int(coarse_max_points), MIN_SOURCE_POINTS)
        self.max_step_m = None if max_step_m is None else float(max_step_m)
        self.max_step_rad = float(max_step_rad)
        self.num_threads = num_threads

    # ---------------------------------------------------------------------------------------
    def evaluate(self, target: NdtTarget, source_points: np.ndarray, T_target_source: np.ndarray,
                 derivatives: bool = True) -> NdtEvaluation:
        """Score, inliers and (optionally) b, H of the cost -score at a pose (finest level,
        ``neighbors``), without optimizing. Same conventions as ``NdtResult``."""
        snap = target.snapshot(0)
        src = _as_points(source_points, "source points", 1)
        T = _check_T(T_target_source, "T_target_source")
        return self._eval(snap, NEIGHBORS[self.neighbors], src, T, derivatives)

    def inliers_per_group(self, target: NdtTarget, source_points: np.ndarray, starts: np.ndarray,
                          T_target_source: np.ndarray) -> np.ndarray:
        """(G,) int64: for each group g of source_points[starts[g]:starts[g + 1]] (points (N, 3),
        ``starts`` (G + 1,) ascending from 0 to N), the inliers :meth:`evaluate` counts over that
        group alone at the pose (finest level), in one kernel call (no Python per group)."""
        snap = target.snapshot(0)
        src = _as_points(source_points, "source points", 0)
        T = _check_T(T_target_source, "T_target_source")
        st = np.ascontiguousarray(starts, dtype=np.int64)
        if st.ndim != 1 or len(st) < 1 or st[0] != 0 or st[-1] != len(src) or np.any(np.diff(st) < 0):
            raise RegistrationError(f"starts: expected ascending offsets from 0 to {len(src)}")
        d1, d2 = ndt_constants(snap.resolution, self.outlier_ratio)
        key_cache, row_cache = _new_memo(len(src))
        return _kernels().ndt_inliers_per_group(src, st, T, snap.kernel_level(), NEIGHBORS[self.neighbors], d1, d2,
                                                INLIER_MAHALANOBIS_SQ, key_cache, row_cache)

    def _eval(self, snap: _Snapshot, neighbors: int, src: np.ndarray, T: np.ndarray,
              derivatives: bool, gauss_newton: bool = False,
              memo: tuple | None = None) -> NdtEvaluation:
        k = _kernels()
        d1, d2 = ndt_constants(snap.resolution, self.outlier_ratio)
        mode = (k.MODE_SCORE if not derivatives
                else (k.MODE_GN if gauss_newton else k.MODE_EXACT))
        if memo is None:
            memo = _new_memo(len(src))
        acc = k.ndt_evaluate(src, 1, T, snap.kernel_level(), neighbors, d1, d2,
                             INLIER_MAHALANOBIS_SQ, mode, memo[0], memo[1])
        score = float(acc[0])
        inliers = int(round(acc[1]))
        if not derivatives:
            return NdtEvaluation(score, inliers, None, None)
        b = np.empty(6)
        H = np.empty((6, 6))
        Hgn = np.empty((6, 6))
        k.right_derivatives(acc, T, b, H, Hgn)
        return NdtEvaluation(score, inliers, b, Hgn if gauss_newton else H)

    def _level(self, snap: _Snapshot, neighbors: str, src: np.ndarray, stride: int,
               T: np.ndarray, epsilon: float, max_iterations: int, memo: tuple,
               first_both: bool, max_first_step: float = np.inf):
        """One ``ndt_level`` kernel call: (T, acc, b, H, iterations, converged, passes)."""
        k = _kernels()
        d1, d2 = ndt_constants(snap.resolution, self.outlier_ratio)
        max_step_m = self.max_step_m if self.max_step_m is not None else snap.resolution
        out = k.ndt_level(src, stride, T, snap.kernel_level(), NEIGHBORS[neighbors], d1, d2,
                          INLIER_MAHALANOBIS_SQ, memo[0], memo[1], max_iterations, epsilon,
                          max_step_m, self.max_step_rad,
                          self.step == "gauss_newton",
                          k.MODE_BOTH if first_both else k.MODE_EXACT, max_first_step)
        if self.stage_observer is not None:
            self.stage_observer(neighbors, float(snap.resolution), int(stride), out[6])
        return out

    def align(self, target: NdtTarget, source_points: np.ndarray,
              T_init: np.ndarray | None = None) -> NdtResult:
        """Register source points to the target.

        target: an ``NdtTarget`` (map frame). source_points: (N, 3) float, sensor frame, metres
        (downsample beforehand, e.g. a 0.5 m voxel grid; extra columns after xyz are ignored;
        a C-contiguous float64 (N, 3) array is used without a copy).
        T_init: (4, 4) initial ``T_target_source`` (identity if None).
        """
        levels = target.levels()  # one consistent set even if a tile update swaps them now
        src = _as_points(source_points, "source points", MIN_SOURCE_POINTS)
        T = _check_T(T_init)
        _set_threads(self.num_threads)
        coarse_iterations = 0
        passes = 0
        if self.coarse_to_fine and len(levels) > 1:
            # the coarse levels only bring T into the fine basin: a subset of the points will do
            stride = max(1, len(src) // self.coarse_max_points)
            coarse_memo = _new_memo(len(src))
            for snap in reversed(levels[1:]):
                if len(snap.keys) == 0:
                    continue
                coarse_memo[0][:] = -1
                T, _, _, _, it, _, p = self._level(snap, self.coarse_neighbors, src, stride, T,
                                                   10.0 * self.step_epsilon, self.max_iterations,
                                                   coarse_memo, True)
                coarse_iterations += it
                passes += p
        fine = levels[0]
        memo = _new_memo(len(src))  # per-point voxel rows, shared by search and polish
        iterations = 0
        if self.search_neighbors not in (None, self.neighbors):
            T, _, _, _, iterations, _, p = self._level(fine, self.search_neighbors, src, 1, T,
                                                       10.0 * self.step_epsilon,
                                                       self.max_iterations, memo, False)
            passes += p
        T, acc, b, H, it, converged, p = self._level(fine, self.neighbors, src, 1, T,
                                                     self.step_epsilon,
                                                     self.max_iterations - iterations, memo,
                                                     False)
        iterations += it
        passes += p
        return self._result(fine, src, T, acc, b, H, iterations, converged, coarse_iterations, passes, memo)

    def align_from_prediction(self, target: NdtTarget, source_points: np.ndarray, T_pred: np.ndarray,
                              max_first_step: float = 0.03, max_iterations: int = 6) -> NdtResult:
        """Register from a prediction that is usually already close (a tracker's, from the IMU or
        a motion model): when the fine level's (``neighbors``) first Newton step from ``T_pred``
        is shorter than ``max_first_step`` (rad and m together, as ``step_epsilon``), the fine
        level alone iterates from there (at most ``max_iterations``); when it does not converge
        within them (or within a quarter of the resolution of ``T_pred``), or the first step is
        longer, :meth:`align` runs its stages from ``T_pred`` (the passes spent are counted,
        one when the first step decided).

        Arguments and result as :meth:`align`. Why: from such a start the coarse and search
        stages only repeat what the fine level does alone (measured on the small world, seed 2,
        150 scans: 7.2 passes over the points with them, 3.1 without, the same optimum within
        1.4 mm median); from a start 10 cm off (the real HDL-32E pair) the fine level alone
        needs 4-7 iterations, and its first step there is 3-10 cm long.
        """
        levels = target.levels()
        src = _as_points(source_points, "source points", MIN_SOURCE_POINTS)
        T0 = _check_T(T_pred, "T_pred")
        fine = levels[0]
        if len(fine.keys) == 0:
            return self.align(target, src, T0)
        _set_threads(self.num_threads)
        memo = _new_memo(len(src))
        T, acc, b, H, it, converged, passes = self._level(
            fine, self.neighbors, src, 1, T0, self.step_epsilon, min(int(max_iterations), self.max_iterations),
            memo, False, max_first_step)
        moved_m = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
        if not (converged and acc[1] > 0 and moved_m <= 0.25 * fine.resolution):
            res = self.align(target, src, T0)
            res.passes += passes
            return res
        return self._result(fine, src, T, acc, b, H, it, converged, 0, passes, memo)

    def _result(self, fine: _Snapshot, src: np.ndarray, T: np.ndarray, acc, b, H, iterations: int,
                converged: bool, coarse_iterations: int, passes: int, memo: tuple) -> NdtResult:
        """The NdtResult of a fine level's outcome (``ndt_level``'s T, acc, b, H)."""
        ev = NdtEvaluation(float(acc[0]), int(round(acc[1])), b, H)
        if self.step == "gauss_newton":  # exact H at the result
            ev = self._eval(fine, NEIGHBORS[self.neighbors], src, T, True, False, memo)
            passes += 1
        if ev.num_inliers == 0:
            converged = False  # nothing matched: the pose is unconstrained, not converged
        lam, V = np.linalg.eigh(ev.H)
        H = ev.H if lam[0] >= 0.0 else (V * np.maximum(lam, 0.0)) @ V.T
        if lam[0] < 0.0:
            log.debug("NDT Hessian has negative eigenvalue %.3g; clamped to 0 in H", lam[0])
        return NdtResult(
            T_target_source=_orthonormalize(T), converged=bool(converged),
            iterations=int(iterations), score=ev.score, error=-ev.score,
            fitness=ev.num_inliers / len(src), num_inliers=ev.num_inliers,
            num_points=len(src), H=0.5 * (H + H.T), b=ev.b, eigenvalues=lam, eigenvectors=V,
            H_exact=ev.H, coarse_iterations=coarse_iterations, passes=passes)


def _new_memo(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-point (voxel key, neighbour-list row) memo of the DIRECT1/7 kernels; key -1: empty."""
    return np.full(max(n, 1), -1, dtype=np.int64), np.empty(max(n, 1), dtype=np.int64)


def align(target_points: np.ndarray, source_points: np.ndarray,
          T_init: np.ndarray | None = None, resolution: float = 1.0,
          **options: Any) -> NdtResult:
    """One-shot NDT: build a target from ``target_points`` and register ``source_points``.

    target_points: (N, 3) map/target frame; source_points: (M, 3) sensor frame; metres.
    T_init: (4, 4) initial ``T_target_source``. options: ``min_points_per_voxel``,
    ``coarse_levels`` and any
    ``NdtRegistration`` keyword (neighbors, outlier_ratio, max_iterations, step_epsilon, ...).
    """
    min_pts = options.pop("min_points_per_voxel", 6)
    coarse_levels = options.pop("coarse_levels", 1)
    target = NdtTarget.build(target_points, resolution=resolution, min_points_per_voxel=min_pts,
                             coarse_levels=coarse_levels)
    reg = NdtRegistration(**options)
    return reg.align(target, source_points, T_init)
