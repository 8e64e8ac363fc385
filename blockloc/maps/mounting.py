"""The LiDAR mounting (``T_body_lidar``) estimated from a mapping drive, before the map is built.

A map built from body poses (an offline SLAM's, or a dataset's ground truth such as NCLT's) and
the *nominal* extrinsic inherits the robot's mounting error: every keyframe is turned by that
error about its own position, so keyframes taken from different places and headings disagree
(0.3 deg over a 10 m baseline is 5 cm) and the map is blurred differently along each street. A
LiDAR SLAM map does not have this: its poses come from the scans themselves.

The estimate is a hand-eye calibration from registered keyframe pairs. For keyframes ``i, j``
with body poses ``T_map_body_i, T_map_body_j`` the body motion is ``A_ij = T_bi_bj``; the scans
registered against each other give the LiDAR motion ``B_ij = T_li_lj`` with its information
``H_ij`` (the engine's Hessian, GTSAM Pose3 tangent). A mounting ``X = T_body_lidar`` explains a
pair when ``X^-1 A_ij X = B_ij``; :func:`solve_mounting` finds the ``X`` that minimizes
``sum_ij e_ij^T H_ij e_ij`` with ``e_ij = Log(B_ij^-1 X^-1 A_ij X)``, robustly (Cauchy weights),
with a weak prior that holds what the drive cannot observe at the nominal value (a ground robot
that only turns about its vertical axis cannot tell the LiDAR's height, for instance).

The rotation is always taken from the estimate; the translation only when the drive determines
it (:func:`translation_determined`). A ground robot observes the horizontal translation only
through its turns, at ``|error of A_ij's translation| / (2 sin(turn / 2))``, and the mapping
poses' own error (an offline SLAM's: centimetres, smooth along the drive) is not in the
registration's information, so the fit's sigma cannot tell: on the small world's seeds 2 and 3 it
said 3-8 mm where the translation was 11-22 mm off, worse than the nominal's own 4-9 mm per axis, and on
the synthetic square drive with exact poses it said 5-6 mm where the translation was within
1.3 mm. The measure asks the drive to reproduce the translation: a block jackknife over runs of
pairs along the drive (8 runs, each left out in turn) gives its standard error on each body
axis: 8-18 mm on seeds 2 and 3, 1-2 mm on the square. Each body axis's estimated translation
is kept where that is within ``TRANSLATION_TOLERANCE_M`` (5 mm, about what a CAD drawing's
extrinsic is good to); the others keep the nominal value (the real hand-held walk: x and y
estimated at 0.6 and 1.6 mm, z at 9 mm kept nominal; a ground robot's height is not observed).

What limits the translation is the mapping poses, not the pairs: on the small world's seeds 1-5
the same pairs give x within 0.9-6.7 mm of the truth with the true poses, and 6-18 mm off with the
offline-SLAM poses (3 cm, 0.002 rad smooth error) the build has, through the yaw the two share
(a mounting yaw shows only in the direction of each pair's body displacement, which the poses'
error tilts). A translation error ``d`` left in the map moves it by ``R_map d`` and costs the
tracker ``(R_map - R_loc) d``: nothing on the mapping drive's heading, ``2 d`` against it
(``python -m bench.seeds --explain``, docs/bench/accuracy_seeds.md).

Pure functions on numpy arrays and a registration engine passed in; no I/O.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from blockloc.geometry import inv_T, rotation_angle, so3_log

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MountingEstimate:
    """The estimated mounting and how much the drive said about it.

    T_body_lidar: (4, 4) the estimate. T_body_lidar_nominal: (4, 4) where it started.
    rotation_deg: (3,) the correction's rotation vector in the body frame, degrees
    (``R_est R_nominal^T``); translation_m: (3,) ``t_est - t_nominal``, body frame, metres.
    sigma: (6,) 1-sigma of the correction (rotation rad, translation m; Pose3 tangent of the
    LiDAR frame), from the information of the pairs, scaled by their residuals. observed: (6,) bool,
    the axes the pairs constrain more than the prior does. pairs: pairs registered; used: pairs
    kept (converged, with overlap); cost_before / cost_after: median whitened squared residual
    of the kept pairs at the nominal and the estimated mounting. translation_estimated: (3,)
    bool, the body axes on which ``T_body_lidar`` holds the estimated translation (the others:
    the nominal one; translation_m is 0 there, translation_solved_m (3,) is what the fit found);
    translation_uncertainty_m: (3,) body frame, metres, the standard error
    :func:`translation_determined` decided by (nan: an axis the drive does not observe);
    translation_tolerance_m: what it was held to (0: not judged, every axis estimated).
    """

    T_body_lidar: np.ndarray
    T_body_lidar_nominal: np.ndarray
    rotation_deg: np.ndarray
    translation_m: np.ndarray
    sigma: np.ndarray
    observed: np.ndarray
    pairs: int
    used: int
    cost_before: float
    cost_after: float
    notes: list[str] = field(default_factory=list)
    translation_estimated: np.ndarray = field(default_factory=lambda: np.ones(3, bool))
    translation_uncertainty_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    translation_solved_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    translation_tolerance_m: float = 0.0

    def as_dict(self) -> dict:
        """JSON-ready summary (the manifest keeps it beside the map)."""
        return {"T_body_lidar": np.round(self.T_body_lidar, 9).tolist(),
                "T_body_lidar_nominal": np.round(self.T_body_lidar_nominal, 9).tolist(),
                "rotation_deg": np.round(self.rotation_deg, 4).tolist(),
                "translation_m": np.round(self.translation_m, 4).tolist(),
                "sigma_deg": np.round(np.rad2deg(self.sigma[:3]), 4).tolist(),
                "sigma_m": np.round(self.sigma[3:], 4).tolist(),
                "observed": [bool(x) for x in self.observed],
                "pairs": int(self.pairs), "used": int(self.used),
                "cost_before": round(float(self.cost_before), 4),
                "cost_after": round(float(self.cost_after), 4),
                # the body axes whose translation is the estimate's, e.g. "xy" ("": all nominal)
                "translation_estimated": "".join(a for a, e in zip("xyz", self.translation_estimated) if e),
                "translation_solved_m": np.round(self.translation_solved_m, 4).tolist(),
                # JSON has no inf / nan: null for an axis the measure could not judge
                "translation_uncertainty_m": [round(float(u), 4) if np.isfinite(u) else None
                                              for u in self.translation_uncertainty_m],
                "translation_tolerance_m": float(self.translation_tolerance_m)}


def choose_pairs(T_map_body: np.ndarray, *, max_pairs: int = 300, min_baseline_m: float = 4.0,
                 max_baseline_m: float = 15.0, max_keyframes: int = 400,
                 seed: int = 0) -> np.ndarray:
    """Keyframe pairs (P, 2) int64 (indices into ``T_map_body``, (K, 4, 4) map frame) whose
    positions lie ``min_baseline_m .. max_baseline_m`` apart: far enough that a mounting
    rotation moves one scan against the other, near enough that they overlap.

    Anchors are spread evenly along the drive (at most ``max_keyframes`` distinct keyframes are
    used, since each is a scan to read); pairs that turn between them (the heading changes by more
    than 30 deg, e.g. a street driven back or a corner) are taken first, because they observe the
    mounting's translation and roll, which straight driving does not. Deterministic for a seed.
    """
    from scipy.spatial import cKDTree

    T = np.asarray(T_map_body, np.float64)
    K = len(T)
    if K < 2 or max_pairs < 1:
        return np.zeros((0, 2), np.int64)
    pos = T[:, :3, 3]
    rng = np.random.default_rng(seed)
    tree = cKDTree(pos)
    n_anchor = max(1, min(K, max_keyframes // 2, max_pairs))
    anchors = np.unique(np.linspace(0, K - 1, n_anchor).round().astype(np.int64))
    heading = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    pairs: list[tuple[int, int]] = []
    for a in anchors.tolist():
        near = np.asarray(tree.query_ball_point(pos[a], max_baseline_m), np.int64)
        d = np.linalg.norm(pos[near] - pos[a], axis=1)
        near = near[d >= min_baseline_m]
        if len(near) == 0:
            continue
        turn = np.abs(np.angle(np.exp(1j * (heading[near] - heading[a])))) > np.deg2rad(30.0)
        pool = near[turn] if turn.any() and rng.random() < 0.7 else near
        b = int(rng.choice(pool))
        pairs.append((min(a, b), max(a, b)))
    out = np.unique(np.asarray(pairs, np.int64).reshape(-1, 2), axis=0)
    return out[:max_pairs]


def _pose3(T):
    import gtsam

    return gtsam.Pose3(np.asarray(T, np.float64))


def _residuals(xi: np.ndarray, X0, A, B_inv) -> np.ndarray:
    """(P, 6) e_ij = Log(B_ij^-1 X^-1 A_ij X) at X = X0 Exp(xi)."""
    import gtsam

    X = X0.compose(gtsam.Pose3.Expmap(xi))
    Xi = X.inverse()
    return np.stack([gtsam.Pose3.Logmap(b.compose(Xi).compose(a).compose(X)) for a, b in zip(A, B_inv)])


def solve_mounting(A: np.ndarray, B: np.ndarray, H: np.ndarray, T_body_lidar0: np.ndarray, *,
                   prior_sigma_rad: float = np.deg2rad(2.0), prior_sigma_m: float = 0.05,
                   iterations: int = 15) -> dict:
    """Hand-eye least squares: the ``X = T_body_lidar`` with ``X^-1 A_ij X ~ B_ij``.

    A: (P, 4, 4) body motions ``T_bi_bj``; B: (P, 4, 4) registered LiDAR motions ``T_li_lj``;
    H: (P, 6, 6) their information (Pose3 tangent, rotation first; any common scale: it is
    normalized by the residuals). T_body_lidar0: (4, 4) the nominal mounting (start and prior
    mean). Returns a dict: ``T_body_lidar`` (4, 4); ``sigma`` (6,) and ``observed`` (6,) bool
    (module :class:`MountingEstimate`); ``cov`` (6, 6) the correction's covariance (Pose3 tangent
    of the LiDAR frame); ``weights`` (P,) in (0, 1]; ``cost_before`` /
    ``cost_after`` (P,) the pairs' scaled whitened squared residuals at the nominal and the
    estimated mounting.
    """
    import gtsam

    P = len(A)
    X0 = _pose3(T_body_lidar0)
    Ap = [_pose3(a) for a in A]
    Bi = [_pose3(b).inverse() for b in B]
    # whitening: e^T H e = |L^T e|^2 with H = L L^T (a small ridge keeps a flat axis finite)
    L = np.stack([np.linalg.cholesky(0.5 * (h + h.T) + 1e-9 * np.eye(6) * max(np.trace(h), 1e-9))
                  for h in np.asarray(H, np.float64)])

    def whitened(xi: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        r = np.einsum("pji,pj->pi", L, _residuals(xi, X0, Ap, Bi))  # L^T e
        if not jacobian:
            return r, None
        J = np.empty((P, 6, 6))
        for k in range(6):  # forward differences: 6 parameters, cheap residuals
            step = np.zeros(6)
            step[k] = 1e-6
            J[:, :, k] = (np.einsum("pji,pj->pi", L, _residuals(xi + step, X0, Ap, Bi)) - r) / 1e-6
        return r, J

    prior = np.r_[np.full(3, prior_sigma_rad), np.full(3, prior_sigma_m)] ** -2.0
    first = _gauss_newton(whitened, prior, iterations)
    if first["observed"].all() or iterations == 0:
        out = first
    else:
        # what the pairs do not observe is held at the nominal value, not left to drift within
        # the prior (the small world's LiDAR height moved 3 cm that way)
        held = np.where(first["observed"], prior, 1e8 * prior)
        out = _gauss_newton(whitened, held, iterations)
        out["observed"] = first["observed"]
        out["sigma"] = np.where(first["observed"], out["sigma"], first["sigma"])
        out["cov"] = first["cov"]  # of the free fit: what the pairs say, axis by axis
    xi = out.pop("xi")
    out["T_body_lidar"] = X0.compose(gtsam.Pose3.Expmap(xi)).matrix()
    return out


def _gauss_newton(whitened, prior: np.ndarray, iterations: int) -> dict:
    """Robust Gauss-Newton on the 6 mounting parameters (see :func:`solve_mounting`)."""
    xi = np.zeros(6)
    r0, _ = whitened(xi, False)
    d2_0 = np.einsum("pi,pi->p", r0, r0)
    # the engines' Hessians are not calibrated covariances: scale them so the median pair costs
    # what a 6-D chi-square's median does; pairs far beyond are down-weighted (Cauchy)
    scale = 5.35 / max(float(np.median(d2_0)), 1e-300)
    c2 = 4.0 * 5.35
    for _ in range(iterations):
        r, J = whitened(xi, True)
        w = scale / (1.0 + scale * np.einsum("pi,pi->p", r, r) / c2)
        N = np.einsum("pik,pil->kl", J * w[:, None, None], J) + np.diag(prior)
        g = np.einsum("pik,pi->k", J * w[:, None, None], r) + prior * xi
        dx = -np.linalg.solve(N, g)
        xi = xi + dx
        if np.max(np.abs(dx)) < 1e-9:
            break
    r, J = whitened(xi, True)
    d2 = scale * np.einsum("pi,pi->p", r, r)
    w = 1.0 / (1.0 + d2 / c2)
    data = np.einsum("pik,pil->kl", J * (scale * w)[:, None, None], J)
    cov = np.linalg.inv(data + np.diag(prior))
    sigma = np.sqrt(np.diag(cov))
    return {"xi": xi, "sigma": sigma, "cov": cov,
            # an axis is observed when the pairs shrink its variance well below the prior's
            "observed": sigma ** 2 < 0.25 / prior, "weights": w,
            "cost_before": scale * d2_0, "cost_after": d2}


#: What the estimated translation must be good to, per body axis, to replace the nominal one
#: (metres): about what a mounting from a CAD drawing or a tape measure is good to.
TRANSLATION_TOLERANCE_M = 0.005
#: Runs of pairs along the drive the translation's block jackknife leaves out in turn.
JACKKNIFE_BLOCKS = 8


def _body_translation_sigma(cov: np.ndarray, R_body_lidar: np.ndarray) -> np.ndarray:
    """(3,) 1-sigma of the mounting translation along the body axes, metres, from ``cov`` (6, 6)
    (Pose3 tangent of the LiDAR frame: its translation part moves the LiDAR along its own axes)."""
    C = R_body_lidar @ np.asarray(cov)[3:, 3:] @ R_body_lidar.T
    return np.sqrt(np.clip(np.diag(C), 0.0, None))


def translation_determined(A: np.ndarray, B: np.ndarray, H: np.ndarray, T_body_lidar0: np.ndarray,
                           solved: dict, *, tolerance_m: float = TRANSLATION_TOLERANCE_M,
                           blocks: int = JACKKNIFE_BLOCKS, **solve_options) -> tuple[np.ndarray, np.ndarray]:
    """Whether the pairs determine the mounting's translation to ``tolerance_m`` (module docstring).

    A, B, H, T_body_lidar0: as :func:`solve_mounting`, the pairs in the drive's time order;
    solved: its result on all of them. A block jackknife: the pairs are cut into ``blocks`` runs
    along the drive, the mounting solved again without each run, and the spread of those
    translations gives the estimate's standard error, ``sqrt((k - 1) / k * sum (t_i - mean)^2)``
    per body axis. Runs, not single pairs, because the error that matters (the mapping poses')
    is correlated along the drive. Returns (determined, u): u (3,) body frame, metres, that
    standard error; nan on an axis the whole drive does not observe (held at the nominal value
    by the solve: not judged), inf on every axis when there are fewer than 3 pairs a run.
    determined: (3,) bool, the body axes observed with ``u <= tolerance_m``.
    """
    R0 = np.asarray(T_body_lidar0, np.float64)[:3, :3]
    limit = 0.5 * solve_options.get("prior_sigma_m", 0.05)  # as solve_mounting's ``observed``
    observed = _body_translation_sigma(solved["cov"], R0) < limit
    if len(A) < 3 * blocks:
        return np.zeros(3, bool), np.where(observed, np.inf, np.nan)
    runs = np.array_split(np.arange(len(A)), blocks)
    t = np.stack([solve_mounting(A[keep], B[keep], H[keep], T_body_lidar0, **solve_options)["T_body_lidar"][:3, 3]
                  for keep in (np.setdiff1d(np.arange(len(A)), run) for run in runs)])
    u = np.sqrt((blocks - 1) / blocks * ((t - t.mean(axis=0)) ** 2).sum(axis=0))
    u = np.where(observed, u, np.nan)
    return observed & (np.nan_to_num(u, nan=np.inf) <= tolerance_m), u


def estimate_mounting(clouds_lidar, T_map_body: np.ndarray, pairs: np.ndarray,
                      T_body_lidar0: np.ndarray, engine, *, min_fitness: float = 0.15,
                      translation_tolerance_m: float = TRANSLATION_TOLERANCE_M,
                      **solve_options) -> MountingEstimate:
    """The mounting from registered keyframe pairs (module docstring).

    clouds_lidar: mapping keyframe index -> (N, 3) deskewed points in the LiDAR frame, metres
    (a dict or list). T_map_body: (K, 4, 4) the keyframes' body poses, map frame. pairs: (P, 2)
    from :func:`choose_pairs`. T_body_lidar0: (4, 4) the nominal mounting. engine: a registration
    engine (:mod:`blockloc.registration.engines`) that registers scan ``j`` onto scan ``i``
    from the nominal guess. Pairs that do not converge or whose fitness is below ``min_fitness``
    are left out (scan-to-scan fitness is low: on the campus map drive the median pair's was 0.36
    with NDT; 0.15 kept 193 of 200 pairs and the estimate was within 0.035 deg of the truth, 0.25
    kept 141 and was off by 0.06 deg). The rotation is the estimate's; the translation too when
    :func:`translation_determined` says the drive determines it to ``translation_tolerance_m``
    (0: always) on a body axis, else the nominal one there. MapError when no pair is left.
    """
    from blockloc.errors import MapError

    T = np.asarray(T_map_body, np.float64)
    X0 = np.asarray(T_body_lidar0, np.float64)
    X0_inv = inv_T(X0)
    target_of, target = None, None  # pairs come sorted by i: one target serves a run of them
    A, B, H = [], [], []
    for i, j in np.asarray(pairs, np.int64).tolist():
        A_ij = inv_T(T[i]) @ T[j]
        if target_of != i:
            target_of, target = i, engine.build_target(np.asarray(clouds_lidar[i], np.float64))
        res = engine.align(target, np.asarray(clouds_lidar[j], np.float64), X0_inv @ A_ij @ X0)
        if not res.converged or res.fitness < min_fitness or not np.all(np.isfinite(res.H)):
            continue
        A.append(A_ij)
        B.append(np.asarray(res.T_target_source, np.float64))
        H.append(np.asarray(res.H, np.float64))
    if not A:
        raise MapError(f"mounting estimate: none of {len(pairs)} keyframe pairs registered with "
                       f"fitness >= {min_fitness} (expected overlapping keyframe scans)")
    A, B, H = np.stack(A), np.stack(B), np.stack(H)
    sol = solve_mounting(A, B, H, X0, **solve_options)
    notes = [f"only {len(A)} pairs registered: a weak estimate"] if len(A) < 20 else []
    if translation_tolerance_m > 0:
        keep_t, u = translation_determined(A, B, H, X0, sol, tolerance_m=translation_tolerance_m,
                                           **solve_options)
    else:
        keep_t, u = np.ones(3, bool), np.full(3, np.nan)
    X = _quantized(sol["T_body_lidar"], X0)
    solved_t = X[:3, 3] - X0[:3, 3]
    X = X.copy()
    X[:3, 3] = np.where(keep_t, X[:3, 3], X0[:3, 3])
    rot = np.rad2deg(so3_log(X[:3, :3] @ X0[:3, :3].T))
    return MountingEstimate(X, X0, rot, X[:3, 3] - X0[:3, 3], sol["sigma"], sol["observed"],
                            len(pairs), len(A), float(np.median(sol["cost_before"])),
                            float(np.median(sol["cost_after"])), notes, keep_t, u, solved_t,
                            float(translation_tolerance_m))


def _quantized(X: np.ndarray, X0: np.ndarray, step: float = 1e-5) -> np.ndarray:
    """``X`` with its correction from ``X0`` (Pose3 tangent, rad and m) rounded to ``step``.

    The same estimate computed in another process can differ in its last bits (a serial build and
    a Dask worker ran the same pairs and agreed to 9 digits, yet their maps differed by a few
    points where voxel edges fell), and serial and distributed builds must write the same bytes.
    1e-5 rad (0.0006 deg) and 10 um are far below what the estimate resolves (its sigma is
    ~0.005 deg and ~1 mm on a well-observed drive), and far above last-bit differences.
    """
    import gtsam

    xi = gtsam.Pose3.Logmap(_pose3(X0).between(_pose3(X)))
    return _pose3(X0).compose(gtsam.Pose3.Expmap(np.round(xi / step) * step)).matrix()


def map_mounting(params: dict) -> np.ndarray | None:
    """The LiDAR mounting (4, 4) a map was built with when its build estimated one (the manifest
    parameters' ``mounting``, one entry per drive); None when it estimated none, or when its
    drives' estimates disagree by more than 0.05 deg or 5 mm (several robots: no one mounting)."""
    found = [np.asarray(m["T_body_lidar"], np.float64) for m in (params.get("mounting") or {}).values()]
    if not found:
        return None
    for X in found[1:]:
        deg, m = mounting_difference(X, found[0])
        if deg > 0.05 or m > 0.005:
            return None
    return found[0]


def mounting_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation m) between two mountings ``T_body_lidar`` (4, 4)."""
    deg = float(np.rad2deg(rotation_angle(T_a[:3, :3] @ T_b[:3, :3].T)))
    return deg, float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))


def with_map_mounting(seq, store, use: bool):
    """``seq`` seen with the LiDAR mounting ``store`` was built with (``use``: the same robot, as
    ``map.use_map_mounting`` says by default), or as it is, with a warning when the two differ.
    store: anything with ``params`` (a map store's manifest parameters); a map without an
    estimated mounting leaves ``seq`` as it is."""
    from blockloc.datasets.base import RemountedSequence

    X_map = map_mounting(getattr(store, "params", {}) or {})
    if X_map is None:
        return seq
    deg, m = mounting_difference(X_map, np.asarray(seq.info.T_body_lidar, np.float64))
    if use:
        log.info("%s: tracking with the map's estimated LiDAR mounting (%.2f deg, %.3f m from the "
                 "sequence's)", seq.info.name, deg, m)
        return RemountedSequence(seq, X_map)
    if deg > 0.05 or m > 0.005:
        log.warning("the map was built with a LiDAR mounting estimated from its drive that differs "
                    "from %s's by %.2f deg / %.3f m; if the same robot recorded both, "
                    "--set map.use_map_mounting=true tracks with it", seq.info.name, deg, m)
    return seq
