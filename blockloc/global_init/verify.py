"""Verification of global-init candidates and the decision over them.

A refined candidate is verified when more than a good NDT fit holds, because a wrong place with
similar structure can fit well (:func:`passes`): NDT converged, its inlier ratio >= ``min_fitness``,
the above-ground points' inlier ratio >= ``min_structure_fitness`` (those of the projection band
or, when the scan has ``min_static_points`` of them and ``structure_from_static``, the points at or
above the static band's bottom: either set may pass, :func:`structure_sets`), and, in the place
index's static band, the scan's structure covered by the map (>= ``min_coverage``) and the map's
structure not where the scan saw through (<= ``max_see_through`` of the bins seen through).

:func:`decide` turns refined candidates into an :class:`InitResult`: the best verified candidate
by NDT score per point wins; another verified candidate more than ``ambiguity_distance_m`` away
that fits nearly as well (:func:`better_fit` below ``ambiguity_z``), or another NDT optimum near the
best (:func:`nearby_rival`), makes the result ambiguous, and an ambiguous result is never
reported as verified. Given the scan's every point, a rival NDT on them brings to the best's own
optimum is no rival (:func:`one_optimum`: the thinned scan's two optima are one).

The thresholds are the ``global_init`` section's (:class:`Thresholds` copies them); ``bench/real.py``
replays verification with other thresholds through :func:`passes` too.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from blockloc.geometry import inv_T, rotation_angle

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Thresholds:
    """What a refined candidate must reach to be verified (fractions in [0, 1]); the defaults are
    the ``global_init`` section's (``Thresholds.of(GlobalInitConfig())``)."""

    min_fitness: float
    min_structure_fitness: float
    min_coverage: float
    max_see_through: float

    @classmethod
    def of(cls, params) -> "Thresholds":
        """The thresholds of a ``global_init`` section or ``InitParams``, field by field."""
        return cls(params.min_fitness, params.min_structure_fitness, params.min_coverage, params.max_see_through)


def fit_passes(converged: bool, finite: bool, fitness: float, structure_fitness: float, th: Thresholds) -> bool:
    """The NDT part of verification: converged to a finite pose, inlier ratios above the floors."""
    return bool(converged and finite and fitness >= th.min_fitness and structure_fitness >= th.min_structure_fitness)


def consistency_passes(coverage: float, see_through: float, th: Thresholds) -> bool:
    """The static-band part: NaN (too few bins observed to judge) passes."""
    if math.isfinite(coverage) and coverage < th.min_coverage:
        return False
    return not (math.isfinite(see_through) and see_through > th.max_see_through)


def consistency_judged(cand) -> bool:
    """Whether the static-band coverage test judged ``cand`` (an :class:`InitCandidate`): enough of
    the scan's static-band bins to judge by (NaN: an open stretch; only the NDT fit verified it)."""
    return bool(math.isfinite(cand.coverage))


def plausible(cand, p) -> bool:
    """Whether ``cand`` (an :class:`InitCandidate`) fits well enough to count as a rival (and, in
    ``second_scan``, as a hypothesis): fitness and structure fitness above ``p``'s floors
    (``InitParams``), converged or not."""
    return bool(cand.fitness >= p.min_fitness and cand.structure_fitness >= p.min_structure_fitness)


def fits_strongly(cand, min_fitness: float, min_structure_fitness: float) -> bool:
    """Whether ``cand`` (an :class:`InitCandidate`) fits well above the verification floors: inlier
    ratio >= ``min_fitness`` and above-ground inlier ratio >= ``min_structure_fitness`` (fractions).
    What lets a best stand on its NDT fit alone where its coverage was not judged."""
    return bool(cand.fitness >= min_fitness and cand.structure_fitness >= min_structure_fitness)


