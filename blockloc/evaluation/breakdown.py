"""The position error broken down the way an engineer debugs it (pure numpy, no I/O).

Where ATE gives one number, this says what kind of error it is:

- **along-track / cross-track / vertical** components: the error vector ``p_est - p_gt`` (map
  frame) projected on the ground truth's horizontal direction of travel, on the horizontal axis
  90 deg from it (``z x forward``: left in a z-up map, right in NCLT's z-down map) and on the map's
  z axis. A timing error or a scale error shows along track, a mounting yaw or a lateral map
  error across it. Poses slower than ``min_speed_mps`` have no direction of travel and are left
  out of the two horizontal components.
- the **time shift** that best explains the along-track error: the estimate at stamp t is the
  ground truth at ``t - time_shift_s`` to first order (positive: the estimate lags), so its
  along-track error is ``-speed * time_shift_s``; a 1-D least-squares fit over the moving poses.
  With an intercept too (``along = c - speed * shift``, when the speeds vary by more than
  0.1 m/s): a constant along-track offset ``c`` (a mounting or map shift seen along the way)
  told apart from a lag, which grows with speed.
- the **constant offset**: the mean error vector in the map frame (a map shift), and in the
  body frame (``R_map_body^T`` of each error, averaged: a LiDAR mounting translation error).
- the error **against speed and turn rate**: the poses binned by the ground truth's speed and
  yaw rate, each bin's count, translation RMSE and along/cross-track figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.errors import EvaluationError

#: Bin edges of the breakdown tables: speed (m/s) and turn rate (deg/s); the last bin is open.
SPEED_EDGES_MPS = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
TURN_RATE_EDGES_DEG_S = (0.0, 2.0, 5.0, 10.0, 20.0, 45.0)


@dataclass
class ErrorBreakdown:
    """Per-pose components and the fitted explanations of one evaluation.

    along_m, cross_m: (N,) metres, NaN where the ground truth moves slower than ``min_speed_mps``;
    vertical_m: (N,) metres (map z); speed_mps: (N,) ground-truth speed; turn_rate_deg_s: (N,)
    absolute ground-truth rotation rate about the map z axis (yaw rate); moving: (N,) bool.
    time_shift_s: the 1-D fit (None without moving poses); offset_m: (3,) mean error, map frame;
    body_offset_m: (3,) mean error, body frame; fit_with_offset: (shift s, along-track offset m)
    of the fit with an intercept (None when the moving poses' speeds vary by 0.1 m/s or less).
    """

    along_m: np.ndarray
    cross_m: np.ndarray
    vertical_m: np.ndarray
    speed_mps: np.ndarray
    turn_rate_deg_s: np.ndarray
    moving: np.ndarray
    time_shift_s: float | None
    offset_m: np.ndarray
    trans_m: np.ndarray
    body_offset_m: np.ndarray
    fit_with_offset: tuple[float, float] | None  # (shift s, along-track offset m)

    def along_after_shift_m(self) -> np.ndarray:
        """(M,) the moving poses' along-track error with the fitted time shift taken out."""
        a, s = self.along_m[self.moving], self.speed_mps[self.moving]
        return a + s * (self.time_shift_s or 0.0)

    def table(self, by: str, edges) -> list[dict]:
        """Rows of the error against ``by`` ('speed' or 'turn_rate'), one per non-empty bin
        ``[lo, hi)`` of ``edges`` (the last bin open, ``hi`` None): ``lo``, ``hi``, ``count``,
        ``trans_rmse_m``, ``along_mean_m``, ``along_rms_m``, ``cross_rms_m`` (None without a moving
        pose in the bin)."""
        x = self.speed_mps if by == "speed" else self.turn_rate_deg_s
        edges = [float(e) for e in edges]
        rows = []
        for k, lo in enumerate(edges):
            hi = edges[k + 1] if k + 1 < len(edges) else None
            sel = (x >= lo) & (x < hi) if hi is not None else (x >= lo)
            if not sel.any():
                continue
            mov = sel & self.moving
            rows.append({"lo": lo, "hi": hi, "count": int(sel.sum()),
                         "trans_rmse_m": _rms(self.trans_m[sel]),
                         "along_mean_m": float(np.mean(self.along_m[mov])) if mov.any() else None,
                         "along_rms_m": _rms(self.along_m[mov]) if mov.any() else None,
                         "cross_rms_m": _rms(self.cross_m[mov]) if mov.any() else None})
        return rows


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def error_breakdown(stamps: np.ndarray, poses_gt: np.ndarray, poses_est: np.ndarray, *,
                    min_speed_mps: float = 0.2) -> ErrorBreakdown:
    """Break the position error of matched poses down (see the module docstring).

    stamps: (N,) seconds, increasing, the matched poses' common time; poses_gt, poses_est:
    (N, 4, 4) ``T_map_body`` (the estimate already aligned if alignment is used), row i of each
    at stamps[i]. Velocity and yaw rate are the ground truth's, by central differences.
    EvaluationError when the inputs do not match or N < 2.
    """
    t = np.asarray(stamps, np.float64).ravel()
    G = np.asarray(poses_gt, np.float64).reshape(-1, 4, 4)
    P = np.asarray(poses_est, np.float64).reshape(-1, 4, 4)
    if not len(t) == len(G) == len(P):
        raise EvaluationError(f"error breakdown: {len(t)} stamps, {len(G)} ground-truth and {len(P)} "
                              "estimated poses; expected as many of each")
    if len(t) < 2 or not np.all(np.diff(t) > 0):
        raise EvaluationError("error breakdown: expected at least 2 poses with increasing stamps")
    p_gt = G[:, :3, 3]
    err = P[:, :3, 3] - p_gt
    vel = np.gradient(p_gt, t, axis=0)
    horiz = vel.copy()
    horiz[:, 2] = 0.0
    speed = np.linalg.norm(vel, axis=1)
    hspeed = np.linalg.norm(horiz, axis=1)
    moving = hspeed >= float(min_speed_mps)
    fwd = np.full_like(horiz, np.nan)
    fwd[moving] = horiz[moving] / hspeed[moving, None]
    side = np.cross(np.array([0.0, 0.0, 1.0]), fwd)  # z x forward
    along = np.einsum("ij,ij->i", err, fwd)
    cross = np.einsum("ij,ij->i", err, side)
    yaw = np.unwrap(np.arctan2(G[:, 1, 0], G[:, 0, 0]))  # heading of the body x axis in the map
    turn = np.degrees(np.abs(np.gradient(yaw, t)))
    shift, both = None, None
    if moving.any():
        s, a = speed[moving], along[moving]
        # along = -speed * shift: least squares over the moving poses
        shift = float(-np.dot(s, a) / np.dot(s, s))
        if np.std(s) > 0.1:  # along = c - speed * shift: separable only when the speed varies
            (c, neg_shift), *_ = np.linalg.lstsq(np.c_[np.ones_like(s), s], a, rcond=None)
            both = (float(-neg_shift), float(c))
    body = np.einsum("nji,nj->ni", G[:, :3, :3], err)  # R_map_body^T e
    return ErrorBreakdown(along_m=along, cross_m=cross, vertical_m=err[:, 2], speed_mps=speed,
                          turn_rate_deg_s=turn, moving=moving, time_shift_s=shift,
                          offset_m=err.mean(axis=0), trans_m=np.linalg.norm(err, axis=1),
                          body_offset_m=body.mean(axis=0), fit_with_offset=both)


def breakdown_metrics(b: ErrorBreakdown) -> dict:
    """The JSON-able keys ``blockloc eval`` and ``metrics.json`` carry (all ``err_...``):
    ``{along,cross,vertical}_{mean,rms}_m`` (None without moving poses for the horizontal ones),
    ``err_moving_poses``, ``err_time_shift_s``, ``err_along_rms_after_shift_m``, ``err_offset_m``
    ([x, y, z], map frame), ``err_body_offset_m`` ([x, y, z], body frame),
    ``err_time_shift_with_offset_s`` and ``err_along_offset_m`` (the fit with an intercept, or
    None), ``err_by_speed`` and ``err_by_turn_rate`` (lists of bin rows,
    :meth:`ErrorBreakdown.table`)."""
    out: dict = {}
    mov = b.moving
    for name, x in (("along", b.along_m[mov]), ("cross", b.cross_m[mov]), ("vertical", b.vertical_m)):
        out[f"err_{name}_mean_m"] = float(np.mean(x)) if len(x) else None
        out[f"err_{name}_rms_m"] = _rms(x) if len(x) else None
    out["err_moving_poses"] = int(mov.sum())
    out["err_time_shift_s"] = b.time_shift_s
    out["err_along_rms_after_shift_m"] = _rms(b.along_after_shift_m()) if mov.any() else None
    out["err_offset_m"] = [float(v) for v in b.offset_m]
    out["err_body_offset_m"] = [float(v) for v in b.body_offset_m]
    out["err_time_shift_with_offset_s"], out["err_along_offset_m"] = b.fit_with_offset or (None, None)
    out["err_by_speed"] = b.table("speed", SPEED_EDGES_MPS)
    out["err_by_turn_rate"] = b.table("turn_rate", TURN_RATE_EDGES_DEG_S)
    return out
