"""Evaluate an estimate against ground truth: files or trajectories in, a flat metrics dict out.

The dict is JSON-able and flat (``metrics.json`` of a tracking run embeds it). Keys:

- ``gt_poses``, ``est_poses``, ``matched``, ``association`` ('time', 'interpolated' or 'index'),
  ``max_time_diff_s``, ``duration_s`` and ``path_length_m`` (of the matched ground truth),
  ``aligned``, ``align_T_gt_est`` ((4, 4) as nested lists, or None);
- ``ate_trans_{rmse,mean,median,std,max}_m``, ``ate_full_{rmse,mean,median,std,max}``
  (evo's APE ``full_transformation``), ``ate_rot_{rmse,mean,median,std,max}_deg``;
- ``rpe_deltas_m`` and per delta D (formatted ``{D:g}``, e.g. ``rpe_10m_...``): ``pairs``,
  ``trans_rmse_m``, ``trans_mean_m``, ``trans_mean_pct``, ``rot_rmse_deg``, ``rot_mean_deg``,
  ``rot_mean_deg_per_m``; all None when the path is shorter than D (a note says so);
- the error breakdown (:mod:`blockloc.evaluation.breakdown`): ``err_{along,cross,vertical}_{mean,rms}_m``,
  ``err_moving_poses``, ``err_time_shift_s``, ``err_along_rms_after_shift_m``, ``err_offset_m``
  ([x, y, z], map frame), ``err_by_speed``, ``err_by_turn_rate`` (lists of bin rows); absent
  when the poses are paired by index (no time to differentiate);
- ``notes`` (list of str), ``plots`` (list of PNG paths); ``gt_file``, ``est_file`` for files.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blockloc.errors import EvaluationError
from blockloc.evaluation.metrics import absolute_pose_errors, associate, nearest_within, relative_pose_errors
from blockloc.geometry import Trajectory

log = logging.getLogger(__name__)

DEFAULT_RPE_DELTAS_M = (1.0, 10.0, 100.0)
ATE_STATS = ("rmse", "mean", "median", "std", "max")


def rpe_key(delta_m: float) -> str:
    """Key prefix of one RPE delta, e.g. 10.0 -> 'rpe_10m'."""
    return f"rpe_{delta_m:g}m"


def _span(stamps: np.ndarray) -> str:
    return f"{stamps[0]:.3f}..{stamps[-1]:.3f} s" if len(stamps) else "empty"


def match_poses(gt: Trajectory, est: Trajectory, *, max_time_diff_s: float = 0.02,
                by_index: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays (K,) into gt and est of the poses compared.

    by_index: pair row k with row k (equal lengths required), for files without stamps.
    Raises EvaluationError when nothing matches, naming both time spans.
    """
    if len(gt) == 0 or len(est) == 0:
        raise EvaluationError(f"cannot evaluate: {len(gt)} ground-truth poses, {len(est)} estimated poses")
    if by_index:
        if len(gt) != len(est):
            raise EvaluationError(f"pairing by index needs equal lengths, got {len(gt)} ground-truth and "
                                  f"{len(est)} estimated poses (give the KITTI file a times file)")
        idx = np.arange(len(gt))
        return idx, idx
    if not max_time_diff_s >= 0:
        raise EvaluationError(f"max_time_diff_s {max_time_diff_s!r}: expected a non-negative number of seconds")
    i_gt, i_est = associate(gt.stamps, est.stamps, max_time_diff_s)
    if len(i_gt) == 0:
        raise EvaluationError(f"no estimated pose within {max_time_diff_s} s of a ground-truth pose "
                              f"(ground truth {_span(gt.stamps)}, estimate {_span(est.stamps)}; "
                              f"same time base and unit expected)")
    return i_gt, i_est


