"""Trajectory error metrics on numpy arrays: association, Umeyama alignment, ATE and RPE.

Pure functions, no I/O. Poses are (N, 4, 4) ``T_map_body`` in metres; stamps (N,) seconds.

ATE follows the block-map paper's table (which used evo): with the absolute error pose
``E_i = inv(T_gt_i) @ T_est_i``
- translation part: ``||t_est_i - t_gt_i||`` in metres (evo ``APE`` ``translation_part``);
- full: ``||E_i - I||_F``, unitless (evo ``APE`` ``full_transformation``; the norm is the same
  for ``E_i`` and ``inv(E_i)``, so the operand order does not matter);
- rotation: the angle of ``E_i`` in degrees.

RPE over path-length deltas, defined like evo's ``RPE`` with ``delta_unit=meters``,
``all_pairs=True``, ``pairs_from_reference=True``, ``rel_delta_tol=0.1``: every pose i is paired with
the later pose j whose ground-truth path distance from i is nearest to delta, kept when within 10%
of delta; ``E_ij = inv(inv(G_i) G_j) @ inv(P_i) P_j``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from blockloc.errors import EvaluationError
from blockloc.geometry import inv_T

RPE_REL_TOL = 0.1


# ----------------------------------------------------------------------------- association


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_time_diff_s: float = 0.02
              ) -> tuple[np.ndarray, np.ndarray]:
    """Pair stamps of two trajectories by nearest time, each stamp used at most once.

    stamps_a: (N,), stamps_b: (M,) float64 seconds (any order).
    Candidates are each stamp's nearest neighbour in the other list (both directions) with
    ``|dt| <= max_time_diff_s``; they are accepted greedily from the smallest |dt| so no stamp is
    matched twice (evo's ``associate_trajectories`` pairs the same way when stamps are unambiguous).
    Returns index arrays (K,) into a and b, sorted by the a index.
    """
    a = np.asarray(stamps_a, dtype=np.float64).reshape(-1)
    b = np.asarray(stamps_b, dtype=np.float64).reshape(-1)
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    oa, ob = np.argsort(a, kind="stable"), np.argsort(b, kind="stable")
    sa, sb = a[oa], b[ob]

    def nearest(sorted_ref: np.ndarray, query: np.ndarray) -> np.ndarray:
        k = np.searchsorted(sorted_ref, query)
        lo = np.clip(k - 1, 0, len(sorted_ref) - 1)
        hi = np.clip(k, 0, len(sorted_ref) - 1)
        return np.where(np.abs(sorted_ref[lo] - query) <= np.abs(sorted_ref[hi] - query), lo, hi)

    nb_of_a = nearest(sb, sa)  # (N,) into sb
    na_of_b = nearest(sa, sb)  # (M,) into sa
    ia = np.arange(len(sa))
    # Mutual nearest neighbours within tolerance have the smallest |dt| of every candidate touching
    # either end, so the greedy pass would accept them first: take them all at once.
    mutual = (na_of_b[nb_of_a] == ia) & (np.abs(sa - sb[nb_of_a]) <= max_time_diff_s)
    used_a = mutual.copy()
    used_b = np.zeros(len(sb), dtype=bool)
    used_b[nb_of_a[mutual]] = True
    out_a: list[int] = []
    out_b: list[int] = []
    # The rest (dense stamps, one stamp nearest to several): greedy from the smallest |dt|.
    cand_a = np.concatenate([ia, na_of_b])
    cand_b = np.concatenate([nb_of_a, np.arange(len(sb))])
    dt = np.abs(sa[cand_a] - sb[cand_b])
    keep = (dt <= max_time_diff_s) & ~used_a[cand_a] & ~used_b[cand_b]
    cand_a, cand_b, dt = cand_a[keep], cand_b[keep], dt[keep]
    for k in np.lexsort((cand_b, cand_a, dt)):
        i, j = cand_a[k], cand_b[k]
        if used_a[i] or used_b[j]:
            continue
        used_a[i] = used_b[j] = True
        out_a.append(i)
        out_b.append(j)
    out_a = oa[np.concatenate([ia[mutual], np.asarray(out_a, dtype=np.int64)])]
    out_b = ob[np.concatenate([nb_of_a[mutual], np.asarray(out_b, dtype=np.int64)])]
    order = np.argsort(out_a, kind="stable")
    return out_a[order], out_b[order]


def nearest_within(stamps_ref: np.ndarray, stamps_query: np.ndarray, max_time_diff_s: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """For each query stamp, the nearest reference stamp if within ``max_time_diff_s``.

    stamps_ref: (N,) sorted ascending; stamps_query: (M,) seconds. A reference stamp may serve
    several queries (used to gate interpolation, not for one-to-one pairing).
    Returns index arrays (K,) into ref and query, sorted by the query index.
    """
    ref = np.asarray(stamps_ref, dtype=np.float64).reshape(-1)
    q = np.asarray(stamps_query, dtype=np.float64).reshape(-1)
    if len(ref) == 0 or len(q) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    k = np.searchsorted(ref, q)
    lo = np.clip(k - 1, 0, len(ref) - 1)
    hi = np.clip(k, 0, len(ref) - 1)
    j = np.where(np.abs(ref[lo] - q) <= np.abs(ref[hi] - q), lo, hi)
    keep = np.flatnonzero(np.abs(ref[j] - q) <= max_time_diff_s)
    return j[keep].astype(np.int64), keep.astype(np.int64)


# ----------------------------------------------------------------------------- alignment


def umeyama_alignment(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rigid transform (no scale) minimizing sum ||dst_i - (R src_i + t)||^2 (Umeyama 1991).

    src, dst: (N, 3) corresponding points, metres. Returns (4, 4) ``T_dst_src``.
    Raises EvaluationError when the points are too few or collinear (rotation not determined).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise EvaluationError(f"alignment needs two (N, 3) point sets, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise EvaluationError(f"alignment needs at least 3 matched poses, got {len(src)}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)  # (3, 3), Umeyama eq. 38
    U, d, Vt = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(np.float64).eps) < 2:
        raise EvaluationError("alignment is undetermined: the matched positions are collinear or all equal")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0  # a rotation, not a reflection
    R = U @ S @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_d - R @ mu_s
    return T


def rotation_angle_rad(R: np.ndarray) -> np.ndarray:
    """Angle (rad, in [0, pi]) of rotation matrices (3, 3) or (N, 3, 3).

    atan2 of the sine (from the skew part) and cosine (from the trace): accurate near 0 and pi,
    where arccos of the trace loses half the digits (1e-8 rad floor).
    """
    R = np.asarray(R, dtype=np.float64)
    sin_vec = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = 0.5 * np.linalg.norm(sin_vec, axis=-1)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin, cos)


# ----------------------------------------------------------------------------- statistics


def error_stats(errors: np.ndarray) -> dict[str, float]:
    """rmse, mean, median, std, min, max of a (N,) error array (N >= 1)."""
    e = np.asarray(errors, dtype=np.float64)
    return {
        "rmse": float(np.sqrt(np.mean(e**2))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
    }


# ----------------------------------------------------------------------------- ATE


@dataclass
class AteResult:
    """Per-pose absolute errors of matched poses.

    trans_m: (N,) metres; full: (N,) ||E - I||_F; rot_deg: (N,) degrees.
    T_align: (4, 4) ``T_gt_est`` applied to the estimate before comparison (identity if none).
    """

    trans_m: np.ndarray
    full: np.ndarray
    rot_deg: np.ndarray
    T_align: np.ndarray = field(default_factory=lambda: np.eye(4))

    def stats(self) -> dict[str, dict[str, float]]:
        return {"trans_m": error_stats(self.trans_m), "full": error_stats(self.full),
                "rot_deg": error_stats(self.rot_deg)}


def absolute_pose_errors(poses_gt: np.ndarray, poses_est: np.ndarray, *, align: bool = False) -> AteResult:
    """ATE of matched poses.

    poses_gt, poses_est: (N, 4, 4) ``T_map_body``, row i of each at the same time.
    align: first move the estimate by the Umeyama SE(3) fit of its positions to the ground truth.
    """
    G = np.asarray(poses_gt, dtype=np.float64).reshape(-1, 4, 4)
    P = np.asarray(poses_est, dtype=np.float64).reshape(-1, 4, 4)
    if len(G) != len(P):
        raise EvaluationError(f"{len(G)} ground-truth poses but {len(P)} estimated poses")
    if len(G) == 0:
        raise EvaluationError("no matched poses to evaluate")
    T_align = np.eye(4)
    if align:
        T_align = umeyama_alignment(P[:, :3, 3], G[:, :3, 3])
        P = T_align @ P
    E = inv_T(G) @ P
    trans = np.linalg.norm(P[:, :3, 3] - G[:, :3, 3], axis=1)
    full = np.linalg.norm((E - np.eye(4)).reshape(len(E), 16), axis=1)
    rot = np.degrees(rotation_angle_rad(E[:, :3, :3]))
    return AteResult(trans, full, rot, T_align)


# ----------------------------------------------------------------------------- RPE


def pairs_by_path_distance(positions: np.ndarray, delta_m: float, rel_tol: float = RPE_REL_TOL
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j), j > i, whose path distance is nearest to ``delta_m`` (within rel_tol).

    positions: (N, 3) metres along the path. For each i the j > i minimizing
    ``|d_j - d_i - delta_m|`` (d: accumulated distance; the first such j on ties) is kept when that
    is at most ``rel_tol * delta_m``. Returns (K,) index arrays i, j.
    """
    pos = np.asarray(positions, dtype=np.float64)
    n = len(pos)
    if n < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    i = np.arange(n - 1)
    target = d[i] + delta_m
    hi = np.searchsorted(d, target, side="left")  # first index with d >= target
    hi = np.maximum(hi, i + 1)
    # The best j below the target is the first index holding the largest value < target.
    below_val = d[np.clip(hi - 1, 0, n - 1)]
    below = np.maximum(np.searchsorted(d, below_val, side="left"), i + 1)
    has_below = hi - 1 > i
    has_above = hi < n
    err_above = np.where(has_above, np.abs(d[np.minimum(hi, n - 1)] - d[i] - delta_m), np.inf)
    err_below = np.where(has_below, np.abs(d[below] - d[i] - delta_m), np.inf)
    use_below = err_below <= err_above
    j = np.where(use_below, below, np.minimum(hi, n - 1))
    err = np.where(use_below, err_below, err_above)
    keep = err <= rel_tol * delta_m
    return i[keep], j[keep]


@dataclass
class RpeResult:
    """Relative errors over pose pairs about ``delta_m`` apart along the ground-truth path.

    i, j: (K,) pair indices; path_m: (K,) ground-truth path distance of each pair;
    trans_m: (K,) translation error, metres; rot_deg: (K,) rotation error, degrees.
    """

    delta_m: float
    i: np.ndarray
    j: np.ndarray
    path_m: np.ndarray
    trans_m: np.ndarray
    rot_deg: np.ndarray

    @property
    def trans_pct(self) -> np.ndarray:
        """(K,) translation error as % of the pair's path distance."""
        return 100.0 * self.trans_m / np.maximum(self.path_m, 1e-12)

    @property
    def rot_deg_per_m(self) -> np.ndarray:
        """(K,) rotation error per metre of path, deg/m."""
        return self.rot_deg / np.maximum(self.path_m, 1e-12)


def relative_pose_errors(poses_gt: np.ndarray, poses_est: np.ndarray, delta_m: float,
                         rel_tol: float = RPE_REL_TOL) -> RpeResult | None:
    """RPE for one path-length delta; None when no pair is ``delta_m`` apart (path too short).

    poses_gt, poses_est: (N, 4, 4) ``T_map_body`` of matched poses.
    """
    G = np.asarray(poses_gt, dtype=np.float64).reshape(-1, 4, 4)
    P = np.asarray(poses_est, dtype=np.float64).reshape(-1, 4, 4)
    if len(G) != len(P):
        raise EvaluationError(f"{len(G)} ground-truth poses but {len(P)} estimated poses")
    if not delta_m > 0:
        raise EvaluationError(f"RPE delta {delta_m!r} m: expected a positive distance")
    i, j = pairs_by_path_distance(G[:, :3, 3], delta_m, rel_tol)
    if len(i) == 0:
        return None
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1))])
    G_rel = inv_T(G[i]) @ G[j]
    P_rel = inv_T(P[i]) @ P[j]
    E = inv_T(G_rel) @ P_rel
    return RpeResult(float(delta_m), i, j, d[j] - d[i], np.linalg.norm(E[:, :3, 3], axis=1),
                     np.degrees(rotation_angle_rad(E[:, :3, :3])))