def stands_alone(cand, p) -> bool:
    """Whether ``cand`` (an :class:`InitCandidate`, verified) may end a search on its own: its
    static-band coverage was judged (:func:`consistency_judged`), or it fits strongly
    (:func:`fits_strongly` with ``p.unjudged_min_fitness`` and ``p.unjudged_min_structure_fitness``;
    ``p``: ``InitParams``). Else only the NDT fit verified it, and a wrong place of an open stretch
    fits well enough: the search goes on (``search_on_unjudged``)."""
    return consistency_judged(cand) or fits_strongly(cand, p.unjudged_min_fitness, p.unjudged_min_structure_fitness)


def clear_best(cands: list, p) -> bool:
    """Whether the best of ``cands`` (:class:`InitCandidate` list, the decision's, best first) is the
    answer of a search that ended with it, though only its NDT fit verified it, not strongly
    (:func:`stands_alone` false): it fits well (``p.unjudged_end_min_fitness`` and
    ``p.unjudged_end_min_structure_fitness``) and better by ``p.unjudged_end_margin`` in inlier ratio
    than every other candidate more than ``p.ambiguity_distance_m`` from it, verified or not (the
    scan fits there clearly better than at any other place searched; a wrong place of an open
    stretch fits about as well as others do)."""
    best = cands[0]
    if not fits_strongly(best, p.unjudged_end_min_fitness, p.unjudged_end_min_structure_fitness):
        return False
    others = [c.fitness for c in cands[1:] if np.isfinite(c.fitness)
              and np.linalg.norm(c.T_map_body[:3, 3] - best.T_map_body[:3, 3]) > p.ambiguity_distance_m]
    return all(f <= best.fitness - p.unjudged_end_margin for f in others)


def passes(converged: bool, fitness: float, structure_fitness: float, coverage: float, see_through: float,
           th: Thresholds, finite: bool = True) -> bool:
    """Whether a refined candidate with these measurements is verified under ``th``."""
    return fit_passes(converged, finite, fitness, structure_fitness, th) and consistency_passes(coverage, see_through, th)


def structure_sets(projection_structure: np.ndarray, static_body: np.ndarray | None, min_static_points: int,
                   structure_from_static: bool) -> list[np.ndarray]:
    """The scan's above-ground point sets (N, 3), body frame, the structure test tries in turn.

    Ground points fit the ground almost anywhere: the structure above it must fit too. Judged on
    the static structure (at or above the place band's bottom) when the scan has enough of it:
    people, cars and bushes near the sensor fill the low band with points no map holds (seen: 0.16
    of the low points within 10 m fit at the true pose). Either band may pass: tree crowns dominate
    the static band where the foliage changed between sessions (seen on campus: 0.43-0.51 of it fit
    at true poses whose projection band fit 0.98), as crowds dominate the low band.
    """
    if structure_from_static and static_body is not None and len(static_body) >= min_static_points:
        return [static_body, projection_structure]
    return [projection_structure]


def structure_fit(refiner, structures: list[np.ndarray], T_map_body: np.ndarray, min_structure_fitness: float) -> float:
    """The best inlier ratio of the point sets at a pose; the first set passing the test ends it."""
    best = 0.0
    for pts in structures:
        best = max(best, refiner.inlier_ratio(pts, T_map_body))
        if best >= min_structure_fitness:
            break
    return best


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
    overlap: float = 1.0  # share of the scan's points where the map holds data (refine.Footprint)
    # (T_start, RefineResult) of the NDT restarts around it (:func:`probe_optima`), once made
    probes: list | None = field(default=None, repr=False, compare=False)
    # whether a final decision aligned it once more from where NDT left it unconverged (``_settle``)
    settle_tried: bool = field(default=False, repr=False, compare=False)


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


