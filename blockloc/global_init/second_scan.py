"""More evidence for an ambiguous relocalization: a second scan and the motion between the two.

Along a street of repeated structure one scan may fit two places nearly equally (``decide`` then
reports the result ambiguous and never verified). A scan taken a few metres on sees what lies
further along: each verified pose of the first scan, moved by the motion between the scans
(odometry, IMU, or the second scan registered to the first), is a start for the second scan, which
is refined and verified there exactly as any candidate (``GlobalLocalizer._refine``: fitness, the
structure test, static-band consistency, overlap) and decided over exactly as any search
(``verify.decide``: a rival that fits nearly as well keeps the result ambiguous). Nothing is
loosened: the evidence is a second, independent test of each hypothesis.

A session carries an :class:`Ambiguity` from one scan to the next (``blockloc.app.recovery``):
:func:`follow_up` registers the new scan to the ambiguous one (:func:`scan_motion`) and tests the
hypotheses there; a result still ambiguous becomes the next :class:`Ambiguity` (the hypotheses
the new scan rejected are gone), so the evidence of every scan since the first adds up.

A hypothesis is a pose, not a street: the scan confirms it only where it was put. NDT started at a
hypothesis can slide along a street of repeated structure to another optimum (campus, nominal map,
frame 39798: of three hypotheses 4.5-21.5 m from the truth, none at it, one slid 15 m onto another
and the other crept 0.2-0.4 m a scan; seven scans on, one pose 6.9 m off was left and verified).
So a plausible candidate that refinement moved more than ``ambiguity_distance_m`` from where its
hypothesis put it keeps the result ambiguous (:func:`slid_m`), and a hypothesis carried on is its
pose moved by the motions only (``T_map_body_2d``, the refinement's start), never by refinement:
creeping adds up against where the first scan put it, not against the last scan.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from blockloc.global_init.bnb import Candidate2D
from blockloc.global_init.verify import InitCandidate, InitResult, plausible

#: scan-to-scan registration starts along the first body's x axis (m), tried in turn until one fits
#: (the motion between two scans is unknown without a tracker; a vehicle moves along its x)
MOTION_STARTS_M = (0.0, 1.5, -1.5, 3.0, -3.0)
#: the share of the second scan's points (within MOTION_RANGE_M) inside the first scan's NDT cells
#: for a motion to be trusted. Campus (sim, HDL-32E), frames 1808->1809, 2131->2132, 2131->2136
#: (0.13-0.65 m): 0.52-0.63 at the found motion (1-9 cm off); the second scan turned 90 degrees: 0.14-0.21
MIN_MOTION_FITNESS = 0.4
#: the second scan's points farther than this are left out: the first scan is too sparse out there
#: for NDT's cells (campus: fitness 0.39-0.56 with points to 60 m, 0.52-0.63 to 30 m, same motions)
MOTION_RANGE_M = 30.0
#: the first scan as the registration target: dense enough for NDT's cells (a cell needs 6 points;
#: one point per 0.5 m voxel leaves a flat 1 m cell 4), the second scan thinned as refinement thins it
TARGET_VOXEL_M = 0.2
TARGET_MAX_POINTS = 30000
SOURCE_MAX_POINTS = 4000


def slid_m(c: InitCandidate) -> float:
    """How far (m, horizontal, map frame) refinement moved ``c`` from its start (0 without one)."""
    if c.T_map_body_2d is None or c.T_map_body is None:
        return 0.0
    return float(np.linalg.norm(np.asarray(c.T_map_body)[:2, 3] - np.asarray(c.T_map_body_2d)[:2, 3]))


def ambiguous_hypotheses(result: InitResult, params, anchored: bool = False) -> list[np.ndarray]:
    """The poses T_map_body (4, 4) an ambiguous result could not tell apart: its verified
    candidates and those as plausible as ``decide`` counts rivals (:func:`plausible`), at least
    ``ambiguity_distance_m`` apart, best first. ``anchored``: each at its refinement's start
    (``T_map_body_2d``: a follow-up's hypothesis moved by the motion; module docstring)."""
    out: list[np.ndarray] = []
    for c in result.candidates:
        T = c.T_map_body_2d if anchored and c.T_map_body_2d is not None else c.T_map_body
        if not (c.verified or plausible(c, params)) or T is None or not np.all(np.isfinite(T)):
            continue
        if all(np.linalg.norm(T[:3, 3] - o[:3, 3]) > params.ambiguity_distance_m for o in out):
            out.append(np.asarray(T, float))
    return out


def resolve_with_second_scan(localizer, hypotheses: list[np.ndarray], T_first_second: np.ndarray,
                             points_body: np.ndarray, gravity_body: np.ndarray) -> InitResult:
    """Which of ``hypotheses`` (poses T_map_body (4, 4) of the body at the first scan) the second
    scan confirms (module docstring).

    localizer: a ``GlobalLocalizer``; T_first_second (4, 4): the body at the second scan in the
    body frame of the first (the motion between them); points_body (N, 3), body frame, metres, and
    gravity_body (3,): the second scan. Returns the ``InitResult`` of the second scan: verified
    (its pose is the body at the second scan) only when one hypothesis passes verification there,
    no other fits nearly as well, no plausible one slid (:func:`slid_m`; ambiguous then, with
    ``stats['slid']`` of them) and, where the best's static-band coverage was not judged, it fits
    strongly (``stats['unjudged']`` otherwise).
    """
    t0 = time.perf_counter()
    scan, scan_ndt = localizer.prepare_scan(np.asarray(points_body, float), np.asarray(gravity_body, float))
    cells = localizer._scan_cells(points_body, gravity_body)
    R_L_map = localizer.map.R_L_map
    leaves = []
    for T_first in hypotheses:
        T = np.asarray(T_first, float) @ np.asarray(T_first_second, float)
        R_L_body = R_L_map @ T[:3, :3]
        R_heading = R_L_body @ scan.R_tilt.T  # the levelled scan's turn into the levelled frame
        xy = (R_L_map @ T[:3, 3])[:2]
        leaves.append(Candidate2D(float(xy[0]), float(xy[1]), math.atan2(R_heading[1, 0], R_heading[0, 0]), 1.0))
    cands = localizer._refine(leaves, scan, scan_ndt, cells)
    p = localizer.params
    slid = sum((c.verified or plausible(c, p)) and slid_m(c) > p.ambiguity_distance_m for c in cands)
    res = localizer._decide(cands, {"hypotheses": len(hypotheses), "slid": slid}, time.perf_counter() - t0,
                            scan_ndt, searched=False)
    if slid and res.verified:  # the scan fits along the street: no hypothesis is confirmed where it was put
        res.verified, res.ambiguous = False, True
    # (a hypothesis confirmed on its NDT fit alone needs a strong fit: ``searched=False`` above,
    # ``GlobalLocalizer._decide``; ``stats['unjudged']`` otherwise)
    return res


@dataclass
class Ambiguity:
    """An ambiguous result carried to the next scan: ``hypotheses`` (poses T_map_body (4, 4) of the
    body at this scan, :func:`ambiguous_hypotheses`), the scan's points (N, 3), body frame, metres,
    voxel-selected (the next scan registers to them), its ``stamp`` (s) and ``frame`` index."""

    hypotheses: list[np.ndarray]
    points_body: np.ndarray  # (N, 3) voxel-selected at TARGET_VOXEL_M
    stamp: float
    frame: int = -1
    scans: int = 1  # scans whose evidence the hypotheses carry

    @classmethod
    def of(cls, result: InitResult, params, points_body: np.ndarray, stamp: float, frame: int = -1,
           scans: int = 1) -> "Ambiguity | None":
        """The ambiguity of an ambiguous ``result`` of the scan ``points_body`` (N, 3), body frame,
        or None when the result is not ambiguous or has fewer than two hypotheses. After the first
        scan (``scans`` > 1: ``result`` is a follow-up's) the hypotheses are anchored (module
        docstring)."""
        if not result.ambiguous:
            return None
        hyps = ambiguous_hypotheses(result, params, anchored=scans > 1)
        if len(hyps) < 2:
            return None
        return cls(hyps, motion_points(points_body, TARGET_VOXEL_M, params.max_range_m, TARGET_MAX_POINTS),
                   float(stamp), int(frame), scans)


def motion_points(points_body: np.ndarray, voxel_m: float, max_range_m: float = 60.0,
                  max_points: int = SOURCE_MAX_POINTS) -> np.ndarray:
    """A scan (N, 3) thinned for scan-to-scan registration: one point per ``voxel_m`` voxel within
    ``max_range_m`` of the body, at most ``max_points`` (a fixed-seed sample)."""
    from blockloc.voxels import voxel_select

    pts = np.asarray(points_body, float).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    pts = pts[voxel_select(pts, voxel_m, range_m=(0.5, max_range_m))]
    if len(pts) > max_points:
        pts = pts[np.sort(np.random.default_rng(0).choice(len(pts), max_points, replace=False))]
    return pts


def scan_motion(engine, first_body: np.ndarray, second_body: np.ndarray, R_first_second: np.ndarray | None = None,
                starts_m: tuple[float, ...] = MOTION_STARTS_M,
                min_fitness: float = MIN_MOTION_FITNESS) -> tuple[np.ndarray | None, float]:
    """The body's motion between two scans, T_first_second (4, 4), by registering the second scan
    (N, 3), body frame, to the first (M, 3), body frame, with ``engine`` (the registration protocol;
    the first scan dense enough for its cells: ``TARGET_VOXEL_M``).

    R_first_second: (3, 3) the rotation between them when known (the gyro), else identity. The
    translation is started from each of ``starts_m`` along the first body's x, and the converged
    result of the highest fitness wins: the ground fits from any start (seen on a synthetic street:
    fitness 0.82 at no motion for a true 2 m), the structure only from the right one. Returns
    (T_first_second, or None when none converged with fitness >= ``min_fitness``; its fitness)."""
    if len(first_body) < 100 or len(second_body) < 100:
        return None, 0.0
    target = engine.build_target(np.asarray(first_body, float))
    best_T, best_fit = None, 0.0
    for d in starts_m:
        T0 = np.eye(4)
        if R_first_second is not None:
            T0[:3, :3] = R_first_second
        T0[0, 3] = d
        r = engine.align(target, np.asarray(second_body, float), T0)
        T = np.asarray(r.T_target_source, float)
        if r.converged and np.all(np.isfinite(T)) and float(r.fitness) > best_fit:
            best_T, best_fit = T, float(r.fitness)
    return (best_T if best_fit >= min_fitness else None), best_fit


def follow_up(localizer, ambiguity: Ambiguity, points_body: np.ndarray, gravity_body: np.ndarray,
              R_first_second: np.ndarray | None = None) -> tuple[InitResult | None, dict]:
    """Test ``ambiguity``'s hypotheses with a later scan (points_body (N, 3), body frame, metres;
    gravity_body (3,)): the motion by :func:`scan_motion` with the localizer's engine (the gyro's
    rotation ``R_first_second`` (3, 3) as its start when known), then
    :func:`resolve_with_second_scan`. Returns (the later scan's InitResult, or None when the motion
    could not be registered; what was done: ``motion_fitness``, ``hypotheses``, ``from_frame``,
    ``motion_m``)."""
    p = localizer.params
    pts = motion_points(points_body, p.scan_voxel_m, min(MOTION_RANGE_M, p.max_range_m))
    T_fs, fit = scan_motion(localizer.engine, ambiguity.points_body, pts, R_first_second)
    info = {"from_frame": ambiguity.frame, "hypotheses": len(ambiguity.hypotheses), "motion_fitness": round(fit, 3),
            "scans": ambiguity.scans + 1}
    if T_fs is None:
        return None, info
    info["motion_m"] = round(float(np.linalg.norm(T_fs[:3, 3])), 3)
    return resolve_with_second_scan(localizer, ambiguity.hypotheses, T_fs, points_body, gravity_body), info
