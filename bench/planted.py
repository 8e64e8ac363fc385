"""What each planted error of the simulator costs in ATE (issue 41): the small world of one seed
simulated again with one error source off at a time, mapped and tracked with the defaults.

    python -m bench.planted                                  # seed 2, the first 400 frames of loc
    python -m bench.planted --seed 2 --frames 400 --work /work/data2/accuracy/planted
    python -m bench.planted --errors none,imu_time_offset --modes default   # a quick subset

For every error E (``none``: all on, the world as ``blockloc sim`` makes it) and mode M:

- the localization session with E off, its first ``--frames`` frames written once
  (``blockloc.sim.generate_dataset(..., sessions=("loc",), max_frames=N, <preset field>=...)``,
  the same draws for every other error source: each is scaled from its own random stream);
- the block map of the mapping session with E off (rendered on the fly, keyframes only), built as
  ``blockloc map build`` does with the config's ``map`` settings; only errors of the map drive
  (``MAP_ERRORS``) build their own map, the others share ``none``'s;
- ``blockloc track --seq LOC --map MAP --init gt --max-frames N --no-record`` and
  ``blockloc eval --interpolate --json``, as a user types them.

Modes: ``default`` (this checkout's defaults: mounting rotation estimated, translation only where
the drive determines it) and ``full`` (``map.mounting_translation_tolerance_m=0``: the estimated
translation on every observed axis, the default before issue 41). Writes
docs/bench/planted_errors.md: the ATE of each row and what switching the error off gains.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

from blockloc.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "planted_errors.md"
#: error name: (what it is, the preset fields it sets: "group.field" or "field")
ERRORS = {
    "none": ("every error on (the world as `blockloc sim` makes it)", {}),
    "imu_time_offset": ("IMU stamps lag by 4 ms", {"imu.time_offset_s": 0.0}),
    "imu_scale_factor": ("IMU scale factor 0.3 % per axis", {"imu.scale_factor_sigma": 0.0}),
    "imu_misalignment": ("IMU axis misalignment 1.5 mrad", {"imu.misalignment_sigma_rad": 0.0}),
    "imu_bias_instability": ("IMU bias instability (Gauss-Markov)",
                             {"imu.acc_bias_instability": 0.0, "imu.gyro_bias_instability": 0.0}),
    "imu_drops": ("lost IMU samples", {"imu.drop_prob": 0.0, "imu.drop_burst_per_min": 0.0}),
    "laser_offsets": ("per-laser range and angle offsets",
                      {"lidar.laser_range_offset_m": 0.0, "lidar.laser_angle_offset_deg": 0.0}),
    "mounting": ("LiDAR mounting 1 cm / 0.3 deg off the nominal",
                 {"extrinsic_error_m": 0.0, "extrinsic_error_deg": 0.0}),
    "slam": ("mapping drive's offline-SLAM pose error (3 cm, 0.002 rad)",
             {"slam_error_m": 0.0, "slam_error_rad": 0.0}),
}
#: Errors that change the mapping drive (its own map); the IMU's reach only the localization drive.
MAP_ERRORS = {"laser_offsets", "mounting", "slam"}
LOC_ERRORS = set(ERRORS) - {"slam"}  # the SLAM error is the map drive's poses only
MODES = {"default": [], "full": ["map.mounting_translation_tolerance_m=0"]}


def preset_overrides(name: str, fields: dict) -> dict:
    """``get_preset`` overrides (top-level preset fields) that set ``fields`` ({"group.field" |
    "field": value}) of the preset ``name``."""
    from blockloc.sim.presets import get_preset

    p = get_preset(name)
    top, groups = {}, {}
    for key, value in fields.items():
        group, _, field = key.rpartition(".")
        if group:
            groups.setdefault(group, {})[field] = value
        else:
            top[field] = value
    for group, vals in groups.items():
        top[group] = replace(getattr(p, group), **vals)
    return top


def _blockloc(args: list[str], log: Path) -> str:
    """``blockloc ARGS`` (this checkout's, nice'd); its stdout; output also appended to ``log``."""
    print("$ blockloc " + shlex.join(args), flush=True)
    res = subprocess.run(["nice", sys.executable, "-m", "blockloc.cli", *args], capture_output=True, text=True,
                         cwd=ROOT)
    with open(log, "a") as fh:
        fh.write("$ blockloc " + shlex.join(args) + "\n" + res.stderr[-4000:])
    if res.returncode:
        raise SystemExit(f"blockloc {shlex.join(args)}: exit {res.returncode} (see {log})")
    return res.stdout


def ensure_loc(work: Path, preset: str, seed: int, error: str, frames: int) -> Path:
    """The localization session with ``error`` off (``none``'s for errors that do not reach it)."""
    from blockloc.sim import generate_dataset

    if error not in LOC_ERRORS:
        error = "none"
    out = work / f"loc_{error}_{frames}"
    if not (out / "loc").is_dir():
        print(f"simulating loc with {error} off ({frames} frames) -> {out}", flush=True)
        generate_dataset(preset, seed, out, sessions=("loc",), max_frames=frames,
                         **preset_overrides(preset, ERRORS[error][1]))
    return out / "loc"


def ensure_map(work: Path, preset: str, seed: int, error: str, mode: str) -> Path:
    """The block map of the mapping drive with ``error`` off, built with ``mode``'s settings."""
    from blockloc.app.runs import build_map
    from blockloc.config import load_config
    from blockloc.errors import MapError
    from blockloc.maps.store import open_map
    from blockloc.sim.presets import get_preset
    from blockloc.sim.stream import SimSequence

    if error not in MAP_ERRORS:
        error = "none"
    out = work / f"map_{error}_{mode}"
    try:
        open_map(out)
        return out
    except MapError:
        pass
    overrides: dict = {}
    for item in MODES[mode]:  # "section.key=value" as --set takes it
        key, value = item.split("=", 1)
        section, name = key.split(".")
        overrides.setdefault(section, {})[name] = float(value)
    cfg = load_config("sim", overrides=overrides)
    t0 = time.time()
    print(f"building the map with {error} off, mode {mode} -> {out}", flush=True)
    seq = SimSequence(get_preset(preset, **preset_overrides(preset, ERRORS[error][1])), "map", seed)
    build_map(seq, "block", out, cfg.map, overwrite=True)
    (work / f"map_{error}_{mode}.build_s").write_text(f"{time.time() - t0:.1f}\n")
    return out


def run_one(work: Path, preset: str, seed: int, error: str, mode: str, frames: int) -> dict:
    log = work / "planted.log"
    loc = ensure_loc(work, preset, seed, error, frames)
    m = ensure_map(work, preset, seed, error, mode)
    r = work / f"run_{error}_{mode}_{frames}"
    if not (r / "metrics.json").exists():
        _blockloc(["track", "--seq", str(loc), "--map", str(m), "--init", "gt", "--max-frames", str(frames),
                   "--no-record", "--out", str(r)], log)
    ev = r / "eval.json"
    if not ev.exists():
        (gt,) = sorted(loc.glob("groundtruth_*.csv"))
        atomic_write_text(ev, _blockloc(["eval", "--gt", str(gt), "--est", str(r / "poses.tum"), "--interpolate",
                                         "--json"], log))
    metrics = json.loads((r / "metrics.json").read_text())
    mounting = {}
    params = json.loads((m / "manifest.json").read_text()).get("parameters", {})
    for est in (params.get("mounting") or {}).values():
        mounting = {"translation_estimated": est.get("translation_estimated", "xyz")}
    return {**json.loads(ev.read_text()), "failures": metrics.get("failures"), **mounting}


def report(rows: dict, argv: list[str], started: str, load0: float, seed: int, frames: int, modes: list[str],
           cpu_s: float) -> str:
    from bench.__main__ import machine

    cmd = "python -m bench.planted" + (" " + shlex.join(argv) if argv else "")
    lines = ["## What each planted simulator error costs (issue 41)", "",
             f"Command: `{cmd}` (started {started}). Machine: {machine()}. Load average (1 min) {load0:.1f} at "
             f"the start, {os.getloadavg()[0]:.1f} at the end; this process's CPU time {cpu_s:.0f} s (the "
             "tracks run in child processes, not counted). "
             f"Small world, seed {seed}, the first {frames} frames of its localization session; each row "
             "switches one error source off in both drives it reaches (see `bench/planted.py`), maps and "
             "tracks as the defaults do (`--init gt`); `full` builds with "
             "`--set map.mounting_translation_tolerance_m=0` (the estimated mounting translation "
             "whatever the drive determines, the default before issue 41). Gain = ATE with every error "
             "on minus ATE with this one off (+: the error costs that much).", "",
             "| error switched off | what it is | " + " | ".join(
                 f"ATE {m} [m] | gain {m} [mm] | rotation {m} [deg] | along mean {m} [cm]" for m in modes)
             + " | failures | map's mounting translation (axes estimated) |",
             "|---|---|" + "---|---|---|---|" * len(modes) + "---|---|"]
    for error, by_mode in rows.items():
        cells = []
        for m in modes:
            r = by_mode.get(m)
            base = rows.get("none", {}).get(m)
            if r is None:
                cells += ["-"] * 4
                continue
            gain = "-" if base is None or error == "none" else \
                f"{1000 * (base['ate_trans_rmse_m'] - r['ate_trans_rmse_m']):+.1f}"
            cells += [f"{r['ate_trans_rmse_m']:.4f}", gain, f"{r['ate_rot_rmse_deg']:.3f}",
                      f"{100 * r['err_along_mean_m']:+.1f}"]
        fails = ", ".join(str(by_mode[m].get("failures")) for m in modes if m in by_mode)
        axes = ", ".join((by_mode[m].get("translation_estimated") or "nominal") if "translation_estimated"
                         in by_mode[m] else "-" for m in modes if m in by_mode)
        lines.append(f"| {error} | {ERRORS[error][0]} | " + " | ".join(cells) + f" | {fails} | {axes} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--frames", type=int, default=400, help="frames of the localization session")
    ap.add_argument("--errors", default=",".join(ERRORS))
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--work", type=Path, default=None, help="where sessions, maps and runs are kept "
                    "(default: <blockloc cache>/bench-planted)")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    errors = [e for e in args.errors.split(",") if e]
    modes = [m for m in args.modes.split(",") if m]
    bad = [e for e in errors if e not in ERRORS] + [m for m in modes if m not in MODES]
    if bad:
        ap.error(f"unknown {', '.join(bad)}: errors are {', '.join(ERRORS)}; modes {', '.join(MODES)}")
    if args.work is None:
        from blockloc.cache import cache_root

        args.work = Path(cache_root()) / "bench-planted"
    args.work.mkdir(parents=True, exist_ok=True)
    started, load0, c0 = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), os.getloadavg()[0], time.process_time()
    rows: dict = {}
    for error in errors:
        for mode in modes:
            rows.setdefault(error, {})[mode] = run_one(args.work, args.preset, args.seed, error, mode, args.frames)
            atomic_write_text(args.out, report(rows, argv, started, load0, args.seed, args.frames, modes,
                                               time.process_time() - c0))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
