"""Global initialization: from one scan and gravity to a verified 6-DoF pose in the map.

Steps (``GlobalLocalizer.localize``):
1. level the scan with gravity and project it to 2D cells (``projection``);
2. branch and bound over (x, y, yaw) in the window around the hint (``bnb``) on the map pyramid of
   that region (``maps``), keeping the K best distinct candidates;
3. refine every candidate in 6-DoF with NDT and verify it by fitness (``refine``);
4. the best verified candidate wins; another verified candidate nearly as good but more than
   ``ambiguity_distance_m`` away marks the result ambiguous (reported, never hidden).
Without a hint (``_relocalize_places``), the map's place index (``place_index``) ranks the places
that look like the scan, with a yaw guess each; one branch and bound runs over small windows
around the best ``place_candidates[0]`` of them (yaw within ``place_yaw_window_deg`` of the guess),
then, while nothing is verified, around more of them (optionally around the first ones at every
yaw: ``place_all_yaw_candidates``); only then
(``whole_map_fallback``) are square regions tiling the map searched in the order of a cheap score
(the best coarse bound of a subsampled scan over coarse angles) until one gives a verified match
or ``max_search_s`` has passed (then the result is unverified: "not found", ``stats['timed_out']``).
Tracking uses the same entry points to start and to recover.

Verification (``_refine``) asks more than a good NDT fit, because a wrong place with similar
structure can fit well: NDT converged, its inlier ratio >= ``min_fitness``, the above-ground
points' inlier ratio >= ``min_structure_fitness`` (those of the projection band or, when the scan
has ``min_static_points`` of them and ``structure_from_static``, the points at or above the static
band's bottom: either set may pass), and, in the place index's static band, the
scan's structure covered by the map (>= ``min_coverage``) and the map's structure not where the
scan saw through (<= ``max_see_through`` of the bins seen through). Another verified candidate
more than ``ambiguity_distance_m`` away that fits nearly as well makes the result ambiguous, and an
ambiguous result is never reported as verified.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from blockloc.errors import GlobalInitError
from blockloc.geometry import inv_T, transform_points
from blockloc.global_init.bnb import (Candidate2D, Window, make_angles, required_cells, rotated_cells, search,
                                     search_windows)
from blockloc.global_init.maps import ArrayMap, ProjectionParams, StoreMap
from blockloc.global_init.pyramid import extend
from blockloc.global_init.projection import ScanProjection, heading_offset, project_scan
from blockloc.global_init.refine import Refiner
from blockloc.voxels import voxel_select

log = logging.getLogger(__name__)

GROUP_M = 400.0  # windows of the no-hint search share one pyramid crop per square of this side


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
    ambiguity_distance_m: float = 0.5  # rivals farther than this (NDT merges closer ones) count
    probe_m: tuple[float, ...] = (1.0, 2.0)  # NDT restarts from the best moved this far look for rivals
    ambiguity_fitness_margin: float = 0.05
    ndt_resolution_m: float = 1.0
    scan_voxel_m: float = 0.5
    max_ndt_points: int = 3000
    ambiguity_score_ratio: float = 0.8  # once one is verified, refine others only above this x best
    ambiguity_z: float = 2.5  # a rival is no ambiguity when the best fits significantly better (z)
    refine_range_m: float = 50.0
    reloc_window_m: float = 100.0
    max_regions: int = 0  # 0: every region of the map
    num_threads: int = 2
    # no-hint relocalization through the place index
    use_place_index: bool = True
    place_candidates: tuple[int, ...] = (8, 64, 256)  # places searched per stage (around the yaw guesses)
    place_all_yaw_candidates: int = 0  # then this many of them at every yaw (0: none)
    place_window_m: float = 12.0  # window around each place (>= 2 x the index's tolerance + spacing)
    place_yaw_window_deg: float = 16.0  # around each place's yaw guess (its error: p95 ~5 deg)
    place_top_k: int = 6  # leaves refined per stage
    # the best leaves of each window (0: one top place_top_k over all windows, by 2D score)
    place_leaves_per_window: int = 1
    place_top_level: int = 3  # its roots' level (2^3 cells = 4 m at 0.5 m: tight bounds in small windows)
    place_band_m: tuple[float, float] = (2.0, 4.0)
    place_max_range_m: float = 63.0
    place_spacing_m: float = 3.0
    place_tolerance_m: float = 1.5
    place_max_offset_m: float = 20.0
    whole_map_fallback: bool = True
    # No-hint search budget (s, 0: none): checked between place stages and between the fallback's
    # regions, so a scan that the place stages miss ends as "not found" instead of searching a large
    # map region by region for minutes (seen: 349 s on campus). It bounds the search, not one stage.
    max_search_s: float = 10.0
    # static-band consistency at the refined pose (verification)
    min_coverage: float = 0.9
    max_see_through: float = 0.35
    consistency_tolerance_m: float = 0.75
    min_consistency_bits: int = 20
    min_static_points: int = 300  # fewer static-band points: the structure test uses the low band
    structure_from_static: bool = True  # False: the structure test always uses the projection band

    @property
    def projection_params(self) -> ProjectionParams:
        return ProjectionParams(self.resolution_m, self.pyramid_levels, tuple(self.band_m), self.projection)

    @property
    def place_index_params(self):
        from blockloc.global_init.place_index import PlaceIndexParams

        return PlaceIndexParams(resolution_m=self.resolution_m, num_levels=self.pyramid_levels,
                                band_m=tuple(self.place_band_m), max_range_m=self.place_max_range_m,
                                spacing_m=self.place_spacing_m, tolerance_m=self.place_tolerance_m,
                                max_offset_m=self.place_max_offset_m)

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
    coverage: float = float("nan")  # static-band scan bins the map covers (NaN: not tested)
    see_through: float = float("nan")  # static-band bins seen through that the map fills
    refiner: object = field(default=None, repr=False, compare=False)  # its NDT target, while deciding


@dataclass
class InitResult:
    """Outcome of global initialization.

    T_map_body: (4, 4) best pose (the best verified candidate; without one, the best-scoring
    refined candidate, or None when the search found nothing); verified candidates are ranked by
    NDT score per point. verified: the best candidate passed verification and the result is not
    ambiguous (only then may the pose be used).
    ambiguous: another verified candidate nearly as good lies > ambiguity_distance_m away.
    candidates: every refined candidate, best first. time_s: wall time of the search and refinement
    (map pieces and the place index load lazily on the first call; ``stats['index_load_s']``).
    stats: search details.
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

    def __init__(self, map_source, params: InitParams | None = None, engine=None, place_index=None):
        self.map = map_source
        self.params = params or InitParams()
        if engine is None:  # the default engine at the refinement resolution
            from blockloc.registration.engines import make_engine

            engine = make_engine("ndt", resolution_m=self.params.ndt_resolution_m,
                                 num_threads=self.params.num_threads)
        self.engine = engine  # refines and verifies candidates
        self._place_index = place_index
        self._place_source = None
        self._coverage_source = None
        self._index_load_s = 0.0
        self._structure_body = None  # the scan's points the structure test uses (set by _refine)

    @property
    def place_index(self):
        """The map's place index (``place_index``), loaded (or built) on first use."""
        if self._place_index is None:
            from blockloc.global_init.place_index import index_for_source

            t = time.perf_counter()
            self._place_index = index_for_source(self.map, self.params.place_index_params)
            self._index_load_s = time.perf_counter() - t
        return self._place_index

    @property
    def place_source(self):
        """The map projected in the place index's static band (consistency checks)."""
        if self._place_source is None:
            p = self._place_index.params if self._place_index is not None else self.params.place_index_params
            self._place_source = self.map.with_params(p.projection_params)
        return self._place_source

    @property
    def coverage_source(self):
        """The map in the place index's band, every point (``band`` mode): what covers a scan."""
        if self._coverage_source is None:
            from dataclasses import replace

            self._coverage_source = self.map.with_params(replace(self.place_source.params, mode="band"))
        return self._coverage_source

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
        self._structure_body = None
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
            cells = self._scan_cells(points_body, gravity_body)
            cands, stats = self._search_region(scan, scan_ndt, center, window_m, theta_c, yaw_win, cells=cells)
            stats["regions_searched"] = 1
            return self._decide(cands, stats, time.perf_counter() - t0, scan_ndt)
        cands, stats = [], {}
        if p.use_place_index:
            t_idx = time.perf_counter()
            index = self.place_index
            t0 += time.perf_counter() - t_idx  # loading the index is opening the map, not searching
            stats["index_load_s"] = self._index_load_s
        cells = self._scan_cells(points_body, gravity_body)
        deadline = t0 + p.max_search_s if p.max_search_s > 0 else math.inf
        if p.use_place_index:
            cands, stats = self._relocalize_places(scan, scan_ndt, cells, index, theta_c, yaw_win, stats, deadline)
            res = self._decide(cands, stats, time.perf_counter() - t0, scan_ndt, final=False)
            # An ambiguous result stays ambiguous however much more is searched.
            if res.verified or res.ambiguous or not p.whole_map_fallback or stats.get("timed_out"):
                return self._decide(cands, stats, time.perf_counter() - t0, scan_ndt)
        more, st = self._relocalize(scan, scan_ndt, theta_c, yaw_win, cells, deadline)
        stats.update({k: v + stats.get(k, 0) if k in ("bnb_time_s", "refine_time_s", "nodes_visited") else v
                      for k, v in st.items()})
        return self._decide(cands + more, stats, time.perf_counter() - t0, scan_ndt)

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
                       theta_c: float, yaw_win: float, use_s0: bool | None = None, cells=None):
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
        cands = self._refine(c2d, scan, scan_ndt, cells)
        stats["refine_time_s"] = time.perf_counter() - t
        return cands, stats

    def _refine(self, c2d: list[Candidate2D], scan: ScanProjection, scan_ndt: np.ndarray, cells=None,
                skip: list[Candidate2D] | None = None, ordered: bool = False) -> list[InitCandidate]:
        """Refine 2D candidates best first with NDT and verify them (module docstring); once one is
        verified, only those scoring within ``ambiguity_score_ratio`` of the best are refined.
        ``skip``: candidates refined before (a later stage finds them again). ``ordered``: in the
        given order (best place first) rather than by 2D score."""
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
        for c in (c2d if ordered else sorted(c2d, key=lambda c: -c.score)):
            # Once a candidate is verified, only those scoring close to the best can make the
            # result ambiguous; the others need no NDT run.
            if any(o.verified for o in out) and c.score < p.ambiguity_score_ratio * best_score:
                if ordered:
                    continue
                break
            if skip is not None and any(abs(c.x - o.x) < 0.5 and abs(c.y - o.y) < 0.5
                                        and abs((c.theta - o.theta + math.pi) % (2 * math.pi) - math.pi) < 0.02
                                        for o in skip):
                continue
            if skip is not None:
                skip.append(c)
            T0 = self._pose_from_2d(c, scan)
            refiner = refiner_for(np.array([c.x, c.y]))
            if refiner is None:
                continue
            r = refiner.align(scan_ndt, T0)
            if not r.converged and np.all(np.isfinite(r.T_map_body)):
                r = refiner.align(scan_ndt, r.T_map_body)  # out of iterations, e.g. sliding along a corridor
            finite = bool(np.all(np.isfinite(r.T_map_body)))
            # Ground points fit the ground almost anywhere: the structure above it must fit too.
            # Judged on the static structure (at or above the place band's bottom) when the scan
            # has enough of it: people, cars and bushes near the sensor fill the low band with
            # points no map holds (seen: 0.16 of the low points within 10 m fit at the true pose).
            # Either band may pass: tree crowns dominate the static band where the foliage changed
            # between sessions (seen on campus: 0.43-0.51 of it fit at true poses whose projection
            # band fit 0.98), as crowds dominate the low band.
            static = cells.static_body if cells is not None and cells.static_body is not None else None
            structures = [scan.structure_body]
            if p.structure_from_static and static is not None and len(static) >= p.min_static_points:
                structures = [static, scan.structure_body]
            self._structure_body = structures  # a rival of the best must pass the same test (_nearby_rival)
            sfit = self._structure_fit(refiner, structures, r.T_map_body) if finite else 0.0
            ok = bool(r.converged and finite and r.fitness >= p.min_fitness
                      and sfit >= p.min_structure_fitness)
            cov, see = self._consistency(r.T_map_body, scan, cells) if (ok and cells is not None) else (np.nan, np.nan)
            if math.isfinite(cov) and cov < p.min_coverage:
                ok = False
            if math.isfinite(see) and see > p.max_see_through:
                ok = False
            out.append(InitCandidate(r.T_map_body, c.score, r.fitness, r.converged, ok, T0, r.ndt_score, sfit,
                                     cov, see, refiner))
        return out

    def _structure_fit(self, refiner, structures: list[np.ndarray], T_map_body: np.ndarray) -> float:
        """The best inlier ratio of the scan's above-ground point sets (static band first, then the
        projection band; :meth:`_refine`) at a pose; the first set passing the test ends it."""
        best = 0.0
        for pts in structures:
            best = max(best, refiner.inlier_ratio(pts, T_map_body))
            if best >= self.params.min_structure_fitness:
                break
        return best

    def _scan_cells(self, points_body: np.ndarray, gravity_body: np.ndarray):
        """The scan's cells in the place index's band (consistency checks, place queries)."""
        from blockloc.global_init.place_index import scan_cells

        ip = self._place_index.params if self._place_index is not None else self.params.place_index_params
        return scan_cells(points_body, gravity_body, ip)

    def _consistency(self, T_map_body: np.ndarray, scan: ScanProjection, cells) -> tuple[float, float]:
        """(coverage, see_through) of the scan's static-band bins at a refined pose; NaN where
        fewer than ``min_consistency_bits`` bins were observed (nothing to judge by)."""
        from dataclasses import replace

        from blockloc.global_init.place_index import consistency_at

        p = self.params
        ip = self._place_index.params if self._place_index is not None else p.place_index_params
        ip = replace(ip, tolerance_m=p.consistency_tolerance_m)
        T_L_body = np.eye(4)
        T_L_body[:3, :3] = self.map.R_L_map @ T_map_body[:3, :3]
        T_L_body[:3, 3] = self.map.R_L_map @ T_map_body[:3, 3]
        R_heading = T_L_body[:3, :3] @ cells.R_tilt.T
        theta = math.atan2(R_heading[1, 0], R_heading[0, 0])
        try:
            return consistency_at(self.place_source, T_L_body[:2, 3], theta, cells, ip, p.min_consistency_bits,
                                  coverage_source=self.coverage_source)
        except GlobalInitError:
            return np.nan, np.nan

    def _relocalize_places(self, scan: ScanProjection, scan_ndt: np.ndarray, cells, index, theta_c: float,
                           yaw_win: float, stats: dict, deadline: float = math.inf):
        """No-hint search through the place index, widening stage by stage (module docstring) while
        ``time.perf_counter()`` is before ``deadline``."""
        p = self.params
        t = time.perf_counter()
        theta_window = (theta_c, yaw_win) if yaw_win < 2 * math.pi else None
        places = index.query_cells(cells, max(p.place_candidates), theta_window=theta_window)
        stats.update(place_query_s=time.perf_counter() - t, places=len(index), place_stage=0)
        if not places:
            return [], stats
        yaw_guess = math.radians(p.place_yaw_window_deg)
        # An optional last stage tries every yaw around the best places (a yaw guess off by more
        # than the window: a symmetric scene); it costs most of a search that finds nothing (seen:
        # 15 of 20 s on the small world), so by default the regions' search (all yaws) follows.
        stages = [(k, yaw_guess) for k in p.place_candidates]
        if p.place_all_yaw_candidates > 0:
            stages.append((p.place_all_yaw_candidates, min(yaw_win, 2 * math.pi)))
        out: list[InitCandidate] = []
        done: list[Candidate2D] = []
        k_done = 0
        for i, (k, yaw) in enumerate(stages):
            if yaw >= min(yaw_win, 2 * math.pi) and yaw_guess >= min(yaw_win, 2 * math.pi) and i > 0:
                break  # the guesses' windows already covered every allowed yaw
            if i > 0 and time.perf_counter() >= deadline:
                stats["timed_out"] = True
                break
            # The places not searched yet (a later yaw-only stage: its places again, at every yaw).
            first = k_done if yaw == yaw_guess else 0
            windows = [Window(c.xy_L, p.place_window_m, c.theta if yaw < 2 * math.pi else theta_c, yaw)
                       for c in places[first:k]]
            k_done = max(k_done, k) if yaw == yaw_guess else k_done
            if not windows:
                continue
            t = time.perf_counter()
            c2d, st = self._search_windows(scan, windows)
            stats["bnb_time_s"] = stats.get("bnb_time_s", 0.0) + time.perf_counter() - t
            stats["nodes_visited"] = stats.get("nodes_visited", 0) + st.nodes_visited
            t = time.perf_counter()
            out.extend(self._refine(c2d, scan, scan_ndt, cells, skip=done, ordered=p.place_leaves_per_window > 0))
            stats["refine_time_s"] = stats.get("refine_time_s", 0.0) + time.perf_counter() - t
            stats["place_stage"] = i + 1
            stats["windows"] = len(windows)
            stats["regions_searched"] = st.regions  # the GROUP_M squares holding windows
            res = self._decide(list(out), {}, 0.0, scan_ndt, final=False)
            if res.verified or res.ambiguous:
                break  # found; or two places fit, which searching more would not change
        return out, stats

    def _search_windows(self, scan: ScanProjection, windows: list[Window]):
        """Branch and bound over the windows, one pyramid per group of nearby windows."""
        from blockloc.global_init.bnb import SearchStats

        p = self.params
        r = p.resolution_m
        top = min(p.pyramid_levels - 1, p.place_top_level)
        reach = float(np.hypot(*scan.xy.T).max()) + (1 << top) * r + 2 * r
        # Windows (best place first) in groups spanning at most GROUP_M: one pyramid crop each,
        # however large the map.
        groups: list[tuple[np.ndarray, np.ndarray, list[Window]]] = []
        for w in windows:
            c = np.asarray(w.center, float)
            for g in groups:
                lo, hi = np.minimum(g[0], c), np.maximum(g[1], c)
                if np.all(hi - lo <= GROUP_M):
                    g[0][:], g[1][:] = lo, hi
                    g[2].append(w)
                    break
            else:
                groups.append((c.copy(), c.copy(), [w]))
        cands: list[Candidate2D] = []
        total = SearchStats(0, 0.0, 0, 0, 0.0, 0.0)
        best = 0.0
        rank = {id(w): i for i, w in enumerate(windows)}
        for _, _, ws in groups:
            c = np.array([w.center for w in ws])
            half = 0.5 * max(w.size_m for w in ws) + reach
            lo = np.floor((c.min(axis=0) - half) / r).astype(np.int64) - 2
            hi = np.floor((c.max(axis=0) + half) / r).astype(np.int64) + 3
            try:
                pyr = self.map.pyramid(lo, hi)
            except GlobalInitError:
                continue
            # Leaves below ambiguity_score_ratio x the best matter neither as the answer nor as its
            # runner-up (_refine would not refine them): prune them, across groups too.
            c2d, st = search_windows(pyr, scan.xy, ws, p.place_top_k, p.use_s0, p.s0_ratio, p.min_score, p.nms_m,
                                     p.nms_deg, max_range=scan.max_range, keep_ratio=p.ambiguity_score_ratio,
                                     min_leaf_score=p.ambiguity_score_ratio * best, top_level=p.place_top_level,
                                     per_window_k=p.place_leaves_per_window)
            for c in c2d:
                c.window = rank[id(ws[c.window])] if c.window >= 0 else -1
            cands.extend(c2d)
            best = max([best] + [c.score for c in c2d])
            total = SearchStats(st.num_angles, st.angle_step_rad, total.num_roots + st.num_roots,
                                total.nodes_visited + st.nodes_visited, max(total.s0, st.s0),
                                total.time_s + st.time_s)
        total.regions = len(groups)
        cands = [c for c in cands if c.score >= p.ambiguity_score_ratio * best]
        if p.place_leaves_per_window > 0:
            # Best places first (the index's ranking sees free space, which the 2D score does not),
            # each window's leaves by score: a saturated window cannot take every refinement.
            cands.sort(key=lambda c: (c.window, -c.score))
        else:
            cands.sort(key=lambda c: -c.score)
        return cands[: p.place_top_k], total

    def _relocalize(self, scan: ScanProjection, scan_ndt: np.ndarray, theta_c: float, yaw_win: float, cells=None,
                    deadline: float = math.inf):
        """The regions' search (module docstring), region by region while before ``deadline``."""
        p = self.params
        w = p.reloc_window_m
        centers = self.map.region_centers(w)
        if len(centers) == 0:
            raise GlobalInitError("the map has no blocks/tiles to relocalize in")
        t = time.perf_counter()
        cheap = np.full(len(centers), -np.inf)
        for i, c in enumerate(centers):
            if time.perf_counter() >= deadline:
                break  # the regions scored so far come first
            cheap[i] = self._cheap_score(scan, c, w)
        order = np.argsort(-cheap, kind="stable")
        if p.max_regions > 0:
            order = order[: p.max_regions]
        t_cheap = time.perf_counter() - t
        all_cands: list[InitCandidate] = []
        stats: dict = {"regions": len(centers), "cheap_time_s": t_cheap, "regions_searched": 0}
        for k, i in enumerate(order):
            if time.perf_counter() >= deadline:
                stats["timed_out"] = True
                break
            # Regions overlap by the scan's reach, so a pose near a border is inside some window.
            cands, st = self._search_region(scan, scan_ndt, centers[i], w + 2.0 * p.resolution_m, theta_c, yaw_win,
                                            cells=cells)
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

    def _nearby_rival(self, best: InitCandidate, scan_ndt: np.ndarray) -> InitCandidate | None:
        """Another NDT optimum near the best that fits about as well, or None.

        NDT started from the best moved by ``probe_m`` along the map axes slides to the nearest other
        local optimum where the scan constrains a direction weakly (a corridor: walls fit along
        their length). One more than ``ambiguity_distance_m`` away, within the fitness margin and
        not significantly worse (:func:`better_fit` < ``ambiguity_z``) means the scan cannot tell
        where along that direction the body is: the result must not be verified. A rival is
        plausible only as a candidate is (as in ``_decide``): its above-ground structure fits too
        (seen on the real walk: optima 4.7 m off with fitness 0.55 whose structure did not fit, 0.50,
        kept two correct poses unverified).
        """
        p = self.params
        structure = getattr(self, "_structure_body", None)
        for d in p.probe_m:
            for dx, dy in ((d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d)):
                T0 = best.T_map_body.copy()
                T0[:2, 3] += (dx, dy)
                r = best.refiner.align(scan_ndt, T0)
                if not r.converged and np.all(np.isfinite(r.T_map_body)):
                    # out of iterations on its way (back to the best, or on to another optimum): an
                    # optimum is where it stops; one still sliding after this counts as a rival
                    r = best.refiner.align(scan_ndt, r.T_map_body)
                if not (np.all(np.isfinite(r.T_map_body)) and r.fitness >= p.min_fitness):
                    continue
                dist = float(np.linalg.norm(r.T_map_body[:3, 3] - best.T_map_body[:3, 3]))
                if dist <= p.ambiguity_distance_m or r.fitness < best.fitness - p.ambiguity_fitness_margin:
                    continue
                sfit = self._structure_fit(best.refiner, structure, r.T_map_body) if structure is not None else 1.0
                if sfit < p.min_structure_fitness:
                    log.debug("an NDT optimum %.2f m from the best (fitness %.2f) whose structure does not fit "
                              "(%.2f): no rival", dist, r.fitness, sfit)
                    continue
                rival = InitCandidate(r.T_map_body, 0.0, r.fitness, r.converged, False, T0, r.ndt_score, sfit,
                                      refiner=best.refiner)
                if better_fit(scan_ndt, best, rival) < p.ambiguity_z:
                    log.info("a rival NDT optimum %.2f m from the best fits about as well", dist)
                    return rival
        return None

    def _decide(self, cands: list[InitCandidate], stats: dict, elapsed: float,
                scan_ndt: np.ndarray | None = None, final: bool = True) -> InitResult:
        """The result from refined candidates (see the module docstring). With ``scan_ndt`` (the
        points refined, body frame), a plausible rival far from the best is no ambiguity when the
        best explains the scan significantly better (:func:`better_fit`). ``final``: drop the
        candidates' NDT targets."""
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
                    if scan_ndt is not None and best.refiner is not None and c.refiner is not None \
                            and better_fit(scan_ndt, best, c) >= p.ambiguity_z:
                        continue
                    ambiguous = True
                    break
        if final and best.verified and not ambiguous and scan_ndt is not None and best.refiner is not None:
            rival = self._nearby_rival(best, scan_ndt)
            if rival is not None:
                ambiguous = True
                cands.append(rival)
        if final:
            for c in cands:
                c.refiner = None
        if ambiguous:
            log.warning("global init is ambiguous: two verified candidates more than %.1f m apart",
                        p.ambiguity_distance_m)
        return InitResult(best.T_map_body, best.score, best.fitness, cands, ambiguous, elapsed,
                          best.verified and not ambiguous, stats)


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


