"""Benchmark of trajectory evaluation at the scale of a long drive.

    python -m bench.evaluation [--poses 53000] [--repeats 5]

A campus-scale run (NCLT 2012-01-22: 6.36 km in 87 min; LiDAR at 10 Hz gives ~53k estimated
poses) against 100 Hz ground truth: times reading the TUM files, evaluating (association, ATE,
RPE 1/10/100 m), plotting, and `blockloc eval --json` end to end. Writes docs/bench/evaluation.md.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from blockloc.fileio import atomic_write_text
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent


def _trajectory(n: int, dt: float, seed: int):
    from blockloc.geometry import Trajectory

    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 0.01, n))
    pos = np.cumsum(1.2 * dt * np.stack([np.cos(yaw), np.sin(yaw), np.zeros(n)], 1), 0)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix().reshape(n, 3, 3)
    poses[:, :3, 3] = pos
    return Trajectory(1326044400.0 + dt * np.arange(n), poses)


def _median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def main(argv: list[str] | None = None) -> int:
    from bench.__main__ import machine
    from blockloc.evaluation.report import evaluate_trajectories
    from blockloc.trajectory_io import read_tum, write_tum
    from blockloc.geometry import Trajectory

    ap = argparse.ArgumentParser()
    ap.add_argument("--poses", type=int, default=53000, help="estimated poses (10 Hz)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    n_est = args.poses
    gt = _trajectory(n_est * 10, 0.01, seed=1)
    rng = np.random.default_rng(2)
    idx = np.arange(5, len(gt), 10)
    est_poses = gt.poses[idx].copy()
    est_poses[:, :3, 3] += rng.normal(0, 0.05, (len(idx), 3))
    est = Trajectory(gt.stamps[idx] + rng.uniform(-0.002, 0.002, len(idx)), est_poses)

    import os

    load_before = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t_write, _ = _median_time(lambda: write_tum(tmp / "est.tum", est), args.repeats)
        write_tum(tmp / "gt.tum", gt)
        t_read_est, _ = _median_time(lambda: read_tum(tmp / "est.tum"), args.repeats)
        t_read_gt, _ = _median_time(lambda: read_tum(tmp / "gt.tum"), args.repeats)
        t_eval, m = _median_time(lambda: evaluate_trajectories(gt, est), args.repeats)
        t_interp, _ = _median_time(lambda: evaluate_trajectories(gt, est, interpolate=True), args.repeats)
        t_plot, _ = _median_time(lambda: evaluate_trajectories(gt, est, rpe_deltas_m=(), plot_dir=tmp / "p"),
                                 max(1, args.repeats // 2))
        cmd = ["blockloc", "eval", "--gt", str(tmp / "gt.tum"), "--est", str(tmp / "est.tum"), "--json"]
        t_cli, _ = _median_time(lambda: subprocess.run(cmd, check=True, capture_output=True), args.repeats)
        rows += [
            ("write TUM, estimate", f"{len(est):,} poses", t_write),
            ("read TUM, estimate", f"{len(est):,} poses", t_read_est),
            ("read TUM, ground truth", f"{len(gt):,} poses", t_read_gt),
            ("evaluate (nearest association, ATE, RPE 1/10/100 m)", f"{m['matched']:,} matched", t_eval),
            ("evaluate with --interpolate", f"{m['matched']:,} matched", t_interp),
            ("evaluate + 2 PNG plots (no RPE)", "", t_plot),
            ("`blockloc eval --json` end to end (both files)", "", t_cli),
        ]
    this_cmd = "python -m bench.evaluation " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    lines = [
        "## Trajectory evaluation",
        "",
        f"Command: `{this_cmd.strip()}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}).",
        f"Machine: {machine()}. Load average (1 min) {load_before:.1f} before and "
        f"{os.getloadavg()[0]:.1f} after the run (other processes share the 2 cores, so times are upper bounds).",
        "",
        f"A simulated {len(est) * 0.12 / 1000:.1f} km drive: estimate at 10 Hz, ground truth at 100 Hz "
        f"(campus scale, like NCLT 2012-01-22). Median of {args.repeats} runs.",
        "",
        "| step | size | median time [s] |",
        "|---|---|---|",
    ]
    lines += [f"| {name} | {size} | {t:.3f} |" for name, size, t in rows]
    out = ROOT / "docs" / "bench" / "evaluation.md"
    atomic_write_text(out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
