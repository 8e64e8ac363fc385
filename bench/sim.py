"""Simulator benchmark: world build time, session setup, scan rate (streamed), dataset write time
and bytes. Writes docs/bench/sim.md.

    python -m bench.sim            # full (writes the small dataset once, ~1 min)
    python -m bench.sim --quick    # fewer repetitions, no dataset write
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "sim.md"


def _median_time(fn, reps: int) -> float:
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _du(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    from bench.__main__ import machine

    from blockloc.sim.presets import get_preset
    from blockloc.sim.stream import SimSequence, cached_world, session_trajectory
    from blockloc.sim.world import build_world

    reps = 2 if args.quick else 5
    rows = []
    stream_rows = []
    for name in ("small", "campus", "city"):
        p = get_preset(name)
        t_world = _median_time(lambda: build_world(p, 1), 1 if name == "city" else reps)
        w = build_world(p, 1)

        def setup():
            session_trajectory.cache_clear()
            cached_world.cache_clear()
            seq = SimSequence(p, next(s for s in p.sessions if not p.is_mapping(s)), 1)
            seq.scene  # noqa: B018  (builds the RaycastingScene; city: on the first cast)
            return seq

        setup()  # warm imports (open3d)
        t_setup = _median_time(setup, max(2, reps // 2))
        lengths = []
        for s in p.sessions:
            tr = session_trajectory(p, 1, s)
            lengths.append(f"{s} {tr.path_length() / 1000:.2f} km / {tr.duration / 60:.1f} min")
        rows.append((name, f"{p.size_m[0]:.0f} x {p.size_m[1]:.0f}", w.num_triangles(), len(w.movables),
                     t_world, t_setup, "; ".join(lengths)))
        loc = next(s for s in p.sessions if not p.is_mapping(s))
        for az in sorted({p.lidar.azimuth_steps, 200}):
            seq = SimSequence(get_preset(name, azimuth_steps=az), loc, 1)
            n = 60 if args.quick else 200
            start = 100
            seq.frame(start)
            per, npts = [], []
            for i in range(start, start + n):
                t0 = time.perf_counter()
                f = seq.frame(i)
                per.append(time.perf_counter() - t0)
                npts.append(len(f))
            med = statistics.median(per)
            stream_rows.append((name, az, n, med * 1e3, 1.0 / med, statistics.median(npts)))

    write_rows = []
    if not args.quick:
        tmp = Path(tempfile.mkdtemp(prefix="bench-sim-"))
        try:
            cmd = ["blockloc", "sim", "--preset", "small", "--seed", "1", "--out", str(tmp / "sim_out")]
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            wall = time.perf_counter() - t0
            sizes = {d.name: _du(d) for d in sorted((tmp / "sim_out").iterdir()) if d.is_dir()}
            frames = {d: len(list((tmp / "sim_out" / d / "velodyne_sync").iterdir())) for d in sizes}
            write_rows.append((" ".join(cmd[:-1] + ["sim_out"]), wall, sizes, frames))
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    lines = ["## Simulator", "",
             f"Machine: {machine()}. Command: `python -m bench.sim{' --quick' if args.quick else ''}`, "
             f"run {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Seed 1.", "",
             f"World build (median of {reps}) and session setup (trajectory + open3d scene, "
             "median) per preset:", "",
             "| preset | size (m) | triangles | movables | world build (s) | session setup (s) | routes |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r[0]} | {r[1]} | {r[2]:,} | {r[3]:,} | {r[4]:.2f} | {r[5]:.2f} | {r[6]} |")
    lines += ["", "Streaming (`open_sim_sequence`, one scan ray-cast per call, moving actors "
              "included, median over consecutive frames of the `loc` session):", "",
              "| preset | azimuth steps | frames | ms / scan | scans / s | points / scan |",
              "|---|---|---|---|---|---|"]
    for r in stream_rows:
        lines.append(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.1f} | {r[4]:.1f} | {r[5]:,.0f} |")
    if write_rows:
        cmd, wall, sizes, frames = write_rows[0]
        total = sum(sizes.values())
        lines += ["", f"Writing the `small` dataset (`{cmd}`, one run, NCLT layout with "
                  f"velodyne_hits.bin): {wall:.1f} s wall, {total / 1e6:.0f} MB in total ("
                  + ", ".join(f"{k}: {frames[k]} scans, {v / 1e6:.0f} MB" for k, v in sizes.items()) + ")."]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    tmp_out = OUT.with_suffix(".md.tmp")
    tmp_out.write_text("\n".join(lines) + "\n")
    tmp_out.replace(OUT)
    print("\n".join(lines))
    return OUT


if __name__ == "__main__":
    main(sys.argv[1:])
