"""Maps from a server: 20 simulated robots on loopback fetching their regions from one server.

    python -m bench.server [--quick]

One ``blockloc map serve`` process (subprocess, so the server has its own interpreter) serves a
grid store of 12 x 12 tiles of 20 m (25,000 points each, ~400 kB). 20 robot threads in this
process each open the store at the server's URL through ``RemoteMapFiles`` with their own
on-disk cache (bounded at 16 MB, so the LRU evicts), random-walk over the map and, on entering a
new tile, load the 3 x 3 tiles around it that they do not hold in memory (the provider's pattern:
tiles that left the window and come back are disk-cache hits).

Two modes, each run ``RUNS`` times with fresh caches; the fragment quotes medians over the runs:

* saturated: robots step without pause (a stress test: throughput is the server's capacity,
  latencies are under full load);
* paced: each robot moves 2 m per 0.1 s tick (20 m/s, a tile change about every second).

"tile latency" is the time of one ``MapStore.load`` (fetch or cache read, sha256 check, PCD
decode). Every loop is bounded in steps and in time. Writes ``docs/bench/server.md``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from blockloc.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
N_ROBOTS = 20
GRID = 12            # tiles per side
TILE_M = 20.0
POINTS = 25_000      # per tile
CACHE_MB = 16
RUNS = 3
SATURATED_STEPS = 400
PACED_S = 15.0
TICK_S = 0.1
STEP_M = 2.0
RUN_LIMIT_S = 120.0  # hard bound of one run


def build_map(out: Path) -> None:
    from blockloc.maps.store import MapWriter

    rng = np.random.default_rng(0)
    with MapWriter(out, "grid", params={"tile_size_m": TILE_M}) as w:
        for i in range(GRID):
            for j in range(GRID):
                cx, cy = (i + 0.5) * TILE_M, (j + 0.5) * TILE_M
                pts = np.c_[rng.uniform(-TILE_M / 2, TILE_M / 2, (POINTS, 2)) + [cx, cy],
                            rng.uniform(0, 5, POINTS)].astype(np.float32)
                w.add(f"{cx:.1f}_{cy:.1f}", pts, rng.uniform(0, 100, POINTS).astype(np.float32))
        w.commit()


def start_server(root: Path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "blockloc.cli", "map", "serve", str(root),
                             "--port", "0"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    line = proc.stderr.readline().strip()
    if not line.startswith("serving "):
        proc.kill()
        raise RuntimeError(f"map serve did not start: {line!r}")
    return proc, line.split()[1].rstrip("/")


def stop_server(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)


class Robot(threading.Thread):
    def __init__(self, k: int, url: str, cache_dir: Path, paced: bool, start: threading.Barrier,
                 deadline: list):
        super().__init__(daemon=True)
        self.k, self.url, self.cache_dir, self.paced = k, url, cache_dir, paced
        self.start_barrier, self.deadline = start, deadline
        self.miss_s: list[float] = []
        self.steady_miss_s: list[float] = []  # fetches after the first window (no start-up burst)
        self.hit_s: list[float] = []
        self.failures = 0
        self.fetched_bytes = 0
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self._run()
        except BaseException as exc:  # reported by the main thread
            self.error = exc

    def _run(self) -> None:
        from blockloc.errors import MapError
        from blockloc.maps.remote import RemoteMapFiles
        from blockloc.maps.store import open_manifest

        rng = np.random.default_rng(100 + self.k)
        files = RemoteMapFiles(self.url, cache_dir=self.cache_dir, cache_bytes=CACHE_MB * 2**20,
                               seed=self.k)
        store = open_manifest(files)
        ids = set(store.ids)
        size = GRID * TILE_M
        pos = rng.uniform(0.1 * size, 0.9 * size, 2)
        heading = rng.uniform(-np.pi, np.pi)
        held: set[str] = set()
        cell = None
        self.start_barrier.wait(60)
        next_tick = time.perf_counter()
        steps = SATURATED_STEPS if not self.paced else int(PACED_S / TICK_S)
        for _ in range(steps):
            if time.perf_counter() > self.deadline[0]:
                break
            heading += rng.normal(0, 0.3)
            step = pos + STEP_M * np.array([np.cos(heading), np.sin(heading)])
            for a in range(2):  # reflect at the map's edges
                if not 0 <= step[a] < size:
                    heading = np.pi - heading if a == 0 else -heading
                    step[a] = np.clip(step[a], 0, size - 1e-6)
            pos = step
            c = tuple((pos // TILE_M).astype(int))
            if c != cell:
                cell = c
                window = {f"{(c[0] + di + 0.5) * TILE_M:.1f}_{(c[1] + dj + 0.5) * TILE_M:.1f}"
                          for di in (-1, 0, 1) for dj in (-1, 0, 1)} & ids
                for eid in sorted(window - held):
                    before = files.stats.cache_hits
                    t0 = time.perf_counter()
                    try:
                        store.load(eid)
                    except MapError:
                        self.failures += 1
                        continue
                    dt = time.perf_counter() - t0
                    if files.stats.cache_hits > before:
                        self.hit_s.append(dt)
                    else:
                        self.miss_s.append(dt)
                        if held:
                            self.steady_miss_s.append(dt)
                held = window
            if self.paced:
                next_tick += TICK_S
                time.sleep(max(0.0, next_tick - time.perf_counter()))
        self.fetched_bytes = files.stats.fetched_bytes


def run_once(url: str, work: Path, paced: bool) -> dict:
    caches = work / "caches"
    shutil.rmtree(caches, ignore_errors=True)
    barrier = threading.Barrier(N_ROBOTS + 1)
    deadline = [float("inf")]
    robots = [Robot(k, url, caches / f"robot{k:02d}", paced, barrier, deadline) for k in range(N_ROBOTS)]
    for r in robots:
        r.start()
    barrier.wait(120)  # every robot has opened the map
    t0 = time.perf_counter()
    deadline[0] = t0 + RUN_LIMIT_S
    for r in robots:
        r.join(RUN_LIMIT_S + 30)
    wall = time.perf_counter() - t0
    errors = [r.error for r in robots if r.error is not None]
    if errors:
        raise RuntimeError(f"{len(errors)} robots failed: {errors[0]!r}")
    miss = np.concatenate([r.miss_s for r in robots]) if robots else np.zeros(0)
    hit = np.concatenate([r.hit_s for r in robots]) if robots else np.zeros(0)
    steady = np.concatenate([r.steady_miss_s for r in robots]) if robots else np.zeros(0)
    loads = len(miss) + len(hit)
    fetched = sum(r.fetched_bytes for r in robots)
    return {
        "wall_s": wall,
        "tile_loads": loads,
        "fetched_tiles": len(miss),
        "fetched_mb": fetched / 2**20,
        "throughput_mb_s": fetched / 2**20 / wall,
        "fetches_per_s": len(miss) / wall,
        "miss_p50_ms": float(np.percentile(miss, 50) * 1e3) if len(miss) else float("nan"),
        "miss_p99_ms": float(np.percentile(miss, 99) * 1e3) if len(miss) else float("nan"),
        "steady_p99_ms": float(np.percentile(steady, 99) * 1e3) if len(steady) else float("nan"),
        "all_p99_ms": float(np.percentile(np.r_[miss, hit], 99) * 1e3) if loads else float("nan"),
        "hit_p50_ms": float(np.percentile(hit, 50) * 1e3) if len(hit) else float("nan"),
        "hit_rate": len(hit) / loads if loads else 0.0,
        "failures": sum(r.failures for r in robots),
    }


ROWS = [
    ("wall time of the run, s", "wall_s", "{:.2f}"),
    ("tile loads (all robots)", "tile_loads", "{:.0f}"),
    ("tiles fetched over HTTP", "fetched_tiles", "{:.0f}"),
    ("MB fetched", "fetched_mb", "{:.1f}"),
    ("throughput, MB/s", "throughput_mb_s", "{:.1f}"),
    ("throughput, tiles/s", "fetches_per_s", "{:.1f}"),
    ("tile latency, fetched, p50, ms", "miss_p50_ms", "{:.1f}"),
    ("tile latency, fetched, p99, ms", "miss_p99_ms", "{:.1f}"),
    ("tile latency, fetched after the first window, p99, ms", "steady_p99_ms", "{:.1f}"),
    ("tile latency, all loads, p99, ms", "all_p99_ms", "{:.1f}"),
    ("tile latency, disk-cache hit, p50, ms", "hit_p50_ms", "{:.2f}"),
    ("disk-cache hit rate", "hit_rate", "{:.2f}"),
    ("failed loads", "failures", "{:.0f}"),
]


def main(argv: list[str] | None = None) -> None:
    global RUNS, PACED_S, SATURATED_STEPS
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 run per mode, shorter walks (smoke)")
    args = ap.parse_args(argv)
    if args.quick:
        RUNS, PACED_S, SATURATED_STEPS = 1, 3.0, 40
    from bench.__main__ import machine

    results: dict[str, list[dict]] = {"saturated": [], "paced": []}
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-server-") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        build_map(work / "campus")
        build_s = time.perf_counter() - t0
        map_mb = sum(p.stat().st_size for p in (work / "campus").iterdir()) / 2**20
        proc, url = start_server(work / "campus")
        try:
            for mode in ("saturated", "paced"):
                for _ in range(RUNS):
                    r = run_once(url, work, paced=(mode == "paced"))
                    results[mode].append(r)
                    print(mode, {k: round(v, 3) for k, v in r.items()}, file=sys.stderr)
        finally:
            stop_server(proc)

    def med(mode: str, key: str) -> float:
        return float(np.median([r[key] for r in results[mode]]))

    cmd = "python -m bench.server" + (" --quick" if args.quick else "")
    lines = [
        "## Maps from a server (`blockloc map serve`, 20 robots)",
        "",
        f"Machine: {machine()}. Command: `{cmd}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}).",
        f"One `blockloc map serve` process on 127.0.0.1; a grid store of {GRID}x{GRID} tiles of "
        f"{TILE_M:.0f} m, {POINTS:,} points each ({map_mb:.1f} MB in all, built in {build_s:.1f} s). "
        f"{N_ROBOTS} robot threads in one client process, each with its own `RemoteMapFiles` and a "
        f"{CACHE_MB} MB on-disk cache, random-walk and load the 3x3 tiles around them on each tile "
        "change. Saturated: no pause between steps "
        f"({SATURATED_STEPS} steps of {STEP_M:.0f} m); paced: {STEP_M:.0f} m per {TICK_S} s tick "
        f"for {PACED_S:.0f} s. Medians over {RUNS} runs with fresh caches. Tile latency = one "
        "`MapStore.load` (fetch or cache read + sha256 + PCD decode). Server and client share the "
        f"2 cores; 1-min load average {load_before:.1f} before the runs, {os.getloadavg()[0]:.1f} "
        "after (other work on the machine inflates the saturated numbers' spread).",
        "",
        "| measure | saturated | paced |",
        "|---|---:|---:|",
    ]
    for label, key, fmt in ROWS:
        lines.append(f"| {label} | {fmt.format(med('saturated', key))} | {fmt.format(med('paced', key))} |")
    out = ROOT / "docs" / "bench" / "server.md"
    atomic_write_text(out, "\n".join(lines) + "\n")
    print(out.read_text())


if __name__ == "__main__":
    main()
