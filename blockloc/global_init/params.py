"""Global initialization's settings, each declared once.

:class:`GlobalInitParams` IS the config's ``global_init`` section (``blockloc.config`` imports
it): the YAML keys are its fields, with their defaults and bounds. :class:`InitParams`, what the
localizer takes, extends it with the knobs no config exposes.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from blockloc.bounds import ANGLE_WINDOW, COUNT, FRACTION, NON_NEGATIVE, POSITIVE, PROBABILITY, bounded


@dataclass
class GlobalInitParams:
    """The ``global_init`` section: search windows, projection, branch and bound, place index,
    verification (``verify``). ``window_m`` / ``yaw_window_deg``: the hinted search's window, read
    by the caller that passes them to ``localize``."""

    window_m: float = bounded(40.0, POSITIVE)
    yaw_window_deg: float = bounded(360.0, ANGLE_WINDOW)
    resolution_m: float = bounded(0.5, POSITIVE)  # 2D cell of the branch and bound (NDT refines afterwards)
    pyramid_levels: int = bounded(6, COUNT)  # top level: a sliding max over 2^5 cells = 16 m
    height_band_m: tuple[float, float] = (0.3, 3.0)  # projected points: height above local ground
    projection: str = "band"  # band (height band above local ground) | all (plain occupancy)
    max_range_m: float = bounded(60.0, POSITIVE)  # scan cells used by the 2D search (sets the angular step)
    top_k: int = bounded(5, COUNT)
    use_s0: bool = True  # greedy initial score S0 (block-map paper); False: plain BBS
    s0_ratio: float = bounded(0.9, FRACTION)  # prune below this fraction of S0
    # NDT inlier ratio for a verified match (sim: true 0.8-0.97, false <= 0.61)
    min_fitness: float = bounded(0.75, PROBABILITY)
    # same for the above-ground points alone (true >= 0.9, false <= 0.37)
    min_structure_fitness: float = bounded(0.6, PROBABILITY)
    # Scored on what overlaps (refine.Footprint): inlier ratios and the static-band coverage count
    # only scan points / bins where the map holds data (levelled cells of this size; 0: every point
    # counts), and at least min_overlap of the scan's points must fall there for a verified match
    # (a scan at the map's edge, half outside it)
    footprint_cell_m: float = bounded(1.0, NON_NEGATIVE)
    # A best whose static-band coverage could not be judged (an open stretch: only the NDT fit
    # verified it) is a search's answer only as the clear best (``verify.clear_best``): inlier ratio
    # and above-ground inlier ratio at least these, and an inlier ratio this much above every other
    # candidate's more than ambiguity_distance_m away. Campus, both maps, the ten draws of 2026-12-07:
    # the right bests of this kind fit 0.899-0.931 / 0.82-0.86 with margins 0.093-0.135 (frames
    # 16730, 16735, 39798, 25037, 25061); nominal frame 39893, a place 465 m off, fit 0.776 / 0.61,
    # another candidate 0.781 (it was verified before this rule)
    unjudged_clear_best: bool = True  # false: such a best is a search's answer as any verified one
    unjudged_end_min_fitness: float = bounded(0.88, FRACTION)
    unjudged_end_min_structure_fitness: float = bounded(0.75, FRACTION)
    unjudged_end_margin: float = bounded(0.05, NON_NEGATIVE)
    ambiguity_distance_m: float = bounded(0.5, NON_NEGATIVE)  # rivals farther than this (NDT merges closer ones)
    ndt_resolution_m: float = bounded(1.0, POSITIVE)
    reloc_window_m: float = bounded(100.0, POSITIVE)  # regions of the no-hint relocalization (the place index's fallback)
    # No-hint relocalization through the map's place index (blockloc/global_init/place_index.py).
    use_place_index: bool = True
    place_candidates: tuple[int, ...] = (8, 64, 256)  # places whose windows are searched, stage by stage
    # window around each place (x, y), metres: a scan matches places within place_tolerance_m (1.5 m) of it and
    # places lie 2-3 m apart, so +-4 m holds the true pose of a matching place. 12 m windows cost twice the
    # branch and bound (campus, stage 4: 15M nodes, 1.7 s; 8 m: 8.9M, 0.8 s); chosen on the campus --rng 7 draws
    # of both maps, held out on four other draws each and the small world (docs/bench/global_init.md)
    place_window_m: float = bounded(8.0, POSITIVE)
    place_yaw_window_deg: float = bounded(16.0, ANGLE_WINDOW)  # around each place's yaw guess
    place_band_m: tuple[float, float] = (2.0, 4.0)  # static band: above people, cars and fences
    place_max_range_m: float = bounded(63.0, POSITIVE)
    place_spacing_m: float = bounded(3.0, POSITIVE)  # grid of places over the drivable area
    place_tolerance_m: float = bounded(1.5, POSITIVE)  # a scan this far from a place still matches it
    place_max_offset_m: float = bounded(20.0, POSITIVE)  # grid places within this of a mapping keyframe
    whole_map_fallback: bool = True  # then the regions of reloc_window_m, as without an index
    # no-hint search budget, seconds (0: none); then "not found" (verified false) rather than minutes;
    # numba's compiling (a first search after an install) does not count (``jit.Deadline``)
    max_search_s: float = bounded(10.0, NON_NEGATIVE)
    # Verification at the refined pose, in the static band (both the hinted and the no-hint path).
    min_coverage: float = bounded(0.9, FRACTION)  # scan structure the map covers (true poses: >= 0.91 on campus)
    max_see_through: float = bounded(0.35, FRACTION)  # share of the map's visible structure the scan saw through (true: <= 0.25)
    ambiguity_z: float = bounded(2.5, NON_NEGATIVE)  # a rival is no ambiguity when the best fits this significantly better
    # The structure test on the static band (>= place_band_m[0] above ground: above people and cars)
    # when the scan has enough of it; false: on the projection band (height_band_m) always (indoors,
    # blockloc/presets/handheld.yaml says why).
    structure_from_static: bool = True


@dataclass
class InitParams(GlobalInitParams):
    """The localizer's parameters: the ``global_init`` section's fields (inherited, declared once
    there) and the knobs no config exposes. Build from a config with :meth:`from_config`."""

    max_scan_cells: int = 1500
    min_scan_cells: int = 50
    min_score: float = 0.05
    nms_m: float = 1.0
    nms_deg: float = 5.0
    probe_m: tuple[float, ...] = (1.0, 2.0)  # NDT restarts from the best moved this far look for rivals
    ambiguity_fitness_margin: float = 0.05
    # the final decision climbs (``GlobalLocalizer._climb``): rounds, rivals climbed besides the best,
    # and the NDT score per point an optimum nearby must gain to count as better
    climb_rounds: int = 3
    climb_rivals: int = 3
    climb_min_gain: float = 0.01
    # a final decision first aligns once more each plausible candidate NDT left unconverged, from
    # where it stopped, and judges the optimum it settles at instead (``GlobalLocalizer._settle``)
    settle_unconverged: bool = True
    scan_voxel_m: float = 0.5
    max_ndt_points: int = 3000
    # a verified pose the scan holds loosely (NDT restarts around it end more than one_optimum_m away) is
    # aligned once more on the scan's points, one per whole_scan_voxel_m voxel, against the map within
    # whole_scan_range_m around it (a levelled box; ``verify.on_whole_scan``): the search's refinement
    # sees max_ndt_points within max_range_m against refine_range_m, and along a street the far
    # structure holds the pose. Campus, nominal-mounting map: 65 m as good as 80 m at half the target's
    # cost; chosen on one draw, two held out (docs/bench/global_init.md). whole_scan_voxel_m 0: off
    whole_scan_voxel_m: float = 0.5
    whole_scan_range_m: float = 65.0
    # ... and, after the search went on, a far ambiguity among at most this many candidates is
    # judged on the whole scan (``verify.whole_scan_decides``)
    whole_scan_max_candidates: int = 8
    ambiguity_score_ratio: float = 0.8  # once one is verified, refine others only above this x best
    # a stage whose verified candidates leave the result ambiguous does not end the search: without a
    # hint the place stages go on (``GlobalLocalizer._search_on``), with one the window's branch and
    # bound (``hinted``); the decision judges everything found
    search_on_doubt: bool = True
    # ... and neither does a verified best whose static-band coverage was not judged (too few bins:
    # only its NDT fit verified it; ``GlobalLocalizer._decide_unless_doubted``); where the search
    # ends with such a best, it is the answer only as the clear best (``unjudged_end_*``), else the
    # result is ambiguous (``GlobalLocalizer._decide``); a later scan confirms one only on a strong fit
    search_on_unjudged: bool = True
    # ... unless it fits strongly: inlier ratio and above-ground inlier ratio at least these. Campus,
    # no hint, 12 draws of 100 frames over both maps: the 86 right bests verified with coverage not
    # judged fit 0.905-0.97; none of the 2,570 wrong candidates (> 1 m or 5 deg off) whose coverage
    # was not judged reached both (closest: 0.93 / 0.65 and 0.87 / 0.94 a few metres along a street,
    # 0.87 / 0.75 537 m off). Chosen on 8 draws, 4 held out (docs/bench/global_init.md)
    unjudged_min_fitness: float = 0.90
    unjudged_min_structure_fitness: float = 0.85
    # ... and the decision after the search went on takes the scan's every point (within max_range_m):
    # a rival NDT on them brings back to the best's own optimum (within one_optimum_m / _deg, both
    # converged, the best's coverage judged) is no ambiguity (``verify.one_optimum``); false: as before
    resolve_on_every_point: bool = True
    one_optimum_m: float = 0.1
    one_optimum_deg: float = 0.5
    refine_range_m: float = 50.0
    # refinement targets assembled from per-entry voxel statistics kept between searches, at most
    # this many MB (``targets.TargetCache``; 0: every target built from its points)
    target_cache_mb: float = 1024.0
    max_regions: int = 0  # 0: every region of the map
    num_threads: int = 2  # the registration section's
    # refinement targets built, candidates refined and the final NDT restarts run side by side in
    # this many threads (the registration section's num_threads); 1: one after another. Same
    # results either way (``GlobalLocalizer._map``). Quiet machine, campus no hint: median 0.26 s
    # with 2 against 0.35 s with 1 (docs/bench/global_init.md, the lead's quiet re-measure); with
    # the second core busy elsewhere, 2 gains nothing
    refine_workers: int = 2
    # no-hint relocalization through the place index
    place_all_yaw_candidates: int = 2  # the third stage: this many first places at every yaw (0: none)
    place_flip_open: bool = True  # no hint: an open place's window also at its yaw guess reversed
    place_top_k: int = 6  # leaves refined per stage
    place_later_top_k: int = 12  # the same after the first stage (each way: best places, best 2D scores)
    # the best leaves of each window (0: one top place_top_k over all windows, by 2D score)
    place_leaves_per_window: int = 1
    # the hinted search's place stages (``hinted``): a window holds a few dozen places, and the true
    # one ranked first in it on 40 of 40 small-world frames (seed 2); later stages take every place in it
    hint_place_candidates: tuple[int, ...] = (4, 64, 256)
    place_top_level: int = 3  # its roots' level (2^3 cells = 4 m at 0.5 m: tight bounds in small windows)
    # static-band consistency at the refined pose (verification)
    consistency_tolerance_m: float = 0.75
    min_consistency_bits: int = 20
    min_static_points: int = 300  # fewer static-band points: the structure test uses the low band
    # (footprint_cell_m: in the section above) the map's levelled cells of footprint_cell_m count
    # where they hold at least footprint_min_share of the median non-empty cell's map points: ground
    # seen well, not a few returns from afar, where NDT's Gaussians are poor
    footprint_min_share: float = 0.25
    min_overlap: float = 0.3

    @property
    def projection_params(self):
        """The 2D projection (``blockloc.global_init.maps.ProjectionParams``) of the search."""
        from blockloc.global_init.maps import ProjectionParams

        return ProjectionParams(self.resolution_m, self.pyramid_levels, tuple(self.height_band_m), self.projection)

    @property
    def place_index_params(self):
        """The place index's parameters (``PlaceIndexParams.from_config`` of these)."""
        from blockloc.global_init.place_descriptors import PlaceIndexParams

        return PlaceIndexParams.from_config(self)

    @classmethod
    def from_config(cls, gi: GlobalInitParams, registration=None) -> "InitParams":
        """The section ``gi`` field by field, ``num_threads`` and ``refine_workers`` from the
        registration section's ``num_threads``."""
        kw = {f.name: getattr(gi, f.name) for f in fields(GlobalInitParams)}
        if registration is not None:
            kw["num_threads"] = kw["refine_workers"] = registration.num_threads
        return cls(**kw)
