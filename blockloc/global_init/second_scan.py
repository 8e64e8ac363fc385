"""More evidence for an ambiguous relocalization: a second scan and the motion between the two.

Along a street of repeated structure one scan may fit two places nearly equally (``decide`` then
reports the result ambiguous and never verified). A scan taken a few metres on sees what lies
further along: each verified pose of the first scan, moved by the motion between the scans
(odometry, IMU, or the second scan registered to the first), is a start for the second scan, which
is refined and verified there exactly as any candidate (``GlobalLocalizer._refine``: fitness, the
structure test, static-band consistency, overlap) and decided over exactly as any search
(``verify.decide``: a rival that fits nearly as well keeps the result ambiguous). Nothing is
loosened: the evidence is a second, independent test of each hypothesis.
"""

from __future__ import annotations

import math
import time

import numpy as np

from blockloc.global_init.bnb import Candidate2D
from blockloc.global_init.verify import InitResult


def ambiguous_hypotheses(result: InitResult, params) -> list[np.ndarray]:
    """The poses T_map_body (4, 4) an ambiguous result could not tell apart: its verified
    candidates and those as plausible as ``decide`` counts rivals (fitness and structure fitness
    above ``params``' floors), at least ``ambiguity_distance_m`` apart, best first."""
    out: list[np.ndarray] = []
    for c in result.candidates:
        plausible = c.verified or (c.fitness >= params.min_fitness
                                   and c.structure_fitness >= params.min_structure_fitness)
        if not plausible or c.T_map_body is None or not np.all(np.isfinite(c.T_map_body)):
            continue
        if all(np.linalg.norm(c.T_map_body[:3, 3] - o[:3, 3]) > params.ambiguity_distance_m for o in out):
            out.append(np.asarray(c.T_map_body, float))
    return out


def resolve_with_second_scan(localizer, hypotheses: list[np.ndarray], T_first_second: np.ndarray,
                             points_body: np.ndarray, gravity_body: np.ndarray) -> InitResult:
    """Which of ``hypotheses`` (poses T_map_body (4, 4) of the body at the first scan) the second
    scan confirms (module docstring).

    localizer: a ``GlobalLocalizer``; T_first_second (4, 4): the body at the second scan in the
    body frame of the first (the motion between them); points_body (N, 3), body frame, metres, and
    gravity_body (3,): the second scan. Returns the ``InitResult`` of the second scan: verified
    (its pose is the body at the second scan) only when one hypothesis passes verification there
    and no other fits nearly as well.
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
    return localizer._decide(cands, {"hypotheses": len(hypotheses)}, time.perf_counter() - t0, scan_ndt)
