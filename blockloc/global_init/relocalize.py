"""Global initialization: from one scan and gravity to a verified 6-DoF pose in the map.

Steps (``GlobalLocalizer.localize``):
1. level the scan with gravity and project it to 2D cells (``projection``);
2. branch and bound over (x, y, yaw) in the window around the hint (``bnb``) on the map pyramid of
   that region (``maps``), keeping the K best distinct candidates;
3. refine every candidate in 6-DoF with NDT and verify it by fitness (``refine``);
4. the best verified candidate wins; another verified candidate nearly as good but more than
   ``ambiguity_distance_m`` away marks the result ambiguous (reported, never hidden).
Without a hint, square regions tiling the map are ordered by a cheap score (the best coarse bound
of a subsampled scan over coarse angles) and searched in that order until one gives a verified
match. Tracking uses the same entry points to start and to recover.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from blockloc.errors import GlobalInitError
from blockloc.geometry import inv_T, transform_points
from blockloc.global_init.bnb import Candidate2D, make_angles, required_cells, rotated_cells, search
from blockloc.global_init.maps import ArrayMap, ProjectionParams, StoreMap
from blockloc.global_init.pyramid import extend
from blockloc.global_init.projection import ScanProjection, heading_offset, project_scan
from blockloc.global_init.refine import Refiner
from blockloc.voxels import voxel_select

log = logging.getLogger(__name__)


@dataclass
class InitParams:
    """Every knob of global initialization (defaults: ``GlobalInitConfig``)."""

    resolution_m: float = 0.5
    pyramid_levels: int = 6
    band_m: tuple[float, float] = (0.3, 3.0)
    projection: str = "band"  # band | all
    max_range_m: float = 60.0
    max_scan_cells: int = 1500
    min_scan_cells: int = 50
    top_k: int = 5
    use_s0: bool = True
    s0_ratio: float = 0.9
    min_score: float = 0.05
    nms_m: float = 1.0
    nms_deg: float = 5.0
    min_fitness: float = 0.75
    min_structure_fitness: float = 0.6
    ambiguity_distance_m: float = 2.0
    ambiguity_fitness_margin: float = 0.05
    ndt_resolution_m: float = 1.0
    scan_voxel_m: float = 0.5
    max_ndt_points: int = 3000
    ambiguity_score_ratio: float = 0.8  # once one is verified, refine others only above this x best
    refine_range_m: float = 50.0
    reloc_window_m: float = 100.0
    max_regions: int = 0  # 0: every region of the map
    num_threads: int = 2

    @property
    def projection_params(self) -> ProjectionParams:
        return ProjectionParams(self.resolution_m, self.pyramid_levels, tuple(self.band_m), self.projection)

    @classmethod
    def from_config(cls, gi, registration=None) -> "InitParams":
        """From ``blockloc.config.GlobalInitConfig`` (and optionally ``RegistrationConfig``)."""
        kw = {}
        for name in cls.__dataclass_fields__:
            if hasattr(gi, name):
                kw[name] = getattr(gi, name)
        if "band_m" not in kw and hasattr(gi, "height_band_m"):
            kw["band_m"] = tuple(gi.height_band_m)
        if registration is not None and "num_threads" not in kw:
            kw["num_threads"] = registration.num_threads
        return cls(**kw)


@dataclass
class InitCandidate:
    """A refined candidate. T_map_body (4, 4); score: 2D BnB score [0, 1]; fitness: NDT inlier ratio."""

    T_map_body: np.ndarray
    score: float
    fitness: float
    converged: bool
    verified: bool
    T_map_body_2d: np.ndarray | None = None  # before refinement
    ndt_score: float = 0.0  # NDT score per scan point (higher is better)
    structure_fitness: float = 0.0  # inlier ratio of the scan's above-ground (band) points


@dataclass
class InitResult:
    """Outcome of global initialization.

    T_map_body: (4, 4) best pose (the best verified candidate; without one, the best-scoring
    refined candidate, or None when the search found nothing); verified candidates are ranked by
    NDT score per point. verified: it passed the fitness check.
    ambiguous: another verified candidate nearly as good lies > ambiguity_distance_m away.
    candidates: every refined candidate, best first. time_s: wall time. stats: search details.
    """

    T_map_body: np.ndarray | None
    score: float
    fitness: float
    candidates: list[InitCandidate]
    ambiguous: bool
    time_s: float
    verified: bool
    stats: dict = field(default_factory=dict)


def _check_args(window_m: float, yaw_window_deg: float) -> None:
    if not (window_m > 0 and math.isfinite(window_m)):
        raise GlobalInitError(f"search window {window_m} m: expected a positive size in metres")
    if not (0 < yaw_window_deg and math.isfinite(yaw_window_deg)):
        raise GlobalInitError(f"yaw window {yaw_window_deg} deg: expected a positive angle (<= 360)")


class GlobalLocalizer:
    """Global initialization against one map (ArrayMap or StoreMap), reusable across scans."""

    def __init__(self, map_source, params: InitParams | None = None, engine=None):
        self.map = map_source
        self.params = params or InitParams()
        if engine is None:  # the default engine at the refinement resolution
            from blockloc.registration.engines import make_engine

            engine = make_engine("ndt", resolution_m=self.params.ndt_resolution_m,
                                 num_threads=self.params.num_threads)
        self.engine = engine  # refines and verifies candidates

    @classmethod
    def for_store(cls, store, gravity_map, params: InitParams | None = None, cache_dir=None,
                  engine=None) -> "GlobalLocalizer":
        params = params or InitParams()
        return cls(StoreMap(store, gravity_map, params.projection_params, cache_dir), params, engine)

    @classmethod
    def for_points(cls, map_points, gravity_map, params: InitParams | None = None,
                   engine=None) -> "GlobalLocalizer":
        params = params or InitParams()
        return cls(ArrayMap(map_points, gravity_map, params.projection_params), params, engine)

    # ------------------------------------------------------------------------- public

    def localize(self, points_body: np.ndarray, gravity_body: np.ndarray, hint_xy=None, hint_yaw=None,
                 window_m: float = 40.0, yaw_window_deg: float = 360.0) -> InitResult:
        """Pose of the body for a scan (N, 3) in the BODY frame, metres.

        gravity_body: (3,) gravity direction in the body frame (from the accelerometer).
        hint_xy: (2,) map-frame position hint, metres, or None for whole-map relocalization.
        hint_yaw: map-frame yaw hint (rad) or None (searched over ``yaw_window_deg`` around it).
        """
        t0 = time.perf_counter()
        p = self.params
        _check_args(window_m, yaw_window_deg)
        scan = project_scan(points_body, gravity_body, p.resolution_m, p.band_m, p.projection, p.max_range_m,
                            p.max_scan_cells, p.min_scan_cells)
        scan_ndt = points_body[voxel_select(points_body, p.scan_voxel_m)]
        scan_ndt = scan_ndt[np.linalg.norm(scan_ndt, axis=1) <= p.max_range_m]
        if len(scan_ndt) > p.max_ndt_points:
            rng = np.random.default_rng(0)
            scan_ndt = scan_ndt[np.sort(rng.choice(len(scan_ndt), p.max_ndt_points, replace=False))]
        if hint_yaw is None:
            theta_c, yaw_win = 0.0, 2 * math.pi
        else:
            theta_c = self._theta_from_yaw(float(hint_yaw), scan)
            yaw_win = min(math.radians(yaw_window_deg), 2 * math.pi)
        if hint_xy is not None:
            center = self._hint_to_L(hint_xy)
            cands, stats = self._search_region(scan, scan_ndt, center, window_m, theta_c, yaw_win)
            stats["regions_searched"] = 1
        else:
            cands, stats = self._relocalize(scan, scan_ndt, theta_c, yaw_win)
        return self._decide(cands, stats, time.perf_counter() - t0)

    # ------------------------------------------------------------------------- steps

    def _hint_to_L(self, hint_xy) -> np.ndarray:
        xy = np.asarray(hint_xy, float).reshape(-1)
        if xy.shape != (2,) or not np.all(np.isfinite(xy)):
            raise GlobalInitError(f"pose hint {hint_xy!r}: expected finite x, y in metres")
        c = (self.map.R_L_map @ np.array([xy[0], xy[1], 0.0]))[:2]
        lo, hi = self.map.bounds_L()
        if np.any(c < lo - 1e-6) or np.any(c > hi + 1e-6):
            lo_m = self.map.R_L_map.T @ np.r_[lo, 0.0]
            hi_m = self.map.R_L_map.T @ np.r_[hi, 0.0]
            bmin, bmax = np.minimum(lo_m, hi_m)[:2], np.maximum(lo_m, hi_m)[:2]
            raise GlobalInitError(
                f"pose hint ({xy[0]:.1f}, {xy[1]:.1f}) is outside the map (x {bmin[0]:.1f}..{bmax[0]:.1f}, "
                f"y {bmin[1]:.1f}..{bmax[1]:.1f} m)")
        return c

    def _theta_from_yaw(self, yaw_map: float, scan: ScanProjection) -> float:
        v = self.map.R_L_map @ np.array([math.cos(yaw_map), math.sin(yaw_map), 0.0])
        return math.atan2(v[1], v[0]) - heading_offset(scan.R_tilt)

    def _pose_from_2d(self, c: Candidate2D, scan: ScanProjection) -> np.ndarray:
        """T_map_body of a 2D candidate: roll/pitch from gravity, z from the map's ground."""
        cth, sth = math.cos(c.theta), math.sin(c.theta)
        Rz = np.array([[cth, -sth, 0.0], [sth, cth, 0.0], [0.0, 0.0, 1.0]])
        offs = np.array([[dx, dy] for dx in (-2.0, 0.0, 2.0) for dy in (-2.0, 0.0, 2.0)])
        g = self.map.ground_at(np.array([c.x, c.y]) + offs)
        ground = float(np.nanmedian(g)) if np.any(np.isfinite(g)) else 0.0
        above = -scan.ground_below if math.isfinite(scan.ground_below) else 0.0
        T_L_body = np.eye(4)
        T_L_body[:3, :3] = Rz @ scan.R_tilt
        T_L_body[:3, 3] = [c.x, c.y, ground + above]
        T_map_L = np.eye(4)
        T_map_L[:3, :3] = self.map.R_L_map.T
        return T_map_L @ T_L_body

    def _search_region(self, scan: ScanProjection, scan_ndt: np.ndarray, center: np.ndarray, window_m: float,
                       theta_c: float, yaw_win: float, use_s0: bool | None = None):
        p = self.params
        lo, hi = required_cells(scan.xy, center, window_m, p.resolution_m)
        t = time.perf_counter()
        pyr = self.map.pyramid(lo, hi)
        # Large windows (whole-map relocalization): more levels on top, so that a few hundred
        # roots per angle, not tens of thousands, start the search.
        want = int(math.ceil(math.log2(max(window_m / p.resolution_m / 8.0, 1.0)))) + 1
        pyr = extend(pyr, max(pyr.num_levels, want))
        t_pyr = time.perf_counter() - t
        c2d, st = search(pyr, scan.xy, center, window_m, theta_c, yaw_win, p.top_k,
                         p.use_s0 if use_s0 is None else use_s0, p.s0_ratio, p.min_score, p.nms_m, p.nms_deg,
                         max_range=scan.max_range)
        stats = {"num_angles": st.num_angles, "angle_step_deg": math.degrees(st.angle_step_rad),
                 "num_roots": st.num_roots, "nodes_visited": st.nodes_visited, "s0": st.s0,
                 "bnb_time_s": st.time_s, "pyramid_time_s": t_pyr, "scan_cells": len(scan.xy)}
        t = time.perf_counter()
        cands = self._refine(c2d, scan, scan_ndt)
        stats["refine_time_s"] = time.perf_counter() - t
        return cands, stats

    def _refine(self, c2d: list[Candidate2D], scan: ScanProjection, scan_ndt: np.ndarray) -> list[InitCandidate]:
        if not c2d:
            return []
        p = self.params
        d = min(p.refine_range_m, p.max_range_m)
        # One NDT target per cluster of candidates (a target over candidates far apart would load
        # the whole map): a candidate within d/2 of an existing target's centre reuses it.
        targets: list[tuple[np.ndarray, Refiner | None]] = []

        def refiner_for(xy: np.ndarray) -> Refiner | None:
            for centre, ref in targets:
                if np.all(np.abs(xy - centre) <= 0.5 * d):
                    return ref
            pts = self.map.points_in_box(xy - d, xy + d)
            ref = Refiner(self.engine, pts) if len(pts) >= 100 else None
            targets.append((xy, ref))
            return ref

        out = []
        best_score = max(c.score for c in c2d)
        for c in sorted(c2d, key=lambda c: -c.score):
            # Once a candidate is verified, only those scoring close to the best can make the
            # result ambiguous; the others need no NDT run.
            if any(o.verified for o in out) and c.score < p.ambiguity_score_ratio * best_score:
                break
            T0 = self._pose_from_2d(c, scan)
            refiner = refiner_for(np.array([c.x, c.y]))
            if refiner is None:
                continue
            r = refiner.align(scan_ndt, T0)
            if not r.converged and np.all(np.isfinite(r.T_map_body)):
                r = refiner.align(scan_ndt, r.T_map_body)  # out of iterations, e.g. sliding along a corridor
            finite = bool(np.all(np.isfinite(r.T_map_body)))
            # Ground points fit the ground almost anywhere: the structure above it must fit too.
            sfit = refiner.inlier_ratio(scan.structure_body, r.T_map_body) if finite else 0.0
            ok = bool(r.converged and finite and r.fitness >= p.min_fitness
                      and sfit >= p.min_structure_fitness)
            out.append(InitCandidate(r.T_map_body, c.score, r.fitness, r.converged, ok, T0, r.ndt_score, sfit))
        return out

    def _relocalize(self, scan: ScanProjection, scan_ndt: np.ndarray, theta_c: float, yaw_win: float):
        p = self.params
        w = p.reloc_window_m
        centers = self.map.region_centers(w)
        if len(centers) == 0:
            raise GlobalInitError("the map has no blocks/tiles to relocalize in")
        t = time.perf_counter()
        cheap = np.array([self._cheap_score(scan, c, w) for c in centers])
        order = np.argsort(-cheap, kind="stable")
        if p.max_regions > 0:
            order = order[: p.max_regions]
        t_cheap = time.perf_counter() - t
        all_cands: list[InitCandidate] = []
        stats: dict = {"regions": len(centers), "cheap_time_s": t_cheap, "regions_searched": 0}
        for k, i in enumerate(order):
            # Regions overlap by the scan's reach, so a pose near a border is inside some window.
            cands, st = self._search_region(scan, scan_ndt, centers[i], w + 2.0 * p.resolution_m, theta_c, yaw_win)
            stats["regions_searched"] = k + 1
            for key in ("bnb_time_s", "refine_time_s", "nodes_visited"):
                stats[key] = stats.get(key, 0) + st[key]
            all_cands.extend(cands)
            if any(c.verified for c in cands):
                stats["found_in_rank"] = k + 1
                break
        return all_cands, stats

    def _cheap_score(self, scan: ScanProjection, center: np.ndarray, window_m: float) -> float:
        """Orders regions (prunes none): the best level-3 bound (4 m windows at 0.5 m cells) of a
        200-cell subsample over 128 angles and a 2^3-cell translation stride. The top level alone
        saturates over a 100 m region; this is still ~16M lookups per region."""
        from blockloc.global_init import _kernels as K

        p = self.params
        sub = scan.xy[:: max(1, len(scan.xy) // 200)]
        lo, hi = required_cells(sub, center, window_m, p.resolution_m)
        try:
            pyr = self.map.pyramid(lo, hi)
        except GlobalInitError:
            return 0.0
        angles, _ = make_angles(0.0, 2 * math.pi, 2 * math.pi / 128)
        cx, cy = rotated_cells(sub, angles, p.resolution_m)
        dx = (cx - pyr.origin[0]).astype(np.int32)
        dy = (cy - pyr.origin[1]).astype(np.int32)
        level = min(pyr.num_levels - 1, 3)
        r = p.resolution_m
        half = int(math.ceil(0.5 * window_m / r))
        c0 = np.floor(center / r).astype(np.int64)
        g = np.arange(-half, half + 1, 1 << level)
        gx, gy = np.meshgrid(c0[0] + g, c0[1] + g, indexing="ij")
        A = len(angles)
        n = gx.size
        ra = np.repeat(np.arange(A), n).astype(np.int64)
        rtx = np.tile(gx.ravel(), A).astype(np.int64)
        rty = np.tile(gy.ravel(), A).astype(np.int64)
        b = K.root_scores(pyr.levels, level, dx, dy, ra, rtx, rty)
        return float(b.max()) / (255.0 * len(sub))

    def _decide(self, cands: list[InitCandidate], stats: dict, elapsed: float) -> InitResult:
        p = self.params
        # Verified first, then by the NDT score per point: smoother than the inlier ratio, which
        # ties along weakly constrained directions (corridors).
        cands = sorted(cands, key=lambda c: (c.verified, c.ndt_score, c.fitness), reverse=True)
        # Candidates that NDT brought to the same pose are one candidate (keep the best 2D score).
        merged: list[InitCandidate] = []
        for c in cands:
            same = next((m for m in merged if np.linalg.norm(m.T_map_body[:3, 3] - c.T_map_body[:3, 3]) < 0.3
                         and pose_error(m.T_map_body, c.T_map_body)[1] < 1.0), None)
            if same is None:
                merged.append(c)
            else:
                same.score = max(same.score, c.score)
        cands = merged
        if not cands:
            return InitResult(None, 0.0, 0.0, [], False, elapsed, False, stats)
        best = cands[0]
        ambiguous = False
        if best.verified:
            for c in cands[1:]:
                far = np.linalg.norm(c.T_map_body[:3, 3] - best.T_map_body[:3, 3]) > p.ambiguity_distance_m
                # Unconverged candidates count too: fitting as well elsewhere is what matters.
                plausible = c.fitness >= p.min_fitness and c.structure_fitness >= p.min_structure_fitness
                if plausible and far and c.fitness >= best.fitness - p.ambiguity_fitness_margin:
                    ambiguous = True
                    break
        if ambiguous:
            log.warning("global init is ambiguous: two verified candidates more than %.1f m apart",
                        p.ambiguity_distance_m)
        return InitResult(best.T_map_body, best.score, best.fitness, cands, ambiguous, elapsed,
                          best.verified, stats)


# ----------------------------------------------------------------------------- one-shot API


def localize(scan_points_lidar: np.ndarray, *, T_body_lidar: np.ndarray, map_store,
             gravity_body: np.ndarray | None = None, roll_pitch: tuple[float, float] | None = None,
             gravity_map=(0.0, 0.0, -9.81), hint_xy=None, hint_yaw=None, window_m: float = 40.0,
             yaw_window_deg: float = 360.0, params: InitParams | None = None, cache_dir=None) -> InitResult:
    """Global initialization of one scan against a map store.

    scan_points_lidar: (N, 3) lidar frame, metres. T_body_lidar: (4, 4).
    gravity_body: (3,) gravity in the body frame (e.g. ``gravity_body_from_imu``), or ``roll_pitch``
    (rad) of the body in the map frame. gravity_map: (3,) gravity in the map frame (NCLT and the
    simulator: (0, 0, +9.81), z down). map_store: a ``MapStore`` or a ``GlobalLocalizer`` (reuse one
    across calls to keep its pyramids in memory). Returns an :class:`InitResult`; T_map_body is the
    pose of the body (the ground truth's frame) in the map frame.
    """
    if isinstance(map_store, GlobalLocalizer):
        loc = map_store
    else:
        loc = GlobalLocalizer.for_store(map_store, gravity_map, params, cache_dir)
    g_body = _gravity_body(gravity_body, roll_pitch, gravity_map)
    pts = transform_points(np.asarray(T_body_lidar, float), scan_points_lidar)
    return loc.localize(pts, g_body, hint_xy, hint_yaw, window_m, yaw_window_deg)


def localize_points(map_points: np.ndarray, scan_points_body: np.ndarray, *, gravity_body=None,
                    roll_pitch=None, gravity_map=(0.0, 0.0, -9.81), hint_xy=None, hint_yaw=None,
                    window_m: float = 40.0, yaw_window_deg: float = 360.0,
                    params: InitParams | None = None) -> InitResult:
    """Same as :func:`localize` on arrays: map points (M, 3) map frame, scan (N, 3) body frame."""
    loc = GlobalLocalizer.for_points(map_points, gravity_map, params)
    return loc.localize(np.asarray(scan_points_body, float), _gravity_body(gravity_body, roll_pitch, gravity_map),
                        hint_xy, hint_yaw, window_m, yaw_window_deg)


def _gravity_body(gravity_body, roll_pitch, gravity_map) -> np.ndarray:
    if gravity_body is not None:
        return np.asarray(gravity_body, float).reshape(3)
    if roll_pitch is None:
        raise GlobalInitError("global init needs gravity in the body frame or the body's roll and pitch")
    from blockloc.geometry import rpy_to_R

    R_map_body = rpy_to_R(roll_pitch[0], roll_pitch[1], 0.0)
    return R_map_body.T @ np.asarray(gravity_map, float)


def pose_error(T_est: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) between two (4, 4) poses."""
    from blockloc.geometry import rotation_angle

    d = inv_T(T_ref) @ T_est
    return float(np.linalg.norm(T_est[:3, 3] - T_ref[:3, 3])), float(np.degrees(rotation_angle(d[:3, :3])))