def better_fit(points_body: np.ndarray, a: InitCandidate, b: InitCandidate, block_m: float = 2.0) -> float:
    """How significantly candidate ``a`` explains the scan better than ``b``: a z statistic.

    The points (N, 3), body frame, fall in blocks of ``block_m`` (body xy); per block, d = inliers at
    ``a`` (against a's map) - inliers at ``b`` (against b's). Under "equally good", d is symmetric
    about 0 and sum(d) / sqrt(sum(d^2)) is about standard normal (a sign-flip test; blocks, not
    points, because neighbouring points on one surface pass or fail together). Large: ``a`` fits
    better; around 0: the scan cannot tell them apart.
    """
    pts = np.asarray(points_body, float).reshape(-1, 3)
    keys = np.floor(pts[:, :2] / block_m).astype(np.int64)
    _, block = np.unique(keys, axis=0, return_inverse=True)
    block = block.reshape(-1)
    d = []
    for k in range(int(block.max()) + 1 if len(block) else 0):
        q = pts[block == k]
        d.append(len(q) * (a.refiner.inlier_ratio(q, a.T_map_body) - b.refiner.inlier_ratio(q, b.T_map_body)))
    d = np.asarray(d)
    den = math.sqrt(float(np.sum(d * d)))
    return float(np.sum(d) / den) if den > 0 else 0.0


def pose_error(T_est: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) between two (4, 4) poses."""
    from blockloc.geometry import rotation_angle

    d = inv_T(T_ref) @ T_est
    return float(np.linalg.norm(T_est[:3, 3] - T_ref[:3, 3])), float(np.degrees(rotation_angle(d[:3, :3])))
