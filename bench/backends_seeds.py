"""Every map backend and registration engine over several small-world seeds (issue 41): writes
docs/bench/backends_seeds.md.

    python -m bench.backends_seeds --work W --seeds 1,2,3         # W as bench.seeds lays it out
    python -m bench.backends_seeds --work W --seeds 1 --frames 200

Per seed, in the work directory of ``python -m bench.seeds`` (its world ``sS`` and default block map
``sS_map``, made there when missing): a grid map (``map build --kind grid``) beside the block map,
then ``blockloc track --init gt`` with the defaults on each backend and engine: block (NDT, the
default), block with VGICP, grid, SRT (the grid tiles merged within a radius) and global (every
block at once). Nothing here is tuned: every run is the defaults, so every seed is held out. The
report gives each run's ATE, rotation, failures and along-track mean, and per backend the median and
worst over the seeds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from bench.seeds import _blockloc

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "backends_seeds.md"
#: name: (map suffix, track options)
RUNS = {
    "block (NDT)": ("", []),
    "block, VGICP": ("", ["--set", "registration.method=vgicp"]),
    "grid": ("_grid", ["--map-backend", "grid"]),
    "srt": ("_grid", ["--map-backend", "srt"]),
    "global": ("", ["--map-backend", "global"]),
}
SLUG = {"block (NDT)": "block", "block, VGICP": "vgicp", "grid": "grid", "srt": "srt", "global": "global"}


def run_seed(work: Path, preset: str, seed: int, frames: int) -> dict:
    """{run name: metrics} of one seed (every step skipped when its output is there)."""
    log = work / f"s{seed}_backends.log"
    world = work / f"s{seed}"
    if not (world / "loc").is_dir():
        _blockloc(["sim", "--preset", preset, "--seed", str(seed), "--out", str(world)], log)
    out = {}
    for name, (suffix, extra) in RUNS.items():
        m = work / f"s{seed}_map{suffix}"
        if not (m / "manifest.json").exists():
            kind = "grid" if suffix == "_grid" else "block"
            _blockloc(["map", "build", "--seq", str(world / "map"), "--kind", kind, "--out", str(m)], log)
        r = work / (f"s{seed}_run_backend_{SLUG[name]}" + (f"_f{frames}" if frames else ""))
        if not (r / "metrics.json").exists():
            _blockloc(["track", "--seq", str(world / "loc"), "--map", str(m), "--init", "gt", *extra, "--no-record",
                       *(["--max-frames", str(frames)] if frames else []), "--out", str(r)], log)
        out[name] = json.loads((r / "metrics.json").read_text())
    return out


def report(res: dict, preset: str, frames: int, cmd: str, started: str, machine: str) -> list[str]:
    """The fragment's lines from {seed: {run name: metrics.json}}."""
    seeds = sorted(res)
    lines = [f"## Map backends and engines over small-world seeds {', '.join(map(str, seeds))} (issue 41)", "",
             f"Command: `{cmd}` (started {started}). Machine: {machine}.",
             "", f"`blockloc track --init gt` with the defaults on the `{preset}` world's `loc` session of each "
             "seed, " + (f"first {frames} frames" if frames else "every frame") + "; block maps as `map build` "
             "makes them (the mounting estimated), grid tiles of the same drive for grid and SRT. Nothing was tuned "
             "for this table: every seed is held out.", "",
             "| seed | run | ATE [m] | max [m] | rotation [deg] | along-track mean [cm] | failures | rejected | frames |",
             "|---|---|---|---|---|---|---|---|---|"]
    for s in seeds:
        for name, m in res[s].items():
            along = m.get("err_along_mean_m")
            lines.append(f"| {s} | {name} | {m['ate_trans_rmse_m']:.3f} | {m['ate_trans_max_m']:.3f} | "
                         f"{m['ate_rot_rmse_deg']:.3f} | {'-' if along is None else f'{100 * along:+.1f}'} | "
                         f"{m['failures']} | {m['rejected']} | {m['frames']} |")
    lines += ["", "| run | ATE median [m] | ATE worst [m] | rotation worst [deg] | failures (all seeds) |",
              "|---|---|---|---|---|"]
    for name in RUNS:
        ate = [res[s][name]["ate_trans_rmse_m"] for s in seeds]
        rot = [res[s][name]["ate_rot_rmse_deg"] for s in seeds]
        fails = sum(res[s][name]["failures"] for s in seeds)
        lines.append(f"| {name} | {statistics.median(ate):.3f} | {max(ate):.3f} | {max(rot):.3f} | {fails} |")
    lines.append("")
    return lines


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(prog="python -m bench.backends_seeds")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--frames", type=int, default=0, help="track only the first N frames (0: all)")
    ap.add_argument("--work", type=Path, required=True, help="a bench.seeds work directory")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    from bench.__main__ import machine
    from blockloc.fileio import atomic_write_text

    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    args.work.mkdir(parents=True, exist_ok=True)
    cmd = "python -m bench.backends_seeds " + " ".join(argv if argv is not None else sys.argv[1:])
    started = time.gmtime()
    res = {s: run_seed(args.work, args.preset, s, args.frames) for s in seeds}
    lines = report(res, args.preset, args.frames, cmd.strip(), time.strftime('%Y-%m-%d %H:%M UTC', started), machine())
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return args.out


if __name__ == "__main__":
    main()