def nearby_rival(best: InitCandidate, scan_ndt: np.ndarray, structures: list[np.ndarray] | None,
                 p, dismiss=None) -> InitCandidate | None:
    """Another NDT optimum near the best that fits about as well, or None.

    NDT started from the best moved by ``probe_m`` along the map axes slides to the nearest other
    local optimum where the scan constrains a direction weakly (a corridor: walls fit along
    their length). One more than ``ambiguity_distance_m`` away, within the fitness margin and
    not significantly worse (:func:`better_fit` < ``ambiguity_z``) means the scan cannot tell
    where along that direction the body is: the result must not be verified. A rival is
    plausible only as a candidate is (as in :func:`decide`): its above-ground structure fits too
    (seen on the real walk: optima 4.7 m off with fitness 0.55 whose structure did not fit, 0.50,
    kept two correct poses unverified). ``p``: the localizer's ``InitParams``; ``dismiss(rival)``
    true: that optimum is no rival after all (:func:`one_optimum`), the next one is looked for.
    """
    probes = best.probes if best.probes is not None else probe_optima(best, scan_ndt, p.probe_m, lazy=True)
    for T0, r in probes:
        if not (np.all(np.isfinite(r.T_map_body)) and r.fitness >= p.min_fitness):
            continue
        dist = float(np.linalg.norm(r.T_map_body[:3, 3] - best.T_map_body[:3, 3]))
        if dist <= p.ambiguity_distance_m or r.fitness < best.fitness - p.ambiguity_fitness_margin:
            continue
        sfit = (structure_fit(best.refiner, structures, r.T_map_body, p.min_structure_fitness)
                if structures is not None else 1.0)
        if sfit < p.min_structure_fitness:
            log.debug("an NDT optimum %.2f m from the best (fitness %.2f) whose structure does not fit "
                      "(%.2f): no rival", dist, r.fitness, sfit)
            continue
        rival = InitCandidate(r.T_map_body, 0.0, r.fitness, r.converged, False, T0, r.ndt_score, sfit,
                              refiner=best.refiner)
        if better_fit(scan_ndt, best, rival) < p.ambiguity_z:
            if dismiss is not None and dismiss(rival):
                continue
            log.info("a rival NDT optimum %.2f m from the best fits about as well", dist)
            return rival
    return None


def probe_optima(cand: InitCandidate, scan_ndt: np.ndarray, probe_m, lazy: bool = False, mapper=None):
    """The NDT optima reached from ``cand`` (its ``refiner``) moved by each of ``probe_m`` (m)
    along +-x and +-y of the map: (T_start (4, 4), ``Refiner.align``'s result) each, in that
    order; ``lazy``: a generator (the caller may stop early); ``mapper(fn, starts)``: runs ``fn``
    over the starts, in order (e.g. side by side in threads; default: one after another)."""

    def start(dx: float, dy: float) -> np.ndarray:
        T0 = cand.T_map_body.copy()
        T0[:2, 3] += (dx, dy)
        return T0

    def run(T0: np.ndarray):
        # an optimum is where the settled run stops; one still sliding after it counts as a rival
        return T0, cand.refiner.align_settled(scan_ndt, T0)

    starts = (start(dx, dy) for d in probe_m for dx, dy in ((d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d)))
    if lazy:
        return (run(T0) for T0 in starts)
    return list(mapper(run, list(starts))) if mapper is not None else [run(T0) for T0 in starts]