def evaluate_trajectories(gt: Trajectory, est: Trajectory, *, align: bool = False,
                          max_time_diff_s: float = 0.02,
                          rpe_deltas_m: Sequence[float] = DEFAULT_RPE_DELTAS_M,
                          plot_dir: Path | None = None, by_index: bool = False,
                          interpolate: bool = False) -> dict[str, Any]:
    """ATE and RPE of ``est`` against ``gt`` -> flat JSON-able dict (keys in the module docstring).

    gt, est: ``T_map_body`` trajectories, stamps in seconds on the same clock.
    align: Umeyama SE(3) alignment of the estimate before ATE (off for map-based localization,
    whose estimate lives in the map frame already). max_time_diff_s: association tolerance.
    plot_dir: write ``trajectories.png`` and ``errors.png`` there. by_index: see ``match_poses``.
    interpolate: compare each estimated pose (whose nearest ground-truth stamp is within
    ``max_time_diff_s``) with the ground truth interpolated to its stamp (linear position, slerp),
    removing the up-to-``max_time_diff_s`` time skew of nearest matching (evo's default, used
    otherwise: at 1.5 m/s a 20 ms skew alone is 3 cm of error).
    """
    if interpolate and not by_index:
        if len(gt) == 0 or len(est) == 0:
            raise EvaluationError(f"cannot evaluate: {len(gt)} ground-truth poses, {len(est)} estimated poses")
        i_gt, i_est = nearest_within(gt.stamps, est.stamps, max_time_diff_s)
        if len(i_est) == 0:
            match_poses(gt, est, max_time_diff_s=max_time_diff_s)  # raises the no-overlap message
        G, P = gt.interpolate(est.stamps[i_est]), est.poses[i_est]
        stamps = est.stamps[i_est]
    else:
        i_gt, i_est = match_poses(gt, est, max_time_diff_s=max_time_diff_s, by_index=by_index)
        G, P = gt.poses[i_gt], est.poses[i_est]
        stamps = gt.stamps[i_gt]
    notes: list[str] = []
    if len(i_est) < len(est):
        notes.append(f"matched {len(i_est)} of {len(est)} estimated poses")
    ate = absolute_pose_errors(G, P, align=align)
    out: dict[str, Any] = {
        "gt_poses": len(gt),
        "est_poses": len(est),
        "matched": int(len(i_gt)),
        "association": "index" if by_index else ("interpolated" if interpolate else "time"),
        "max_time_diff_s": None if by_index else float(max_time_diff_s),
        "duration_s": float(stamps[-1] - stamps[0]) if not by_index else None,
        "path_length_m": Trajectory(stamps, G).path_length(),
        "aligned": bool(align),
        "align_T_gt_est": ate.T_align.tolist() if align else None,
    }
    stats = ate.stats()
    for name, field, unit in (("trans", "trans_m", "_m"), ("full", "full", ""), ("rot", "rot_deg", "_deg")):
        for s in ATE_STATS:
            out[f"ate_{name}_{s}{unit}"] = stats[field][s]

    deltas = [float(d) for d in rpe_deltas_m]
    out["rpe_deltas_m"] = deltas
    for delta in deltas:
        key = rpe_key(delta)
        rpe = relative_pose_errors(G, P, delta)
        if rpe is None:
            notes.append(f"RPE {delta:g} m skipped: the matched ground truth is {out['path_length_m']:.1f} m long")
            for k in ("pairs", "trans_rmse_m", "trans_mean_m", "trans_mean_pct", "rot_rmse_deg",
                      "rot_mean_deg", "rot_mean_deg_per_m"):
                out[f"{key}_{k}"] = None
            continue
        out[f"{key}_pairs"] = int(len(rpe.i))
        out[f"{key}_trans_rmse_m"] = float(np.sqrt(np.mean(rpe.trans_m**2)))
        out[f"{key}_trans_mean_m"] = float(np.mean(rpe.trans_m))
        out[f"{key}_trans_mean_pct"] = float(np.mean(rpe.trans_pct))
        out[f"{key}_rot_rmse_deg"] = float(np.sqrt(np.mean(rpe.rot_deg**2)))
        out[f"{key}_rot_mean_deg"] = float(np.mean(rpe.rot_deg))
        out[f"{key}_rot_mean_deg_per_m"] = float(np.mean(rpe.rot_deg_per_m))

    breakdown = None
    if not by_index:
        from blockloc.evaluation.breakdown import breakdown_metrics, error_breakdown

        try:
            breakdown = error_breakdown(stamps, G, ate.T_align @ P)
            out.update(breakdown_metrics(breakdown))
        except EvaluationError as exc:  # fewer than two matched poses
            notes.append(f"no error breakdown: {exc}")

    plots: list[str] = []
    if plot_dir is not None:
        from blockloc.evaluation.plots import plot_error_breakdown, plot_errors_over_time, plot_trajectories

        plot_dir = Path(plot_dir)
        P_shown = ate.T_align @ P
        tag = " (aligned)" if align else ""
        plots.append(str(plot_trajectories(plot_dir / "trajectories.png", gt.positions[:, :2],
                                           P_shown[:, :3, 3][:, :2], ate.trans_m,
                                           title=f"ATE RMSE {out['ate_trans_rmse_m']:.3f} m{tag}")))
        plots.append(str(plot_errors_over_time(plot_dir / "errors.png", stamps, ate.trans_m, ate.rot_deg)))
        if breakdown is not None:
            plots.append(str(plot_error_breakdown(plot_dir / "error_breakdown.png", stamps, breakdown,
                                                  out["err_by_speed"], out["err_by_turn_rate"])))
    out["notes"] = notes
    out["plots"] = plots
    for note in notes:
        log.info("%s", note)
    return out


def evaluate_files(gt: Path, est: Path, *, align: bool = False, max_time_diff_s: float = 0.02,
                   plot_dir: Path | None = None,
                   rpe_deltas_m: Sequence[float] = DEFAULT_RPE_DELTAS_M,
                   interpolate: bool = False) -> dict[str, Any]:
    """Read ``gt`` (TUM, KITTI or NCLT csv) and ``est`` (TUM or KITTI) and evaluate them.

    A KITTI file without a times file is paired with the other trajectory by index.
    Returns ``evaluate_trajectories``' dict plus ``gt_file`` and ``est_file``.
    """
    from blockloc.trajectory_io import read_trajectory_file

    gt_file = read_trajectory_file(gt)
    est_file = read_trajectory_file(est)
    by_index = not (gt_file.timed and est_file.timed)
    try:
        out = evaluate_trajectories(gt_file.trajectory, est_file.trajectory, align=align,
                                    max_time_diff_s=max_time_diff_s, rpe_deltas_m=rpe_deltas_m,
                                    plot_dir=plot_dir, by_index=by_index, interpolate=interpolate)
    except EvaluationError as exc:
        raise EvaluationError(f"{est} vs {gt}: {exc}") from None
    return {"gt_file": str(gt), "est_file": str(est), **out}
