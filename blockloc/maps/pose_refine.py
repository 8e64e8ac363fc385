"""Mapping poses refined against the drive's own scans before a map is built (issue 41).

An offline SLAM's body poses carry a smooth error (the small world's: 3 cm, 0.002 rad, a spline
with knots 2 s apart); a map built from them inherits it, and so does the mounting a build
estimates from them (:mod:`blockloc.maps.mounting`). The scans themselves know better over short
spans: consecutive keyframes registered against each other give the LiDAR's motion to a few
millimetres, and keyframes of the same place seen at other times (a street driven back, a loop)
tie distant parts of the drive together.

:func:`refine_poses` solves one pose graph (GTSAM, Levenberg-Marquardt) over the keyframes:

- variables: each keyframe's LiDAR pose ``L_k = T_map_lidar_k`` and one mounting
  ``X = T_body_lidar`` (the scans register LiDAR to LiDAR; the input poses are of the body, and a
  wrong mounting would make the two disagree on every turn, so it is estimated with them: the
  forward translation the build's hand-eye estimate could not determine from the input poses,
  :mod:`blockloc.maps.mounting`, is what costs the tracker its along-track error);
- a prior on each body pose ``L_k X^-1`` at the input pose (``prior_sigma_*``, widened by the
  square root of the keyframes per ``correlation_s``: the input error is smooth, not independent
  from keyframe to keyframe);
- registration factors ``L_i^-1 L_j = B_ij`` (Huber-robust) between keyframes 1..``odometry_span``
  apart and between revisits: keyframes within ``loop_radius_m`` whose stamps are at least
  ``loop_min_gap_s`` apart (first solve: scan to scan);
- then, ``local_rounds`` times (BALM / HBA-style): each keyframe registered against a local map of
  its ``local_span`` neighbours either side, and the later keyframe of each revisit against the
  other pass's local map, both placed by the poses just solved; the graph is solved again from the
  input priors with these (tighter: ``local_sigma_*``). A single scan is sparse (rings); a local
  map of a few keyframes is not: on seed 1, with the neighbours placed by the truth, 3.5 mm median
  against 14 mm scan to scan;
- a prior holding ``X`` at the given mounting: weak on its rotation and its forward (body x)
  translation, which the drive's turns observe; tight on y and z (see :func:`refine_poses`).

Where the drive never sees a place twice, only the odometry chain averages the input error down,
and a smooth error longer than the chain's drift is not observable at all: the result says how
many revisit factors there were. Pure functions on numpy arrays and a registration engine passed
in; no I/O.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from blockloc.geometry import inv_T

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RefinedPoses:
    """What :func:`refine_poses` found.

    T_map_body: (K, 4, 4) refined body poses, map frame. T_body_lidar: (4, 4) the mounting
    estimated with them. odometry_pairs / loop_pairs: registration factors added (converged,
    fitness above the floor) of those tried; shift_m: (K,) how far each body position moved, m.
    skipped: why the poses were left as they came (None: refined). mounting_x_jackknife_m: (B,)
    the mounting's body x, m, solved again without each of B runs of the revisits (empty: not
    asked for, ``jackknife_blocks`` of :func:`refine_poses`; nan: that run left no revisit registered).
    """

    T_map_body: np.ndarray
    T_body_lidar: np.ndarray
    odometry_pairs: int
    loop_pairs: int
    tried_pairs: int
    shift_m: np.ndarray
    skipped: str | None = None
    mounting_x_jackknife_m: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def mounting_x_se_m(self) -> float:
        """The block jackknife's standard error of the mounting's body x, m
        (``sqrt((B - 1) / B * sum (x_b - mean)^2)``; nan when not computed or a run left no revisit)."""
        x = np.asarray(self.mounting_x_jackknife_m, np.float64)
        if len(x) < 2:
            return float("nan")
        return float(np.sqrt((len(x) - 1) / len(x) * ((x - x.mean()) ** 2).sum()))

    def as_dict(self) -> dict:
        """JSON-ready summary (the manifest keeps it beside the map)."""
        if self.skipped:
            return {"skipped": self.skipped, "tried_pairs": int(self.tried_pairs)}
        jk = ({"mounting_x_se_m": round(self.mounting_x_se_m, 4)}
              if np.isfinite(self.mounting_x_se_m) else {})
        return {"odometry_pairs": int(self.odometry_pairs), "loop_pairs": int(self.loop_pairs),
                "tried_pairs": int(self.tried_pairs), **jk,
                "shift_median_m": round(float(np.median(self.shift_m)), 4) if len(self.shift_m) else 0.0,
                "shift_max_m": round(float(np.max(self.shift_m)), 4) if len(self.shift_m) else 0.0}


def choose_refine_pairs(T_map_body: np.ndarray, stamps: np.ndarray, *, odometry_span: int = 2,
                        loop_radius_m: float = 6.0, loop_min_gap_s: float = 10.0,
                        loops_per_keyframe: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(odometry (P, 2), loops (Q, 2)) int64 keyframe index pairs ``i < j``.

    T_map_body: (K, 4, 4) map frame; stamps: (K,) s. Odometry: every keyframe with the next
    ``odometry_span``. Loops: for each keyframe, its ``loops_per_keyframe`` nearest keyframes
    within ``loop_radius_m`` taken at least ``loop_min_gap_s`` apart in time (the input error is
    independent there).
    """
    from scipy.spatial import cKDTree

    K = len(T_map_body)
    odo = [(i, i + s) for s in range(1, odometry_span + 1) for i in range(K - s)]
    odometry = np.asarray(sorted(odo), np.int64).reshape(-1, 2)
    if K < 2:
        return odometry, np.zeros((0, 2), np.int64)
    pos = np.asarray(T_map_body, np.float64)[:, :3, 3]
    t = np.asarray(stamps, np.float64)
    tree = cKDTree(pos)
    loops = set()
    for i in range(K):
        near = np.asarray(tree.query_ball_point(pos[i], loop_radius_m), np.int64)
        near = near[np.abs(t[near] - t[i]) >= loop_min_gap_s]
        if len(near) == 0:
            continue
        d = np.linalg.norm(pos[near] - pos[i], axis=1)
        for j in near[np.argsort(d, kind="stable")[:loops_per_keyframe]].tolist():
            loops.add((min(i, j), max(i, j)))
    return odometry, np.asarray(sorted(loops), np.int64).reshape(-1, 2)


