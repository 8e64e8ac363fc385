"""``blockloc eval``: ATE and RPE of an estimate file against a ground-truth file, as tables or JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from blockloc.evaluation.report import ATE_STATS, rpe_key


def eval_command(gt: Path, est: Path, align: bool, json_out: bool, plot: Path | None, max_time_diff: float,
                 interpolate: bool, rpe_deltas: str) -> None:
    from blockloc.commands.common import console, parse_deltas
    from blockloc.evaluation.report import evaluate_files

    if plot is not None:  # before any work: a folder of blockloc's plots (or a new one), writable, ours
        from blockloc.outdir import PLOTS, RESULTS, claim_output

        claim_output(plot, "--plot", need_bytes=2**20, kinds=(PLOTS, RESULTS), kind="a plot or results folder")
    metrics = evaluate_files(gt, est, align=align, max_time_diff_s=max_time_diff, plot_dir=plot,
                             interpolate=interpolate, rpe_deltas_m=parse_deltas(rpe_deltas))
    if plot is not None and Path(plot).is_dir():
        from blockloc.outdir import PLOTS, owner, write_marker

        if owner(plot) is None:  # a new plot folder: blockloc's from now on (a results folder stays one)
            write_marker(plot, PLOTS)
    if json_out:
        print(json.dumps(metrics))
    else:
        print_metrics(metrics, console())


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def print_metrics(metrics: dict[str, Any], console) -> None:
    """Print ``metrics`` (from ``evaluate_*``) as rich tables on ``console``."""
    from rich.markup import escape
    from rich.table import Table

    head = Table(title="trajectory evaluation", show_header=False, box=None)
    head.add_column("what", style="bold")
    head.add_column("value")
    for key in ("gt_file", "est_file"):
        if key in metrics:
            head.add_row(key.replace("_", " "), escape(str(metrics[key])))
    head.add_row("matched", f"{metrics['matched']} of {metrics['est_poses']} estimated "
                            f"({metrics['gt_poses']} ground truth), by {metrics['association']}")
    if metrics.get("duration_s") is not None:
        head.add_row("duration", f"{metrics['duration_s']:.1f} s")
    head.add_row("path length", f"{metrics['path_length_m']:.1f} m")
    head.add_row("aligned", "yes (Umeyama SE(3))" if metrics["aligned"] else "no (map frame)")
    console.print(head)

    ate = Table(title="ATE (absolute pose error)")
    ate.add_column("error")
    for s in ATE_STATS:
        ate.add_column(s, justify="right")
    ate.add_row(escape("translation [m]"), *[_fmt(metrics[f"ate_trans_{s}_m"]) for s in ATE_STATS])
    ate.add_row(escape("full ||E-I||_F"), *[_fmt(metrics[f"ate_full_{s}"]) for s in ATE_STATS])
    ate.add_row(escape("rotation [deg]"), *[_fmt(metrics[f"ate_rot_{s}_deg"], 3) for s in ATE_STATS])
    console.print(ate)

    rpe = Table(title="RPE (relative pose error over path length)")
    for col in ("delta", "pairs", "trans RMSE\n[m]", "trans mean\n[%]", "rot RMSE\n[deg]", "rot mean\n[deg/m]"):
        rpe.add_column(escape(col), justify="right")
    for delta in metrics.get("rpe_deltas_m", []):
        k = rpe_key(delta)
        rpe.add_row(f"{delta:g} m", _fmt(metrics[f"{k}_pairs"]), _fmt(metrics[f"{k}_trans_rmse_m"]),
                    _fmt(metrics[f"{k}_trans_mean_pct"], 2), _fmt(metrics[f"{k}_rot_rmse_deg"], 3),
                    _fmt(metrics[f"{k}_rot_mean_deg_per_m"], 4))
    console.print(rpe)
    if "err_time_shift_s" in metrics:
        print_breakdown(metrics, console)
    for note in metrics.get("notes", []):
        console.print(f"note: {escape(note)}", style="yellow")
    for plot in metrics.get("plots", []):
        console.print(f"plot: {escape(plot)}")


def print_breakdown(metrics: dict[str, Any], console) -> None:
    """The error breakdown keys (``err_...``, :mod:`blockloc.evaluation.breakdown`) as tables."""
    from rich.markup import escape
    from rich.table import Table

    comp = Table(title="position error by direction (along / cross: horizontal direction of travel)")
    for col in ("component", "mean [m]", "RMS [m]"):
        comp.add_column(escape(col), justify="right" if col != "component" else "left")
    for name, label in (("along", "along track (+ ahead)"), ("cross", "cross track (+ z x forward)"),
                        ("vertical", "vertical (map z)")):
        comp.add_row(label, _fmt(metrics[f"err_{name}_mean_m"]), _fmt(metrics[f"err_{name}_rms_m"]))
    console.print(comp)
    shift = metrics["err_time_shift_s"]
    if shift is not None:
        console.print(f"time shift that best explains the along-track error: {shift:+.4f} s "
                      f"(+: the estimate lags; along-track RMS {_fmt(metrics['err_along_rms_m'])} m -> "
                      f"{_fmt(metrics['err_along_rms_after_shift_m'])} m without it; "
                      f"{metrics['err_moving_poses']} moving poses)")
    if metrics.get("err_along_offset_m") is not None:
        console.print(f"with a constant along-track offset as well: time shift "
                      f"{metrics['err_time_shift_with_offset_s']:+.4f} s, offset {metrics['err_along_offset_m']:+.4f} m")
    x, y, z = metrics["err_offset_m"]
    console.print(f"constant offset (mean error, map frame): [{x:+.4f}, {y:+.4f}, {z:+.4f}] m")
    if metrics.get("err_body_offset_m") is not None:
        x, y, z = metrics["err_body_offset_m"]
        console.print(f"constant offset in the body frame (a mounting translation shows here): "
                      f"[{x:+.4f}, {y:+.4f}, {z:+.4f}] m")
    for key, label, unit in (("err_by_speed", "speed", "m/s"), ("err_by_turn_rate", "turn rate", "deg/s")):
        t = Table(title=f"error against {label}")
        for col in (f"{label} [{unit}]", "poses", "trans RMSE\n[m]", "along mean\n[m]", "along RMS\n[m]",
                    "cross RMS\n[m]"):
            t.add_column(escape(col), justify="right")
        for r in metrics[key]:
            span = f"{r['lo']:g} - {r['hi']:g}" if r["hi"] is not None else f">= {r['lo']:g}"
            t.add_row(span, str(r["count"]), _fmt(r["trans_rmse_m"]), _fmt(r["along_mean_m"]),
                      _fmt(r["along_rms_m"]), _fmt(r["cross_rms_m"]))
        console.print(t)
