"""How real the simulator looks (issue 15): the realism statistics (``blockloc.evaluation.realism``)
on the real HDL-32E scans, the old simulator (git 700dd19, run from a temporary worktree) and the
new one, medians over >= 20 scans; then KISS-ICP's horizontal drift on the new `small` and
`campus` worlds. Writes docs/bench/realism.md.

    python -m bench.realism                # full (KISS-ICP over 600+ campus scans: ~1 h)
    python -m bench.realism --quick        # fewer scans, shorter KISS-ICP runs
    python -m bench.realism --seed 7       # another world (the tests use seeds 1-6)
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "realism.md"
OLD_COMMIT = "700dd19"
REAL = ("source", "target")

# dumps frames of a simulator as it was at OLD_COMMIT (run with that tree on PYTHONPATH)
_DUMP = """
import sys, numpy as np
from blockloc.sim.stream import open_sim_sequence
out = {}
preset, session, seed, n = sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
s = open_sim_sequence(preset, session, seed)
for i in np.linspace(20, len(s) - 20, n).astype(int):
    f = s.frame(int(i))
    out[f"{i}_pts"], out[f"{i}_int"], out[f"{i}_ring"] = f.points, f.intensity, f.ring
np.savez_compressed(sys.argv[1], **out)
"""

ROWS = [("azimuth step", "azimuth_step_deg", "{:.3f} deg", None),
        ("non-ground points that are scattered (local PCA)", "scattered_share", "{:.1%}", (0.08, 0.30)),
        ("median local thickness of non-ground structure", "thickness_m", "{:.0f} mm", (0.04, 0.15)),
        ("flat-ground point-to-plane residual rms", "ground_residual_m", "{:.1f} mm", (0.015, 0.035)),
        ("points with intensity <= 3", "dark_share", "{:.1%}", (0.05, 1.0)),
        ("points with intensity >= 100", "bright_share", "{:.1%}", (0.0, 0.03)),
        ("ring-to-ring CV of ground intensity", "ground_ring_cv", "{:.2f}", (0.3, 10.0))]


def _fmt(key: str, fmt: str, v: float) -> str:
    if not np.isfinite(v):
        return "-"
    return fmt.format(v * 1000 if fmt.endswith("mm") else v)


def real_stats(data: Path) -> list[dict]:
    from pypcd4 import PointCloud

    from blockloc.evaluation.realism import scan_realism

    rows = []
    for name in REAL:
        a = PointCloud.from_path(data / "hdl32e_pair" / f"{name}.pcd").numpy().astype(np.float64)
        rows.append(scan_realism(a[:, :3], a[:, 3], None, up=(0, 0, 1)))
    return rows


def old_sim_stats(preset: str, seed: int, n: int) -> list[dict]:
    """Scans of the simulator at OLD_COMMIT (a temporary git worktree), statistics by this code."""
    from blockloc.evaluation.realism import scan_realism

    with tempfile.TemporaryDirectory(prefix="bench-realism-") as tmp:
        wt = Path(tmp) / "old"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(wt), OLD_COMMIT],
                       check=True, capture_output=True)
        try:
            npz = Path(tmp) / "old.npz"
            subprocess.run([sys.executable, "-c", _DUMP, str(npz), preset, "loc", str(seed), str(n)],
                           check=True, cwd=tmp, env={"PYTHONPATH": str(wt), "PATH": "/usr/bin:/bin",
                                                     "HOME": str(Path.home())})
            d = np.load(npz)
            keys = sorted({k.rsplit("_", 1)[0] for k in d.files}, key=int)
            return [scan_realism(d[f"{k}_pts"], d[f"{k}_int"], d[f"{k}_ring"], up=(0, 0, -1)) for k in keys]
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(wt)],
                           capture_output=True)


def new_sim_stats(preset: str, seed: int, n: int, session: str = "loc", profile: list | None = None,
                  **overrides) -> list[dict]:
    """Statistics of ``n`` scans spread over the session, each with ``surroundings`` (the kinds
    of the world's blocks within 8 m of the robot: buildings, park, parking, field = an open
    quad); ``profile``: a list to which each scan's (points, intensity) is appended (for the
    intensity-by-range table)."""
    from blockloc.evaluation.realism import scan_realism
    from blockloc.sim.stream import open_sim_sequence

    s = open_sim_sequence(preset, session, seed, **overrides)
    cells = s.scene.world.cells
    out = []
    for i in np.linspace(20, len(s) - 20, n).astype(int):
        f = s.frame(int(i))
        row = scan_realism(f.points, f.intensity, f.ring, up=(0, 0, -1))
        x, y = s.trajectory.T_world_flu(np.array([f.stamp - s.epoch_us * 1e-6]))[0, :2, 3]
        row["surroundings"] = "+".join(sorted({c["type"] for c in cells
                                               if c["rect"][0] - 8 <= x <= c["rect"][1] + 8
                                               and c["rect"][2] - 8 <= y <= c["rect"][3] + 8})) or "road"
        out.append(row)
        if profile is not None:
            profile.append((f.points, f.intensity))
    return out


def scattered_by_surroundings(rows: list[dict]) -> list[str]:
    """Markdown rows: the scattered share's median over the scans taken with and without an open
    quad (field) beside the robot, and over all."""
    groups = {"an open quad (field) within 8 m": [r for r in rows if "field" in r["surroundings"]],
              "no open quad within 8 m": [r for r in rows if "field" not in r["surroundings"]],
              "all": rows}
    lines = ["| scans taken beside | scans | scattered share (median) |", "|---|---|---|"]
    for name, rs in groups.items():
        v = [r["scattered_share"] for r in rs if np.isfinite(r["scattered_share"])]
        lines.append(f"| {name} | {len(v)} | {np.median(v):.1%} |" if v else f"| {name} | 0 | - |")
    return lines


def real_scans(data: Path) -> list:
    from pypcd4 import PointCloud

    out = []
    for name in REAL:
        a = PointCloud.from_path(data / "hdl32e_pair" / f"{name}.pcd").numpy().astype(np.float64)
        out.append((a[:, :3], a[:, 3]))
    return out


def range_table(profiles: dict) -> list[str]:
    """Markdown rows: per column, the intensity-by-range profile (dark share / median)."""
    from blockloc.evaluation.realism import RANGE_BINS_M, intensity_by_range

    got = {name: intensity_by_range(scans) for name, scans in profiles.items()}
    lines = ["| range | " + " | ".join(f"{n}: share / dark / median" for n in got) + " |",
             "|---|" + "---|" * len(got)]
    for k, (lo, hi) in enumerate(RANGE_BINS_M):
        cells = []
        for prof in got.values():
            b = prof[k]
            cells.append("-" if not np.isfinite(b["dark"]) else
                         f"{b['share']:.0%} / {b['dark']:.0%} / {b['median']:.0f}")
        lines.append(f"| {lo:.0f}-{hi:.0f} m | " + " | ".join(cells) + " |")
    return lines


def kiss_drift(preset: str, seed: int, n_frames: int) -> dict:
    """KISS-ICP over the first ``n_frames`` of the `loc` session: horizontal end-point drift and
    the horizontal ATE-free drift rate (final horizontal error / distance driven)."""
    sys.path.insert(0, str(ROOT))
    from bench._track import KissRun
    from blockloc.config import load_config
    from blockloc.sim.stream import open_sim_sequence

    seq = open_sim_sequence(preset, "loc", seed)
    cfg = load_config("sim")
    n = min(n_frames, len(seq))
    run = KissRun(seq, cfg, 0, n)
    t0 = time.perf_counter()
    for f in seq.frames(0, n):
        run.step(f)
    wall = time.perf_counter() - t0
    a = run.arrays()
    gt = seq.ground_truth().interpolate(a["stamps"])
    est = a["poses"]
    d = np.linalg.norm(np.diff(gt[:, :2, 3], axis=0), axis=1).sum()
    err = np.linalg.norm(est[:, :2, 3] - gt[:, :2, 3], axis=1)
    return {"frames": n, "distance_m": float(d), "final_err_m": float(err[-1]), "max_err_m": float(err.max()),
            "drift": float(err[-1] / max(d, 1e-9)), "ms_per_scan": 1e3 * wall / n}


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--skip-kiss", action="store_true")
    ap.add_argument("--scans", type=int, default=24, help="scans per simulated column (>= 20)")
    ap.add_argument("--kiss-frames", type=int, nargs=2, default=(1000, 650), metavar=("SMALL", "CAMPUS"))
    ap.add_argument("--out", type=Path, default=OUT,
                    help="where the fragment goes (default docs/bench/realism.md, whose notes are by hand)")
    args = ap.parse_args(argv)
    from bench.__main__ import machine

    from blockloc.evaluation.realism import median_stats
    from blockloc.sim.presets import get_preset

    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import shared_data_dir  # the same place the tests look

    n = 8 if args.quick else args.scans
    t_start = time.time()
    cols = {"real HDL-32E (2 scans)": median_stats(real_stats(shared_data_dir()))}
    for preset in ("small", "campus"):
        cols[f"old sim {preset} ({OLD_COMMIT})"] = median_stats(old_sim_stats(preset, args.seed, n))
    profiles = {"real HDL-32E": real_scans(shared_data_dir())}
    rows_by_world = {}
    for preset in ("small", "campus"):
        profiles[f"new sim {preset}"] = []
        rows_by_world[preset] = new_sim_stats(preset, args.seed, n, profile=profiles[f"new sim {preset}"])
        cols[f"new sim {preset}"] = median_stats(rows_by_world[preset])
    # the campus with every plant the generator places (before the campus preset thinned them)
    if get_preset("campus").vegetation < 1.0:
        cols["new sim campus, every plant (vegetation 1.0)"] = median_stats(
            new_sim_stats("campus", args.seed, n, vegetation=1.0))
    names = list(cols)
    lines = ["## Simulator realism", "",
             f"Machine: {machine()}. Command: `python -m bench.realism {' '.join(argv or sys.argv[1:])}`, run {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. "
             f"Statistics: `blockloc.evaluation.realism.scan_realism`, the same code on every column; "
             f"simulated columns are medians over {n} scans of the `loc` session (seed {args.seed}, a "
             f"seed the tests do not use); the old simulator runs from a temporary git worktree of "
             f"{OLD_COMMIT}. Target: issue 15's band for the new worlds.", "",
             "| statistic | " + " | ".join(names) + " | target |",
             "|---|" + "---|" * (len(names) + 1)]
    for label, key, fmt, band in ROWS:
        vals = [_fmt(key, fmt, cols[c][key]) for c in names]
        tgt = "-" if band is None else (f">= {_fmt(key, fmt, band[0])}" if band[1] >= 1.0 else
                                        f"<= {_fmt(key, fmt, band[1])}" if band[0] == 0 else
                                        f"{_fmt(key, fmt, band[0])} - {_fmt(key, fmt, band[1])}")
        lines.append(f"| {label} | " + " | ".join(vals) + f" | {tgt} |")
    lines += ["", "The scattered share of the new campus's scans by where they were taken (the localization "
              "session crosses open quads, where tree crowns are most of what stands above the lawn):", ""]
    lines += scattered_by_surroundings(rows_by_world["campus"])
    lines += ["", "Intensity by range, pooled over the same scans (`blockloc.evaluation.realism.intensity_by_range`): "
              "the share of returns in each range bin, the share of those reading <= 3, and their median "
              "intensity.", ""] + range_table(profiles)
    if args.skip_kiss:
        lines += ["", "KISS-ICP drift: not measured in this run (`--skip-kiss`)."]
    else:
        lines += ["", "KISS-ICP (LiDAR only, its defaults; bench._track.KissRun) on the new worlds' `loc` "
                  "sessions from the first frame, started at the true pose: horizontal error at the last "
                  "frame over the horizontal distance driven.", "",
                  "| world | scans | distance (m) | final horizontal error (m) | max (m) | drift | ms / scan |",
                  "|---|---|---|---|---|---|---|"]
        nfs = (300, 200) if args.quick else tuple(args.kiss_frames)
        for preset, nf in zip(("small", "campus"), nfs):
            k = kiss_drift(preset, args.seed, nf)
            lines.append(f"| {preset} | {k['frames']} | {k['distance_m']:.0f} | {k['final_err_m']:.2f} | "
                         f"{k['max_err_m']:.2f} | {k['drift']:.2%} | {k['ms_per_scan']:.0f} |")
        lines.append("")
        lines.append("Target (issue 15): KISS-ICP horizontal drift on 600+ campus scans 0.4-3 % of distance.")
    lines += ["", f"Run time {(time.time() - t_start) / 60:.1f} min."]
    from blockloc.fileio import atomic_write_text

    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return args.out


if __name__ == "__main__":
    main(sys.argv[1:])