def _body_prior_factor(key_l: int, key_x: int, T_map_body: np.ndarray, noise):
    """CustomFactor on (L, X): ``Log(T_map_body^-1 L X^-1)`` (numeric Jacobians: 6 + 6 columns of a
    cheap error)."""
    import gtsam

    Z_inv = gtsam.Pose3(inv_T(T_map_body))

    def err(L, X):
        return gtsam.Pose3.Logmap(Z_inv.compose(L).compose(X.inverse()))

    def error(this, values, H):
        L, X = values.atPose3(this.keys()[0]), values.atPose3(this.keys()[1])
        e = err(L, X)
        if H is not None:
            for which, P in ((0, L), (1, X)):
                J = np.empty((6, 6))
                for k in range(6):
                    d = np.zeros(6)
                    d[k] = 1e-7
                    Pp = P.compose(gtsam.Pose3.Expmap(d))
                    J[:, k] = ((err(Pp, X) if which == 0 else err(L, Pp)) - e) / 1e-7
                H[which] = J
        return e

    return gtsam.CustomFactor(noise, gtsam.KeyVector([key_l, key_x]), error)


def registrations_to_local_maps(keyframes: int, loops: np.ndarray, span: int) -> tuple[list, np.ndarray]:
    """What :func:`refine_poses` registers with ``local_span`` = ``span`` > 0, as
    ``(source keyframe, target keyframes, reference keyframe)``, and (R,) bool: a revisit. Every
    keyframe ``k`` of ``keyframes`` against the local map of its neighbours ``k-span .. k+span`` (itself left out),
    and the later keyframe ``j`` of each revisit ``(i, j)`` against the local map of the other pass,
    ``i-span .. i+span``."""
    K = int(keyframes)
    odometry = [(k, tuple(m for m in range(max(0, k - span), min(K, k + span + 1)) if m != k), k)
                for k in range(K) if K > 1]
    revisits = [(j, tuple(range(max(0, i - span), min(K, i + span + 1))), i)
                for i, j in np.asarray(loops, np.int64).reshape(-1, 2).tolist()]
    return odometry + revisits, np.arange(len(odometry) + len(revisits)) >= len(odometry)


