"""PNG plots of an evaluation (matplotlib, Agg backend, imported lazily)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from blockloc.fileio import atomic_path, figure_mark_kwargs

log = logging.getLogger(__name__)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    """Save ``fig`` as PNG to a temp file beside ``path``, then rename it into place."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=120, format="png", **figure_mark_kwargs("png"))
    return path


def plot_trajectories(path: Path, gt_xy_all: np.ndarray, est_xy: np.ndarray, errors_m: np.ndarray,
                      *, title: str = "") -> Path:
    """Top view: the whole ground truth as a line, the matched estimate coloured by its ATE.

    gt_xy_all: (N, 2) ground-truth positions, map frame, metres; est_xy: (K, 2) estimated positions
    (aligned if alignment was used); errors_m: (K,) translation error of each estimated position.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 6))
    try:
        ax.plot(gt_xy_all[:, 0], gt_xy_all[:, 1], color="0.6", lw=1.5, label="ground truth")
        sc = ax.scatter(est_xy[:, 0], est_xy[:, 1], c=errors_m, s=4, cmap="viridis", label="estimate")
        fig.colorbar(sc, ax=ax, label="translation error [m]")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(loc="best")
        ax.set_title(title or "trajectories (top view)")
        fig.tight_layout()
        return _save(fig, Path(path))
    finally:
        plt.close(fig)


def plot_errors_over_time(path: Path, stamps: np.ndarray, trans_m: np.ndarray, rot_deg: np.ndarray,
                          *, title: str = "") -> Path:
    """Translation (m) and rotation (deg) error over time (s from the first matched stamp)."""
    plt = _pyplot()
    t = np.asarray(stamps, dtype=np.float64)
    t = t - t[0] if len(t) else t
    fig, (ax_t, ax_r) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    try:
        ax_t.plot(t, trans_m, lw=1.0)
        ax_t.axhline(float(np.sqrt(np.mean(np.square(trans_m)))), color="C3", ls="--", lw=1, label="RMSE")
        ax_t.set_ylabel("translation error [m]")
        ax_t.legend(loc="upper right")
        ax_r.plot(t, rot_deg, lw=1.0, color="C1")
        ax_r.set_ylabel("rotation error [deg]")
        ax_r.set_xlabel("time [s]")
        ax_t.set_title(title or "absolute error over time")
        fig.tight_layout()
        return _save(fig, Path(path))
    finally:
        plt.close(fig)


def plot_error_breakdown(path: Path, stamps: np.ndarray, breakdown, by_speed: list[dict],
                         by_turn_rate: list[dict], *, title: str = "") -> Path:
    """Along-track, cross-track and vertical error over time (m; s from the first matched stamp),
    then translation RMSE and along-track mean against speed and against turn rate (one point a
    bin, at the bin's lower edge). breakdown: :class:`blockloc.evaluation.breakdown.ErrorBreakdown`;
    by_speed, by_turn_rate: its ``table`` rows."""
    plt = _pyplot()
    t = np.asarray(stamps, dtype=np.float64)
    t = t - t[0] if len(t) else t
    fig = plt.figure(figsize=(9, 7))
    try:
        ax = fig.add_subplot(2, 1, 1)
        ax.plot(t, breakdown.along_m, lw=1.0, label="along track")
        ax.plot(t, breakdown.cross_m, lw=1.0, label="cross track")
        ax.plot(t, breakdown.vertical_m, lw=1.0, label="vertical (map z)")
        ax.axhline(0.0, color="0.5", lw=0.8)
        shift = breakdown.time_shift_s
        ax.set_title(title or ("position error components" + (
            f" (best time shift {1000 * shift:+.1f} ms)" if shift is not None else "")))
        ax.set_ylabel("error [m]")
        ax.set_xlabel("time [s]")
        ax.legend(loc="upper right")
        for k, (rows, label) in enumerate(((by_speed, "speed [m/s]"), (by_turn_rate, "turn rate [deg/s]"))):
            bx = fig.add_subplot(2, 2, 3 + k)
            x = np.arange(len(rows))
            rmse = [r["trans_rmse_m"] for r in rows]
            along = [np.nan if r["along_mean_m"] is None else r["along_mean_m"] for r in rows]
            bx.bar(x - 0.2, rmse, width=0.4, label="translation RMSE")
            bx.bar(x + 0.2, along, width=0.4, label="along-track mean")
            bx.axhline(0.0, color="0.5", lw=0.8)
            bx.set_xticks(x, [f"{r['lo']:g}-{'' if r['hi'] is None else format(r['hi'], 'g')}\n({r['count']})"
                              for r in rows], fontsize=7)
            bx.set_xlabel(f"{label} (poses)")
            bx.set_ylabel("error [m]")
            bx.legend(loc="best", fontsize=7)
        fig.tight_layout()
        return _save(fig, Path(path))
    finally:
        plt.close(fig)