def decide(cands: list[InitCandidate], stats: dict, elapsed: float, p, scan_ndt: np.ndarray | None = None,
           final: bool = True, structures: list[np.ndarray] | None = None, drop_targets: bool = True,
           dense_points: np.ndarray | None = None, whole=None) -> InitResult:
    """The result from refined candidates (module docstring). With ``scan_ndt`` (the points
    refined, body frame), a plausible rival far from the best is no ambiguity when the best
    explains the scan significantly better (:func:`better_fit`). ``final``: look for a nearby
    rival of a verified best (the scan's ``structures`` test it) and drop the candidates' NDT
    targets (``drop_targets`` False: keep them for a later decision). ``dense_points`` (M, 3),
    body frame: the scan's every point; a rival (far or nearby) NDT on them brings to the best's
    own optimum is none (:func:`one_optimum`). ``whole``: the scan's whole reach
    (``refine.WholeScan``; None: not used): after the search went on (``dense_points`` given), a
    far ambiguity that it settles is none (:func:`whole_scan_decides`); a final decision that drops
    its targets stands (:func:`stand`: a verified best held loosely aligned once more with it).
    ``p``: the localizer's ``InitParams``."""
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
    dense_best: list = []  # the best's optimum on dense_points, once aligned

    def same(rival: InitCandidate) -> bool:
        return dense_points is not None and one_optimum(dense_points, best, rival, p, dense_best, whole)

    if best.verified:
        for c in cands[1:]:
            far = np.linalg.norm(c.T_map_body[:3, 3] - best.T_map_body[:3, 3]) > p.ambiguity_distance_m
            # Unconverged candidates count too: fitting as well elsewhere is what matters.
            if plausible(c, p) and far and c.fitness >= best.fitness - p.ambiguity_fitness_margin:
                if scan_ndt is not None and best.refiner is not None and c.refiner is not None \
                        and better_fit(scan_ndt, best, c) >= p.ambiguity_z:
                    continue
                if c.refiner is not None and same(c):
                    continue
                ambiguous = True
                break
    dismiss = same if dense_points is not None else None  # what makes a nearby rival none
    if final and ambiguous and dense_points is not None and whole is not None:
        group = [best] + [c for c in cands[1:] if plausible(c, p) and c.fitness >= best.fitness - p.ambiguity_fitness_margin
                          and np.linalg.norm(c.T_map_body[:3, 3] - best.T_map_body[:3, 3]) > p.ambiguity_distance_m]
        decided = whole_scan_decides(group, whole, p)
        if decided is not None:
            winner, run = decided
            stats["whole_scan_decided"] = True
            cands = [winner] + [c for c in cands if c is not winner]
            best, ambiguous = winner, False
            dismiss = lambda rival: whole_scan_beats(run, rival, whole, p)  # noqa: E731  (nearby rivals too)
    if final and best.verified and not ambiguous and scan_ndt is not None and best.refiner is not None:
        rival = nearby_rival(best, scan_ndt, structures, p, dismiss=dismiss)
        if rival is not None:
            ambiguous = True
            cands.append(rival)
    if ambiguous:
        log.warning("global init is ambiguous: two verified candidates more than %.1f m apart",
                    p.ambiguity_distance_m)
    res = InitResult(best.T_map_body, best.score, best.fitness, cands, ambiguous, elapsed,
                     best.verified and not ambiguous, stats)
    if final and drop_targets:
        stand(res, whole, p)
    return res


def stand(res: InitResult, whole, p) -> InitResult:
    """A decision that stands (no later decision judges its candidates again): a verified best is
    aligned on the scan's whole reach where the scan holds it loosely (:func:`on_whole_scan`, with
    ``whole``, a ``refine.WholeScan``; None: not), then every candidate's NDT target is dropped. ``res`` is changed in
    place and returned."""
    best = res.candidates[0] if res.candidates else None
    if res.verified and whole is not None and best is not None and best.refiner is not None:
        t = time.perf_counter()
        res.stats["whole_scan_moved"] = on_whole_scan(best, whole, p)
        res.T_map_body = best.T_map_body
        res.stats["whole_scan_s"] = time.perf_counter() - t
        res.time_s += res.stats["whole_scan_s"]
    for c in res.candidates:
        c.refiner = None
    if whole is not None:
        whole.release()  # the whole scan's target too: a localizer keeps nothing of a search between calls
    return res