def register_to_local_maps(clouds_lidar, T_map_lidar: np.ndarray, registrations, engine, *,
                           min_fitness: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """Each ``(k, members, ref)`` of ``registrations``: keyframe ``k``'s scan registered against the
    local map of ``members``' scans placed by ``T_map_lidar`` (K, 4, 4), in ``ref``'s LiDAR frame.
    Returns (kept (R,) bool, measured (R, 4, 4) ``T_map_lidar_k`` as the local map places it).

    clouds_lidar: keyframe index -> (N, 3) deskewed points, LiDAR frame, m. The guess is the given
    relative pose; a registration that does not converge or fits below ``min_fitness`` is not kept.
    A single member is scan-to-scan registration."""
    from blockloc.geometry import transform_points

    L = np.asarray(T_map_lidar, np.float64)
    kept = np.zeros(len(registrations), bool)
    measured = np.tile(np.eye(4), (len(registrations), 1, 1))
    target_of, target = None, None
    for n, (k, members, ref) in enumerate(registrations):
        if target_of != (members, ref):
            L_ref_inv = inv_T(L[ref])
            pts = np.concatenate([np.asarray(clouds_lidar[m], np.float64) if m == ref else
                                  transform_points(L_ref_inv @ L[m], np.asarray(clouds_lidar[m], np.float64))
                                  for m in members])
            target_of, target = (members, ref), engine.build_target(pts)
        res = engine.align(target, np.asarray(clouds_lidar[k], np.float64), inv_T(L[ref]) @ L[k])
        if res.converged and res.fitness >= min_fitness and np.all(np.isfinite(res.T_target_source)):
            kept[n] = True
            measured[n] = L[ref] @ np.asarray(res.T_target_source, np.float64)
    return kept, measured


def refine_poses(T_map_body: np.ndarray, stamps: np.ndarray, clouds_lidar, T_body_lidar: np.ndarray,
                 engine, *, prior_sigma_m: float = 0.03, prior_sigma_rad: float = 0.002,
                 correlation_s: float = 2.0, odometry_sigma_m: float = 0.02,
                 odometry_sigma_rad: float = 0.0015, mounting_sigma_m=(0.05, 1e-4, 1e-4),
                 mounting_sigma_rad: float = np.deg2rad(2.0), odometry_span: int = 2,
                 loop_radius_m: float = 6.0, loop_min_gap_s: float = 10.0,
                 min_fitness: float = 0.15, local_span: int = 2, local_rounds: int = 2,
                 local_sigma_m: float = 0.005, local_sigma_rad: float = 0.0005,
                 jackknife_blocks: int = 0, revisits_left_out=()) -> RefinedPoses:
    """The keyframes' body poses refined against their scans (module docstring).

    T_map_body: (K, 4, 4) input body poses, map frame, m; stamps: (K,) s, increasing;
    clouds_lidar: keyframe index -> (N, 3) deskewed points, LiDAR frame, m; T_body_lidar: (4, 4)
    nominal mounting; engine: a registration engine (:mod:`blockloc.registration.engines`).

    First the scans are registered scan to scan (each keyframe with its next ``odometry_span``,
    each revisit pair; ``odometry_sigma_*``) and the graph solved. local_span: 0 stops there;
    ``s`` > 0 then, ``local_rounds`` times, registers each keyframe against the local map of its
    ``s`` neighbours either side and the later keyframe of each revisit against the local map of
    the other pass (:func:`registrations_to_local_maps`), placed by the poses just solved, and
    solves again from the input priors: a measurement against ``n`` scans becomes one factor to
    each of them with ``local_sigma_*`` times ``sqrt(n)``. Chosen on seed 1 (refined body poses
    against the truth, no tracking): scan to scan only 2.90 cm RMSE; span 2, one round 2.59, two
    rounds 2.48 (3 mm / 0.0003 rad: 2.53; span 3: 2.45 at 1.2x the registrations' cost).

    The defaults were chosen on the small world's seed 1 (docs/bench/accuracy_seeds.md): the
    registration sigmas are what scan-to-scan NDT achieved there against the truth (median 20 mm,
    0.09 deg on neighbours; 10 mm on revisits). ``mounting_sigma_m``: the prior's sigma on the
    mounting's translation per body axis (x forward, y left, z up), or one for all: x is estimated
    (5 cm), y and z held at the given values (0.1 mm). On seed 1, all three free (5 cm) put x 2.4 mm
    from the truth but y 29 mm and z 13 mm off (a ground drive observes y only through its turns,
    where the input error is correlated, and z not at all); x alone free: x 2.0 mm off (given:
    11.6 mm), y and z as given; all held: x stays 11.6 mm off. Its rotation is estimated with the
    poses (``mounting_sigma_rad`` about the given one; ~0: held, with ``mounting_sigma_m`` ~0, for
    poses of the LiDAR itself or a mounting not estimated). A drive with no revisit registered is left as it came
    (``skipped``): the chain alone only averages the input error against its own drift.

    jackknife_blocks: B > 1 also refines B more times, each without one run of the revisits (cut
    in B runs of equal count by the later keyframe's stamp), and returns the mounting's body x of
    each (``mounting_x_jackknife_m``): how well the drive's revisits determine x. Runs, not single
    revisits, because the input error that reaches x is correlated along the drive; the whole
    refinement, registrations included, because the local maps are placed by the poses solved
    with every revisit (re-solving the last graph alone understated the spread 7-fold on the
    small world's seed 2: 0.8 mm against 5.5 mm; docs/bench/accuracy_seeds.md, 2026-12-06 15:30
    UTC). Costs B refinements; 0: none. revisits_left_out: (i, j) revisit pairs not used.
    """
    T = np.asarray(T_map_body, np.float64)
    X0 = np.asarray(T_body_lidar, np.float64)
    t = np.asarray(stamps, np.float64)
    K = len(T)
    odometry, loops = choose_refine_pairs(T, t, odometry_span=odometry_span, loop_radius_m=loop_radius_m,
                                          loop_min_gap_s=loop_min_gap_s)
    left_out = {tuple(p) for p in np.asarray(revisits_left_out, np.int64).reshape(-1, 2).tolist()}
    if left_out:
        loops = np.asarray([p for p in loops.tolist() if tuple(p) not in left_out], np.int64).reshape(-1, 2)
    pairs = np.concatenate([odometry, loops]) if len(loops) else odometry
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))  # scan to scan: j onto i, one target per first keyframe
    rounds = [([(j, (i,), i) for i, j in pairs[order].tolist()], (np.arange(len(order)) >= len(odometry))[order],
               odometry_sigma_m, odometry_sigma_rad)]
    if local_span > 0:
        regs, is_loop = registrations_to_local_maps(K, loops, int(local_span))
        rounds += [(regs, is_loop, local_sigma_m, local_sigma_rad)] * int(local_rounds)
    L, X = T @ X0, X0
    solve_options = dict(prior_sigma_m=prior_sigma_m, prior_sigma_rad=prior_sigma_rad, correlation_s=correlation_s,
                         mounting_sigma_m=mounting_sigma_m, mounting_sigma_rad=mounting_sigma_rad)
    for regs, is_loop, sigma_m, sigma_rad in rounds:
        kept, measured = register_to_local_maps(clouds_lidar, L, regs, engine, min_fitness=min_fitness)
        if not (kept & is_loop).any():
            why = (f"no revisit: no keyframes within {loop_radius_m:g} m taken {loop_min_gap_s:g} s or more apart"
                   if not len(loops) else f"none of {len(loops)} revisit pairs registered")
            return RefinedPoses(T.copy(), X0.copy(), int((kept & ~is_loop).sum()), 0, len(regs), np.zeros(K), why)
        # measured L_k against the members as placed now: one factor L_m -> L_k per member
        factors = [(m, k, inv_T(L[m]) @ Lk, len(members))
                   for (k, members, _), Lk in zip([r for r, ok in zip(regs, kept) if ok], measured[kept])
                   for m in members]
        L, X = _solve(T, t, X0, factors, odometry_sigma_m=sigma_m, odometry_sigma_rad=sigma_rad, **solve_options)
    refined = L @ inv_T(X)
    jackknife = np.zeros(0)
    if jackknife_blocks > 1 and len(loops) >= jackknife_blocks:
        options = dict(solve_options, odometry_sigma_m=odometry_sigma_m, odometry_sigma_rad=odometry_sigma_rad,
                       odometry_span=odometry_span, loop_radius_m=loop_radius_m, loop_min_gap_s=loop_min_gap_s,
                       min_fitness=min_fitness, local_span=local_span, local_rounds=local_rounds,
                       local_sigma_m=local_sigma_m, local_sigma_rad=local_sigma_rad)
        runs = np.array_split(loops[np.argsort(t[loops[:, 1]], kind="stable")], int(jackknife_blocks))
        # a run whose leaving out leaves no revisit registered comes back skipped: no x (nan)
        jackknife = np.array([np.nan if r.skipped else r.T_body_lidar[0, 3] for r in
                              (refine_poses(T, t, clouds_lidar, X0, engine, revisits_left_out=run, **options)
                               for run in runs)])
    return RefinedPoses(refined, X, int((kept & ~is_loop).sum()), int((kept & is_loop).sum()), len(regs),
                        np.linalg.norm(refined[:, :3, 3] - T[:, :3, 3], axis=1), mounting_x_jackknife_m=jackknife)


