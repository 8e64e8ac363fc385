"""Simulator benchmark: world build time, session setup, scan rate (streamed), dataset write time
and bytes. Writes docs/bench/sim.md.

    python -m bench.sim            # full (writes the small dataset once, ~1 min)
    python -m bench.sim --quick    # fewer repetitions, no dataset write

Speed probes (print only; docs/bench/sim.md quotes them with their commands), each optionally run
on another tree (``--tree /work/main``: that tree on PYTHONPATH, for a paired before / after):

    python -m bench.sim --scan-ms campus --frames 40   # median ms a scan (wall, CPU), default sensor
    python -m bench.sim --write-s small --runs 2       # `blockloc sim --preset small` wall time
    python -m bench.sim --write-s small --max-frames 300   # its first 300 frames a session (~2 min)

--write-s writes under the temp directory (``TMPDIR=/big/disk``: the small preset is 2.7 GB).
"""

from __future__ import annotations

import argparse
import resource
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


# frames 100 .. 100 + n of a session's `loc` drive, timed one by one after a first (the scene)
_SCAN_MS = """
import statistics, sys, time
from blockloc.sim.stream import open_sim_sequence
preset, n = sys.argv[1], int(sys.argv[2])
s = open_sim_sequence(preset, "loc", 1)
s.frame(100)
per, cpu = [], []
for i in range(101, 101 + n):
    t0, c0 = time.perf_counter(), time.process_time()
    s.frame(i)
    per.append(time.perf_counter() - t0)
    cpu.append(time.process_time() - c0)
print(f"{statistics.median(per) * 1e3:.1f} ms median wall, {statistics.median(cpu) * 1e3:.1f} ms CPU")
"""


# `blockloc sim`'s writing of the first n frames of each session (generate_dataset's max_frames;
# its workers as for the whole preset when the frames are >= MIN_FRAMES_FOR_WORKERS in all)
_WRITE_FIRST = """
import sys
from blockloc.sim.writer import generate_dataset
generate_dataset(sys.argv[1], 1, sys.argv[2], max_frames=int(sys.argv[3]))
"""


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _env(tree: Path | None) -> dict:
    """The environment of a probe's command: ``tree`` (default this one) first on PYTHONPATH, so
    that the `blockloc` console script (installed editable from elsewhere) runs that code."""
    import os

    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree or ROOT)
    return env


def speed_probe(args) -> None:
    """--scan-ms / --write-s: print each run's figure with the machine's load beside it."""
    tree = Path(args.tree).resolve() if args.tree else None
    where = f"tree {tree}" if tree else f"tree {ROOT}"
    if args.scan_ms:
        for _ in range(args.runs):
            load = _uptime()
            out = subprocess.run([sys.executable, "-c", _SCAN_MS, args.scan_ms, str(args.frames)], check=True,
                                 capture_output=True, text=True, env=_env(tree), cwd=tree or ROOT).stdout
            print(f"scan-ms {args.scan_ms} ({where}, seed 1, loc frames 101-{100 + args.frames}): "
                  f"{out.strip()} | before: {load} | after: {_uptime()}", flush=True)
    if args.write_s:
        for _ in range(args.runs):
            tmp = Path(tempfile.mkdtemp(prefix="bench-sim-"))
            try:
                load = _uptime()
                t0 = time.perf_counter()
                r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                if args.max_frames:  # the first frames of each session, written as the command does
                    cmd = [sys.executable, "-c", _WRITE_FIRST, args.write_s, str(tmp / "sim_out"),
                           str(args.max_frames)]
                else:
                    cmd = ["blockloc", "sim", "--preset", args.write_s, "--seed", "1", "--out", str(tmp / "sim_out")]
                subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               env=_env(tree), cwd=tree or ROOT)
                wall = time.perf_counter() - t0
                r1 = resource.getrusage(resource.RUSAGE_CHILDREN)  # the command and its workers
                cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
                scans = sum(1 for _ in (tmp / "sim_out").glob("*/velodyne_sync/*.bin"))
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            first = f", first {args.max_frames} frames a session" if args.max_frames else ""
            print(f"write-s {args.write_s} ({where}, seed 1{first}): {scans} scans, {wall:.1f} s wall, "
                  f"{cpu:.1f} s CPU ({1e3 * cpu / max(scans, 1):.1f} ms a scan, all in) | "
                  f"before: {load} | after: {_uptime()}", flush=True)


def main(argv: list[str] | None = None) -> Path | None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scan-ms", metavar="PRESET", help="probe: median ms a scan of PRESET's loc drive")
    ap.add_argument("--write-s", metavar="PRESET", help="probe: wall s of `blockloc sim --preset PRESET`")
    ap.add_argument("--frames", type=int, default=40, help="--scan-ms: frames timed")
    ap.add_argument("--max-frames", type=int, default=0,
                    help="--write-s: only the first N frames of each session (a quick re-run)")
    ap.add_argument("--runs", type=int, default=1, help="probe runs (each printed)")
    ap.add_argument("--tree", help="probe another source tree (its path on PYTHONPATH), e.g. /work/main")
    args = ap.parse_args(argv)
    if args.scan_ms or args.write_s:
        speed_probe(args)
        return None
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