def whole_scan_decides(group: list[InitCandidate], whole, p) -> tuple[InitCandidate, InitCandidate] | None:
    """Which of a best and its far rivals (``group``: plausible candidates more than
    ``ambiguity_distance_m`` apart from the best, the best first) the scan's whole reach decides
    for, with its whole-scan run (a candidate holding that target), or None: still ambiguous.

    Each is aligned on the whole scan against the map around it (``whole``, a ``refine.WholeScan``).
    The one with the highest NDT score per point wins when
    - every run converged, within ``ambiguity_distance_m`` of its candidate or at another's run
      (within ``one_optimum_m`` / ``_deg``: one optimum, counted once);
    - the winner was verified by the search and fits the whole scan strongly (inlier ratio at least
      ``unjudged_min_fitness``, the floor a best stands on without coverage);
    - it explains the whole scan significantly better than each other run more than
      ``ambiguity_distance_m`` from its own (:func:`better_fit` at least ``ambiguity_z``, each
      against its own target).
    At most ``whole_scan_max_candidates`` are judged (more: None). The winner's pose becomes its
    whole-scan run's; a nearby rival of it is then judged the same way (:func:`whole_scan_beats`).

    Why: the search ranks on a sample of the near scan. Campus, defaults' map ``--rng 41``, frame
    47154: the true place verified 0.07 m off, outranked by a wrong one 158 m off (NDT score per
    point 2.01 against 1.84, fitness 0.84 against 0.92); on the whole scan 1.66 against 1.93,
    fitness 0.75 against 0.95. Of the wrong places in the campus's ambiguous frames none fit the
    whole scan above 0.84 but one 10.8 m along a street (0.92), which the true place there beat."""
    if len(group) < 2 or len(group) > p.whole_scan_max_candidates:
        return None
    runs: list[tuple[InitCandidate, InitCandidate]] = []  # (candidate, its whole-scan run)
    for c in group:
        run = _whole_run(c, whole)
        if run is None:
            return None
        if any(_one(run, o, p) for _, o in runs):
            continue  # the whole scan brought it to one found already: one optimum
        if float(np.linalg.norm(run.T_map_body[:3, 3] - c.T_map_body[:3, 3])) > p.ambiguity_distance_m:
            return None  # to a place no candidate holds
        runs.append((c, run))
    c, w = max(runs, key=lambda cw: cw[1].ndt_score)
    if not c.verified or w.fitness < p.unjudged_min_fitness:
        return None
    if any(better_fit(whole.points, w, o) < p.ambiguity_z for _, o in runs
           if np.linalg.norm(o.T_map_body[:3, 3] - w.T_map_body[:3, 3]) > p.ambiguity_distance_m):
        return None
    log.info("the whole scan decides an ambiguity of %d candidates (fitness %.2f, score per point %.2f)",
             len(group), w.fitness, w.ndt_score)
    c.T_map_body = w.T_map_body
    return c, w


def _whole_run(c: InitCandidate, whole) -> InitCandidate | None:
    """``c`` aligned on the whole scan (``whole``, a ``refine.WholeScan``) as a candidate holding
    that target, or None (no map there, not converged)."""
    r = whole.align(c.T_map_body)
    if r is None or not r.converged or not np.all(np.isfinite(r.T_map_body)):
        return None
    return InitCandidate(r.T_map_body, c.score, r.fitness, True, c.verified, ndt_score=r.ndt_score,
                         refiner=whole.refiner_at(c.T_map_body))


def whole_scan_beats(run: InitCandidate, rival: InitCandidate, whole, p) -> bool:
    """Whether the whole scan's run of a decided best (``run``, :func:`whole_scan_decides`) leaves
    ``rival`` no ambiguity: the rival's own whole-scan run comes back within
    ``ambiguity_distance_m`` of it, or ``run`` explains the whole scan significantly better
    (:func:`better_fit` at least ``ambiguity_z``). A rival the whole scan cannot align stays one."""
    r = _whole_run(rival, whole)
    if r is None:
        return False
    if float(np.linalg.norm(r.T_map_body[:3, 3] - run.T_map_body[:3, 3])) <= p.ambiguity_distance_m:
        return True
    return better_fit(whole.points, run, r) >= p.ambiguity_z


def loosely_held(best: InitCandidate, p) -> bool:
    """Whether the scan holds ``best`` loosely: of the NDT restarts around it (``best.probes``,
    :func:`probe_optima`; False when none were run) that converged to its own place (within
    ``ambiguity_distance_m``), one ended more than ``one_optimum_m`` from it, so the objective is
    flat in some direction (along a street, an open stretch). No new threshold: one_optimum_m is
    what makes two optima one (:func:`one_optimum`)."""
    if not best.probes:
        return False
    for _, r in best.probes:
        if r.converged and np.all(np.isfinite(r.T_map_body)):
            d = float(np.linalg.norm(r.T_map_body[:3, 3] - best.T_map_body[:3, 3]))
            if p.one_optimum_m < d <= p.ambiguity_distance_m:
                return True
    return False