def _solve(T: np.ndarray, t: np.ndarray, X0: np.ndarray, factors, *, prior_sigma_m, prior_sigma_rad,
           correlation_s, odometry_sigma_m, odometry_sigma_rad, mounting_sigma_m,
           mounting_sigma_rad) -> tuple[np.ndarray, np.ndarray]:
    """One pose graph (module docstring): priors on the body poses at ``T`` (K, 4, 4) and on the
    mounting at ``X0``, ``factors`` ``(i, j, T_lidar_i_lidar_j, n)`` with sigmas times sqrt(n).
    Returns the LiDAR poses (K, 4, 4) and the mounting (4, 4)."""
    import gtsam
    from gtsam.symbol_shorthand import L as L_key
    from gtsam.symbol_shorthand import M as M_key

    K = len(T)
    # the input error is smooth: ~correlation_s of keyframes share one draw of it
    dt = float(np.median(np.diff(t))) if K > 1 else correlation_s
    widen = np.sqrt(max(1.0, correlation_s / max(dt, 1e-6)))
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, prior_sigma_rad), np.full(3, prior_sigma_m)] * widen)
    reg_sigmas = np.r_[np.full(3, odometry_sigma_rad), np.full(3, odometry_sigma_m)]
    reg_noise = {}
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    # M: the mounting T_body_lidar; L(k): keyframe k's LiDAR pose T_map_lidar
    values.insert(M_key(0), gtsam.Pose3(X0))
    # the prior's translation sigmas are per body axis; Pose3's tangent moves the LiDAR along its own
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.eye(3) * mounting_sigma_rad ** 2
    R = X0[:3, :3]
    cov[3:, 3:] = R.T @ np.diag(np.broadcast_to(np.asarray(mounting_sigma_m, np.float64), (3,)) ** 2) @ R
    graph.add(gtsam.PriorFactorPose3(M_key(0), gtsam.Pose3(X0), gtsam.noiseModel.Gaussian.Covariance(cov)))
    for k in range(K):
        values.insert(L_key(k), gtsam.Pose3(T[k] @ X0))
        graph.add(_body_prior_factor(L_key(k), M_key(0), T[k], prior_noise))
    for i, j, b, n in factors:
        if n not in reg_noise:
            reg_noise[n] = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345),
                                                          gtsam.noiseModel.Diagonal.Sigmas(reg_sigmas * np.sqrt(n)))
        graph.add(gtsam.BetweenFactorPose3(L_key(i), L_key(j), gtsam.Pose3(b), reg_noise[n]))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    return np.stack([result.atPose3(L_key(k)).matrix() for k in range(K)]), result.atPose3(M_key(0)).matrix()


def corrected_poses(stamps: np.ndarray, T_map_body: np.ndarray, key_stamps: np.ndarray,
                    T_before: np.ndarray, T_after: np.ndarray) -> np.ndarray:
    """A trajectory's poses (N, 4, 4) moved as its keyframes were: each keyframe's correction
    ``D_k = T_before_k^-1 T_after_k`` (body frame, so a small rotation does not swing positions far
    from the map origin) is interpolated in time (linear / slerp, held beyond the first and last
    keyframe) and applied on the right. stamps: (N,) s; key_stamps: (K,) s increasing; T_*: (K, 4, 4)."""
    from blockloc.geometry import Trajectory

    D = np.einsum("kij,kjl->kil", np.linalg.inv(np.asarray(T_before, np.float64)), np.asarray(T_after, np.float64))
    return np.asarray(T_map_body, np.float64) @ Trajectory(np.asarray(key_stamps, np.float64), D).interpolate(stamps)