def on_whole_scan(best: InitCandidate, whole, p) -> bool:
    """Align a verified best the scan holds loosely (:func:`loosely_held`) once more, on the scan's
    whole reach: ``whole.align(T_map_body)`` (a ``refine.WholeScan``: the scan's points one per
    ``whole_scan_voxel_m`` voxel against the map ``whole_scan_range_m`` around, where the search
    refines a sample of ``max_ndt_points`` within ``max_range_m`` against ``refine_range_m``)
    returns a ``RefineResult`` or None. The pose moves there
    (``best.T_map_body``; its verification figures stay those of the search) when that run
    converged to the same place, within ``ambiguity_distance_m`` (farther would be another place,
    which verification did not judge), with an inlier ratio of at least ``min_fitness``. Returns
    whether it moved.

    Why: along a street the near scan leaves the pose where the map's own error puts it (on the
    campus map built with the nominal mounting, 0.3 m off), and the far structure holds it: the
    four verified poses 0.31-0.37 m off in two draws of 100 frames came to 0.05-0.15 m
    (docs/bench/global_init.md). Only loosely held poses: the wider target costs 58-145 ms."""
    if not loosely_held(best, p):
        return False
    r = whole.align(best.T_map_body)
    if r is None:
        return False
    moved = float(np.linalg.norm(r.T_map_body[:3, 3] - best.T_map_body[:3, 3])) if np.all(
        np.isfinite(r.T_map_body)) else math.inf
    if not (r.converged and moved <= p.ambiguity_distance_m and r.fitness >= p.min_fitness):
        log.debug("the whole scan's alignment kept the verified pose (converged %s, %.2f m, fitness %.2f)",
                  r.converged, moved, r.fitness)
        return False
    best.T_map_body = r.T_map_body
    return True


def settle_once_more(refiner, points: np.ndarray, r):
    """``r`` (what has ``converged`` and ``T_map_body``: a ``Refiner`` result or a candidate), or,
    when NDT left it unconverged, ``refiner.align_settled`` of ``points`` (M, 3), body frame, from
    where it stopped, if that converges. Along a street the objective is flat and NDT still slides
    there after its iterations (defaults' map, 14583: a rival 0.07 m from the best's optimum after
    60 iterations converged 0.04 m from it once more; nominal map 20361 and 14599: the best's own
    run)."""
    if r.converged or not np.all(np.isfinite(r.T_map_body)):
        return r
    again = refiner.align_settled(points, r.T_map_body)
    return again if again.converged and np.all(np.isfinite(again.T_map_body)) else r


def one_optimum(dense_points: np.ndarray, best: InitCandidate, rival: InitCandidate, p,
                dense_best: list | None = None, whole=None) -> bool:
    """Whether ``rival`` is the best's own optimum: NDT on the scan's every point ``dense_points``
    (M, 3), body frame, started from the best (its ``refiner``) and from the rival (its own),
    converges both times (each run settled once more at most, :func:`settle_once_more`) to poses within ``p.one_optimum_m``
    and ``p.one_optimum_deg``, and the best's verification was complete (static-band coverage
    judged, :func:`consistency_judged`).

    Candidates are refined on the thinned scan (``scan_voxel_m``, at most ``max_ndt_points``):
    along a street its NDT objective is flat and holds optima a metre apart that the inlier test
    cannot tell apart (:func:`better_fit` z < ``ambiguity_z``). On every point the scan's finer
    structure decides. Seen on campus (nominal-mounting map ``--rng 7``, defaults' map default
    draw): the rivals of bests 0.27 m (17933) and 0.06 m (14583) from the truth, 0.90 and 0.68 m
    from them, came back to the best's dense optimum within 0.04 m / 0.0 deg; those of wrong bests
    stayed apart (17812, 271 m off: 0.28 m / 0.69 deg; 25037, 183 m off: 1.8 m) or, where one came
    back (39798, 21.5 m off), the best's coverage was not judged. The tolerance is NDT's own
    precision (two runs to one optimum end within centimetres), not the decision's merge radius
    (0.3 m / 1 deg). ``dense_best``: a list holding the best's dense alignment once made (shared
    over one decision's rivals).

    Where the dense runs stay apart, ``whole`` (a ``refine.WholeScan``: the whole scan against the
    map ``whole_scan_range_m`` around) decides the same way: the scan's every point within
    ``max_range_m`` against the map within ``refine_range_m`` may still hold two optima along a
    street that the far structure makes one (defaults' map ``--rng 7``, frame 17992: a best 0.12 m
    and a rival 0.63 m from the truth, both verified and judged, came to 0.05 and 0.04 m)."""
    if not consistency_judged(best) or best.refiner is None or rival.refiner is None:
        return False
    dense_best = [] if dense_best is None else dense_best
    if not dense_best:
        dense_best.append(settle_once_more(best.refiner, dense_points,
                                           best.refiner.align_settled(dense_points, best.T_map_body)))
    rc = settle_once_more(rival.refiner, dense_points, rival.refiner.align_settled(dense_points, rival.T_map_body))
    if _one(dense_best[0], rc, p):
        log.info("a rival %.2f m from the best is its own optimum on every point",
                 float(np.linalg.norm(rival.T_map_body[:3, 3] - best.T_map_body[:3, 3])))
        return True
    if whole is None:
        return False
    if len(dense_best) < 2:
        dense_best.append(whole.align(best.T_map_body))
    rw = whole.align(rival.T_map_body)
    if dense_best[1] is not None and rw is not None and _one(dense_best[1], rw, p):
        log.info("a rival %.2f m from the best is its own optimum on the whole scan",
                 float(np.linalg.norm(rival.T_map_body[:3, 3] - best.T_map_body[:3, 3])))
        return True
    return False


def _one(a, b, p) -> bool:
    """Whether two NDT runs (``RefineResult``) both converged, within ``one_optimum_m`` and ``_deg``."""
    if not (a.converged and b.converged and np.all(np.isfinite(a.T_map_body)) and np.all(np.isfinite(b.T_map_body))):
        return False
    d_m, d_deg = pose_error(a.T_map_body, b.T_map_body)
    return d_m <= p.one_optimum_m and d_deg <= p.one_optimum_deg


def better_fit(points_body: np.ndarray, a: InitCandidate, b: InitCandidate, block_m: float = 2.0) -> float:
    """How significantly candidate ``a`` explains the scan better than ``b``: a z statistic.

    The points (N, 3), body frame, fall in blocks of ``block_m`` (body xy); per block, d = inliers at
    ``a`` (against a's map) - inliers at ``b`` (against b's). Under "equally good", d is symmetric
    about 0 and sum(d) / sqrt(sum(d^2)) is about standard normal (a sign-flip test; blocks, not
    points, because neighbouring points on one surface pass or fail together). Large: ``a`` fits
    better; around 0: the scan cannot tell them apart.
    """
    from blockloc.global_init.projection import unique_cells

    pts = np.asarray(points_body, float).reshape(-1, 3)
    keys = np.floor(pts[:, :2] / block_m).astype(np.int64)
    _, block = unique_cells(keys, return_inverse=True)
    nb = int(block.max()) + 1 if len(block) else 0
    n = np.bincount(block, minlength=nb)
    d = n * (a.refiner.block_inlier_ratios(pts, a.T_map_body, block, nb)
             - b.refiner.block_inlier_ratios(pts, b.T_map_body, block, nb))
    den = math.sqrt(float(np.sum(d * d)))
    return float(np.sum(d) / den) if den > 0 else 0.0


def pose_error(T_est: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) between two (4, 4) poses."""
    d = inv_T(T_ref) @ T_est
    return float(np.linalg.norm(T_est[:3, 3] - T_ref[:3, 3])), float(np.degrees(rotation_angle(d[:3, :3])))
