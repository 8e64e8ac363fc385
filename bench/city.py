"""City-scale map builds on Dask (issue 19), then tracking the city's localization session
through the built map served over HTTP.

    python -m bench city                                   # sim:city: every mapping session, every run
    python -m bench.city --preset campus --max-frames 8000 --track-frames 1500   # development figures
    python -m bench.city --runs serial,local:2 --kinds block,grid
    python -m bench.city --sessions map1,map2 --max-frames 500 --track-frames 200   # ~10 min

Runs (``--runs``), each map build in its own client process so that its peak RSS is the client's:

- ``serial``: the build plan in the client process (no Dask);
- ``local:1``, ``local:2``: ``--cluster local:N`` (a LocalCluster of N single-threaded workers);
- ``cluster:2``: a ``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1, started
  here and stopped by PID; the client connects to the scheduler's address;
- ``kill:2``: as ``cluster:2``, with one worker SIGKILLed by its PID at ``--kill-at`` of the
  ``cluster:2`` build's wall time; the build must complete with the serial checksums.

The drives are the simulator's, ray-cast scan by scan as the build reads them (never on disk). With
``--recorded DIR`` they are first written once in NCLT layout under ``DIR`` (the first
``--max-frames`` of each session, velodyne_sync + velodyne_hits + slam poses, as ``blockloc sim``
writes them) and every build reads those files, as a user's build reads a recording: the build
then does no ray casting, whose threads give the serial build part of the second core.

Every run builds the same map from the preset's mapping sessions (``map``, or ``map1`` ..
``mapN``); the manifests are compared byte for byte (``SOURCE_DATE_EPOCH`` fixes their stamp).
Figures: wall time of the build (cluster start-up apart), CPU utilization (client + workers CPU
time over wall time x cores), peak RSS of the client and of each worker (VmHWM), bytes written
(entries + scratch), and the machine's load average. From the serial run's per-task costs, a
projection of a 100 km^2, 1000 km map on 8, 32 and 128 workers. Then ``blockloc map serve`` serves
the serial map and the preset's ``loc`` session is tracked through it (block backend, its own
process, ``bench._track``). Writes docs/bench/city.md (+ .json).

Without a ``city`` preset in ``blockloc.sim.presets`` (``--preset city``, the default) it stops
with one line.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "city.md"
RUNS = ("serial", "local:1", "local:2", "cluster:2", "kill:2")
EPOCH = "1700000000"  # SOURCE_DATE_EPOCH of every build: identical manifests
TARGET = {"area_km2": 100.0, "path_km": 1000.0, "workers": (8, 32, 128)}


def preset_sessions(preset: str) -> tuple[list[str], str | None]:
    """(mapping sessions, localization session) of a simulator preset; SystemExit (one line)
    when blockloc.sim.presets has no such preset."""
    from blockloc.sim import presets

    names = list(getattr(presets, "PRESETS", {}))
    if preset not in names:
        raise SystemExit(f"bench.city: no '{preset}' simulated preset in blockloc.sim.presets "
                         f"(it has {', '.join(names)}); run with --preset campus for development figures")
    sessions = presets.get_preset(preset).sessions
    maps = [s for s in sessions if s.startswith("map")] or [sessions[0]]
    loc = "loc" if "loc" in sessions else next((s for s in sessions if s not in maps), None)
    return maps, loc


# --------------------------------------------------------------------------- one build, in a child


def warm_raster_tiles(preset: str, seed: int, sessions: list[str], max_frames: int | None,
                      margin_m: float = 110.0) -> tuple[int, float]:
    """Rasterize (once, into the disk cache every build process reads) the simulated world's
    ground tiles around the drives' frames, so that no timed build pays for what only a
    simulated input needs, whichever run comes first (blockloc.cache.DiskTiles). Returns
    (tiles, seconds)."""
    import numpy as np

    from blockloc.sim.stream import open_sim_sequence

    t0 = time.perf_counter()
    lo, hi, world = np.full(2, np.inf), np.full(2, -np.inf), None
    for s in sessions:
        seq = open_sim_sequence(preset, s, seed)
        world = seq.world
        stamps = seq.frame_stamps()[:max_frames]
        xy = seq.trajectory.T_world_flu(stamps - stamps[0])[:, :2, 3]
        lo, hi = np.minimum(lo, xy.min(axis=0)), np.maximum(hi, xy.max(axis=0))
    tile = 128.0  # blockloc.sim.world's raster tile
    ia = np.arange(np.floor((lo[0] - margin_m) / tile), np.floor((hi[0] + margin_m) / tile) + 1)
    ja = np.arange(np.floor((lo[1] - margin_m) / tile), np.floor((hi[1] + margin_m) / tile) + 1)
    for a in ia:
        for b in ja:
            world.ground_material(np.array([(a + 0.5) * tile]), np.array([(b + 0.5) * tile]))
    return len(ia) * len(ja), time.perf_counter() - t0


def record_drives(preset: str, seed: int, sessions: list[str], max_frames: int | None, root: Path) -> Path:
    """The drives written in NCLT layout under ``root/<preset>-<seed>-<frames>/<session>`` (each
    session written only if missing, by the simulator's own writer). Returns that directory."""
    from blockloc.sim.writer import generate_dataset

    where = root / f"{preset}-{seed}-{max_frames or 'all'}"
    for s in sessions:
        if (where / s / "velodyne_sync").is_dir():
            continue
        t0 = time.perf_counter()
        tmp = where / f".{s}.recording"
        generate_dataset(preset, seed, tmp, "nclt", sessions=(s,), max_frames=max_frames)
        (tmp / s).rename(where / s)
        shutil.rmtree(tmp)
        print(f"== recorded {preset}/{s} to {where / s} in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return where


def child_build(spec: dict) -> dict:
    """Build the map described by ``spec`` in this process (the client); its measurements."""
    import functools

    import psutil

    from blockloc.resources import peak_rss_mb
    from blockloc.maps.build_plan import Drive, build_map_from_drives
    from blockloc.maps.distributed import open_executor
    from blockloc.sim.stream import open_sim_sequence

    os.environ["SOURCE_DATE_EPOCH"] = EPOCH
    if spec.get("recorded"):  # NCLT-layout sessions on disk, opened as `map build --seq DIR` does
        from blockloc.app.runs import parse_drive

        drives = [parse_drive(str(Path(spec["recorded"]) / s), max_frames=spec.get("max_frames"))
                  for s in spec["sessions"]]
    else:
        drives = [Drive(f"sim:{spec['preset']}/{s}@{spec['seed']}",
                        functools.partial(open_sim_sequence, spec["preset"], s, spec["seed"]),
                        f"sim-{spec['preset']}-{s}-{spec['seed']}", 0, spec.get("max_frames"))
                  for s in spec["sessions"]]
    me = psutil.Process()
    t_start = time.perf_counter()
    with open_executor(spec.get("cluster")) as ex:
        startup_s = time.perf_counter() - t_start
        workers0 = ex.worker_info() if hasattr(ex, "worker_info") else {}
        cpu0 = sum(me.cpu_times()[:2])
        stats: dict = {}
        t0 = time.perf_counter()
        store = build_map_from_drives(drives, spec["kind"], spec["out"], executor=ex, stats=stats,
                                      overwrite=True, **spec["sizes"])
        wall = time.perf_counter() - t0
        client_cpu = sum(me.cpu_times()[:2]) - cpu0
        workers1 = ex.worker_info() if hasattr(ex, "worker_info") else {}
        overhead = _task_overhead(ex) if hasattr(ex, "client") else None
    workers = [{"pid": w["pid"], "peak_rss_mb": w["peak_rss_mb"],
                "cpu_s": w["cpu_s"] - workers0.get(addr, {}).get("cpu_s", 0.0)}
               for addr, w in sorted(workers1.items())]
    manifest = Path(spec["out"]) / "manifest.json"
    return {"wall_s": wall, "startup_s": startup_s, "client_cpu_s": client_cpu,
            "client_peak_rss_mb": peak_rss_mb(), "workers": workers, "stats": stats,
            "entries": len(store), "points": store.total_points, "bytes": store.total_bytes,
            "checksums": [[e.id, e.sha256] for e in store.entries],
            "manifest_sha256": _sha256(manifest.read_bytes()),
            "bounds": [list(map(float, b)) for b in store.bounds()],
            "events": store.params.get("events"), "task_overhead_s": overhead}


def _noop(i):
    return i


def _task_overhead(ex, n: int = 2000) -> float:
    """Seconds per task of the scheduler's round trip on this cluster: ``n`` no-op tasks timed end
    to end over ``n`` (one scheduler serves every worker: this cost does not shrink with W)."""
    client = ex.client
    t0 = time.perf_counter()
    client.gather(client.map(_noop, range(n), pure=False))
    return (time.perf_counter() - t0) / n


def _sha256(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data).hexdigest()


def run_build(spec: dict, work: Path, kill_after_s: float | None = None, kill_pid: int | None = None) -> dict:
    """``child_build`` in a fresh process (``python -m bench.city --child-build``); optionally
    SIGKILL ``kill_pid`` after ``kill_after_s`` seconds. Adds load averages and the kill."""
    spec_path = work / f"spec-{spec['name'].replace(':', '_')}-{spec['kind']}.json"
    out_path = spec_path.with_suffix(".out.json")
    spec_path.write_text(json.dumps(spec))
    out_path.unlink(missing_ok=True)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "bench.city", "--child-build", str(spec_path), str(out_path)],
                            cwd=ROOT)
    killed_at = None
    if kill_after_s is not None and kill_pid is not None:
        try:
            proc.wait(kill_after_s)
        except subprocess.TimeoutExpired:
            os.kill(kill_pid, signal.SIGKILL)
            killed_at = time.perf_counter() - t0
            print(f"  SIGKILL worker pid {kill_pid} at {killed_at:.0f} s", file=sys.stderr, flush=True)
    rc = proc.wait()
    res = json.loads(out_path.read_text()) if rc == 0 and out_path.exists() else {"error": f"exit {rc}"}
    res.update(name=spec["name"], kind=spec["kind"], load=[load0, os.getloadavg()[0]], killed_at_s=killed_at,
               total_s=time.perf_counter() - t0)
    return res


# --------------------------------------------------------------------------- projection


def projection(serial: dict, local2: dict | None, kind: str) -> dict:
    """Build time of a 100 km^2, 1000 km map on 8 / 32 / 128 workers from measured per-task costs.

    Per task kind the serial run gives the mean CPU time (what the task costs on a core of its
    own; wall time on a shared machine is not that); counts scale with the driven length
    (candidates, merges, chunks) or with the mapped area (blocks and tiles written; a tile's cost
    with the drives' length per area, its revisits). T(W) = work / W + tasks x overhead +
    merges' cost (an upper bound of the decisions' wait for merges), where overhead is the
    per-task scheduling cost measured on local:2 (no-op tasks, :func:`_task_overhead`)."""
    st = serial["stats"]
    tasks = st["tasks"]
    km = st["path_m"] / 1000.0
    (x0, y0, _), (x1, y1, _) = serial["bounds"]
    area = max((x1 - x0) * (y1 - y0) / 1e6, 1e-6)
    length_ratio = TARGET["path_km"] / max(km, 1e-9)
    area_ratio = TARGET["area_km2"] / area
    revisit_ratio = (TARGET["path_km"] / TARGET["area_km2"]) / (km / area)
    scale = {"plan": 1.0, "run": length_ratio, "candidate": length_ratio, "merge": length_ratio,
             "chunk": length_ratio,
             "write": area_ratio, "tile": area_ratio, "tiles": area_ratio}
    cost_scale = {"tile": revisit_ratio, "tiles": revisit_ratio}
    rows, work, n_tasks = {}, 0.0, 0.0
    for k, r in tasks.items():
        mean = r.get("cpu_s", r["seconds"]) / max(r["count"], 1)  # CPU: a dedicated core's cost
        count = r["count"] * scale.get(k, length_ratio)
        cost = mean * cost_scale.get(k, 1.0)
        rows[k] = {"measured_count": r["count"], "mean_s": mean, "count": count, "cost_s": cost}
        work += count * cost
        n_tasks += count
    overhead = (local2 or {}).get("task_overhead_s") or 0.0
    seq = rows.get("merge", {"count": 0, "cost_s": 0})
    chain = seq["count"] * seq["cost_s"]
    times = {w: work / w + n_tasks * overhead + chain for w in TARGET["workers"]}
    return {"kind": kind, "measured_km": km, "measured_area_km2": area, "rows": rows, "work_s": work,
            "tasks": n_tasks, "overhead_s": overhead, "merge_chain_s": chain, "times_s": times}


def cpu_model(stats: dict, workers: int, plan_cpu_s: float | None = None) -> float:
    """Wall time the build would take on an idle machine with ``workers`` single-threaded
    workers, from the measured CPU time of each task: the drives are planned first (each worker
    opens them meanwhile: ``plan_cpu_s``, default the planning tasks' CPU time), then the tasks
    that read scans (block runs, grid chunks) are run in submission order, each on the worker that is
    free first, then the small tasks (merges, writes, tiles) share the workers evenly."""
    import heapq

    tasks = stats["tasks"]
    plan = sum(tasks.get("plan", {}).get("cpu_each", [])) if plan_cpu_s is None else plan_cpu_s
    free = [plan] * workers
    for k in ("run", "chunk"):  # the tasks that read scans (a candidate only adds its runs up)
        for c in tasks.get(k, {}).get("cpu_each", []):
            heapq.heappush(free, heapq.heappop(free) + c)
    rest = sum(r.get("cpu_s", 0.0) for k, r in tasks.items() if k not in ("plan", "run", "chunk"))
    return max(free) + rest / workers


def worker_setup_s(run: dict) -> float:
    """CPU seconds a worker of ``run`` spent outside the build's timed tasks (opening drives,
    Dask's own work), per worker: whole-process CPU minus the tasks' CPU, shared evenly."""
    tasks_cpu = sum(r.get("cpu_s", 0.0) for r in run["stats"]["tasks"].values())
    return max(0.0, (sum(w["cpu_s"] for w in run["workers"]) - tasks_cpu) / len(run["workers"]))


def process_cpu_bound(run: dict, cores: int) -> float:
    """Shortest wall time ``run``'s measured process CPU times allow on ``cores`` idle cores:
    the busiest worker's CPU, or all processes' CPU (client included) over the cores."""
    cpu = [w["cpu_s"] for w in run["workers"]]
    return max(max(cpu), (sum(cpu) + run["client_cpu_s"]) / cores)


# --------------------------------------------------------------------------- tracking via map serve


def track_served(map_dir: Path, seq_name: str, work: Path, max_frames: int | None) -> dict:
    """``blockloc map serve`` the map, track ``seq_name`` through its URL (block backend, one
    process), stop the server by PID. Metrics of ``bench._track.summarize``."""
    from bench._track import run_in_child, summarize
    from blockloc.app.catalog import open_sequence

    srv = subprocess.Popen([sys.executable, "-m", "blockloc.cli", "map", "serve", str(map_dir), "--port", "0"],
                           cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        url = None
        deadline = time.monotonic() + 60
        while url is None and time.monotonic() < deadline:
            line = srv.stderr.readline()
            if not line:
                break
            m = re.search(r"serving (http://\S+?)/?$", line.strip())
            url = m.group(1) if m else None
        if url is None:
            raise SystemExit("bench.city: blockloc map serve did not report its address")
        res = run_in_child(seq_name, url, "block", work / "track.json", max_frames=max_frames)
    finally:
        srv.terminate()
        try:
            srv.wait(10)
        except subprocess.TimeoutExpired:
            srv.kill()
    gt = open_sequence(seq_name).ground_truth()
    m = summarize(res.pop("arrays"), gt)
    m.update({k: res[k] for k in ("peak_rss_mb", "setup_s", "track_s")})
    m["url"] = url
    return {k: v for k, v in m.items() if not k.startswith("_")}


# --------------------------------------------------------------------------- report


def reference_run(runs: dict) -> dict | None:
    """The run a kind's figures are read from: the serial build, else the first run that
    completed (its entries equal the serial build's byte for byte); None if none completed."""
    ok = [r for r in runs.values() if "error" not in r]
    return runs["serial"] if "serial" in runs and "error" not in runs["serial"] else (ok[0] if ok else None)


def _f(v, fmt="{:.1f}"):
    return "-" if v is None else fmt.format(v)


def report(args, cmd: str, results: dict, projections: dict, tracking: dict | None, started: str) -> str:
    from bench.__main__ import machine

    cores = os.cpu_count() or 1
    lines = [f"## City-scale map builds on Dask ({args.preset})", "",
             f"Command: `{cmd}` ({started}). Machine: {machine()}. Development figures when the preset is "
             "not `city` or only part of its drives is built (`--sessions`, `--max-frames`: few tasks"
             + (")" if args.recorded else
                ", and every worker still opens the simulated drives and builds their scene windows itself)")
             + "; the machine is shared (load averages below), so times are upper bounds and speed-ups are what "
             "the load allowed. "
             + ("The drives were recorded to disk once before the timed builds (NCLT layout, `record_drives`); "
                "every build reads those files." if args.recorded else
                "Before the timed builds the simulated world's ground raster tiles around the drives are "
                "computed once into the disk cache that every build process reads (`warm_raster_tiles`), so no run "
                "pays for them because it came first."), ""]
    for kind, runs in results.items():
        ref = reference_run(runs)
        if ref is None:
            continue
        serial = runs.get("serial") if ref is runs.get("serial") else None
        st = ref["stats"]
        raw = sum(r["raw_points"] for r in st["tasks"].values())
        lines += [f"### {kind} map", "",
                  f"Drives: {', '.join(args.sessions)} (seed {args.seed}"
                  + (f", first {args.max_frames} frames each" if args.max_frames else "")
                  + (f"; read from their NCLT-layout recordings in {args.recorded}, no ray casting in the build"
                     if args.recorded else "; ray-cast scan by scan as the build reads them")
                  + f"): {st['keyframes']:,} keyframes over {st['path_m'] / 1000:.2f} km, {raw:,} raw points read; "
                  f"the map holds {ref['entries']:,} {'blocks' if kind == 'block' else 'tiles'}, "
                  f"{ref['points']:,} points, {ref['bytes'] / 2**20:.1f} MiB."
                  + ("" if serial else " No serial build in this run: the 'vs serial' and 'identical' "
                     "columns are empty, and the model and projection below use this run's per-task CPU times."), "",
                  "| run | wall [s] | vs serial | CPU util [%] | client peak RSS [MB] | worker peak RSS [MB] | "
                  "bytes written [MiB] | tasks | identical | load before/after |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for name in RUNS:
            r = runs.get(name)
            if r is None:
                continue
            if "error" in r:
                lines.append(f"| {name} | failed ({r['error']}) | | | | | | | | |")
                continue
            cpu = r["client_cpu_s"] + sum(w["cpu_s"] for w in r["workers"])
            util = 100.0 * cpu / (r["wall_s"] * cores)
            written = sum(t["bytes"] for t in r["stats"]["tasks"].values())
            same = serial and (r["checksums"] == serial["checksums"]
                               and r["manifest_sha256"] == serial["manifest_sha256"])
            wrss = ", ".join(f"{w['peak_rss_mb']:.0f}" for w in r["workers"]) or "-"
            n = sum(t["count"] for t in r["stats"]["tasks"].values())
            note = f" (worker killed at {r['killed_at_s']:.0f} s)" if r.get("killed_at_s") else ""
            vs = f"{serial['wall_s'] / r['wall_s']:.2f}x" if serial else "-"
            ident = "-" if not serial else "yes" if same else "NO"
            lines.append(f"| {name}{note} | {r['wall_s']:.1f} | {vs} | {util:.0f} | "
                         f"{r['client_peak_rss_mb']:.0f} | {wrss} | {written / 2**20:.0f} | {n} | "
                         f"{ident} | {r['load'][0]:.1f} / {r['load'][1]:.1f} |")
        lines += ["", "Wall time: the build alone (a LocalCluster's start-up, "
                  + ", ".join(f"{runs[n]['startup_s']:.1f} s" for n in ("local:1", "local:2") if n in runs and "startup_s" in runs[n])
                  + ", apart). CPU utilization: client + workers CPU time over wall time x "
                  f"{cores} cores. Bytes written: entries plus scratch (candidate blocks, merges, voxel sums). "
                  "Identical: every entry's sha256 and the manifest's bytes equal the serial build's.", ""]
        l2 = runs.get("local:2")
        t1 = cpu_model(st, 1)
        l2ok = bool(l2 and "stats" in l2 and l2.get("workers"))
        # a worker opens the drives (world, trajectories, scenes) outside any timed task: its CPU
        # time beyond its tasks' (process CPU minus task CPU, shared evenly) is its set-up
        setup = worker_setup_s(l2) if l2ok else st["tasks"]["plan"]["cpu_s"]
        plan_each = max(l2["stats"]["tasks"]["plan"]["cpu_each"]) if l2ok else 0.0
        t2 = cpu_model(l2["stats"] if l2ok else st, 2, plan_cpu_s=setup + plan_each)
        bound = process_cpu_bound(l2, cores) if l2ok and serial else None
        one = "serial" if serial else "one worker"
        lines += [f"On an idle machine (a model, not a measurement: each task's CPU time measured in the "
                  + ("serial and the local:2 run" if serial else "local:2 run")
                  + ", the tasks that read scans run in submission order on the first free "
                  f"worker after its set-up of {setup + plan_each:.0f} s CPU (opening the drives, outside any "
                  f"task, plus its planning task)): {one} {t1:.0f} s, local:2 {t2:.0f} s, **{t1 / t2:.2f}x**"
                  + (f"; a cruder bound from whole-process CPU times (the busiest worker, or every process's "
                     f"CPU over {cores} cores, whichever is longer): local:2 >= {bound:.0f} s, serial "
                     f"{serial['client_cpu_s']:.0f} s, <= {serial['client_cpu_s'] / bound:.2f}x" if bound else "")
                  + ". The measured speed-ups above are lower on a shared "
                  "machine: Linux groups a session's processes for CPU shares (autogroup), so two workers "
                  "under load get about the share one process would.", ""]
        tk = st["tasks"]
        lines += ["| task kind | count | CPU mean [s] | CPU total [s] | wall total [s] | MiB written |",
                  "|---|---|---|---|---|---|"]
        for k, r in tk.items():
            lines.append(f"| {k} | {r['count']} | {r.get('cpu_s', 0) / max(r['count'], 1):.3f} | "
                         f"{r.get('cpu_s', 0):.1f} | {r['seconds']:.1f} | {r['bytes'] / 2**20:.1f} |")
        pj = projections.get(kind)
        if pj:
            lines += ["", f"Projection to a {TARGET['area_km2']:.0f} km^2 map of {TARGET['path_km']:.0f} km of drives "
                      f"(from {pj['measured_km']:.2f} km over {pj['measured_area_km2']:.2f} km^2 measured): "
                      f"{pj['tasks']:,.0f} tasks, {pj['work_s'] / 3600:.1f} h of task time, "
                      f"{pj['overhead_s'] * 1e3:.1f} ms scheduling per task (no-op tasks on local:2), "
                      f"merges {pj['merge_chain_s'] / 60:.1f} min in sequence at most. "
                      + ", ".join(f"{w} workers: **{t / 3600:.2f} h**" for w, t in pj["times_s"].items())
                      + ". Model: T(W) = task time / W + tasks x scheduling (one scheduler) + merges (counts scale with "
                      "the driven length, blocks and tiles with the area, a tile's cost with the drives per area)."]
        lines.append("")
    if not tracking:
        why = ("--no-track" if args.no_track else "no block map was built, or the preset has no localization session")
        lines += ["### Tracking through the served map", "",
                  f"Not run ({why}). A map of the first frames of some drives does not cover the "
                  "localization session: track through the map of every mapping session.", ""]
    else:
        t = tracking
        lines += ["### Tracking through the served map", "",
                  f"`blockloc map serve` on the {t.get('map_run', 'serial')} block map, `{args.loc_seq}` tracked through {t['url']} "
                  f"(block backend, its own process, init at the first ground-truth pose"
                  + (f", first {args.track_frames} scans" if args.track_frames else "") + "):", "",
                  "| scans | ATE trans RMSE [m] | ATE max [m] | failures | recoveries | core median [ms] | "
                  "update p99 [ms] | peak RSS [MB] |", "|---|---|---|---|---|---|---|---|",
                  f"| {t['frames']} | {_f(t.get('ate_trans_rmse_m'), '{:.3f}')} | {_f(t.get('ate_trans_max_m'), '{:.3f}')} | "
                  f"{t['failures']} | {t['recoveries']} | {_f(t['core_ms_median'])} | {_f(t['update_ms_p99'])} | "
                  f"{t['peak_rss_mb']:.0f} |", ""]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- main


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child-build"]:
        spec = json.loads(Path(argv[1]).read_text())
        res = child_build(spec)
        Path(argv[2]).write_text(json.dumps(res))
        return 0
    ap = argparse.ArgumentParser(prog="python -m bench.city", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="city")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--kinds", default="block")
    ap.add_argument("--runs", default=",".join(RUNS))
    ap.add_argument("--sessions", default=None, metavar="map1,map2",
                    help="mapping sessions to merge (default: every mapping session of the preset)")
    ap.add_argument("--max-frames", type=int, default=None, help="first N frames of each mapping session")
    ap.add_argument("--track-frames", type=int, default=None, help="first N scans of the localization session")
    ap.add_argument("--no-track", action="store_true")
    ap.add_argument("--kill-at", type=float, default=0.4, help="kill:2: fraction of cluster:2's wall time")
    ap.add_argument("--work", default=None, help="directory for the maps (default: the cache)")
    ap.add_argument("--recorded", default=None, metavar="DIR",
                    help="build from the drives recorded (NCLT layout, written once) under DIR instead of "
                         "ray-casting their scans during the build")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--report-from", default=None, metavar="JSON",
                    help="only write the fragment again from a run's .json (give that run's options too)")
    args = ap.parse_args(argv)
    runs = [r for r in args.runs.split(",") if r]
    if not runs or [r for r in runs if r not in RUNS]:
        print(f"bench.city: --runs {args.runs!r}: expected a comma-separated list of {', '.join(RUNS)}",
              file=sys.stderr)
        return 2
    cmd = "python -m bench.city " + " ".join(shlex.quote(a) for a in argv)
    try:
        maps, loc = preset_sessions(args.preset)
    except SystemExit as exc:
        print(exc, file=sys.stderr)
        return 2
    chosen = [s for s in (args.sessions or "").split(",") if s]
    if [s for s in chosen if s not in maps]:
        print(f"bench.city: --sessions {args.sessions}: the {args.preset} preset's mapping sessions are "
              f"{', '.join(maps)}", file=sys.stderr)
        return 2
    args.sessions = chosen or maps
    args.loc_seq = f"sim:{args.preset}/{loc}@{args.seed}" if loc else None
    from blockloc.cache import cache_root
    from blockloc.config import load_config
    from blockloc.maps.distributed import ProcessCluster

    cfg = load_config("sim", overrides={"map": {"block_size_m": 100.0}})
    sizes = {"block_size_m": cfg.map.block_size_m, "tile_size_m": cfg.map.tile_size_m,
             "voxel_size_m": cfg.map.voxel_size_m, "keyframe_distance_m": cfg.map.keyframe_distance_m,
             "keyframe_angle_deg": cfg.map.keyframe_angle_deg}
    work = Path(args.work) if args.work else cache_root() / "bench" / f"city-{args.preset}-{args.seed}"
    work.mkdir(parents=True, exist_ok=True)
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    if args.report_from:
        saved = json.loads(Path(args.report_from).read_text())
        return write_report(args, saved["command"], saved["results"], saved["tracking"], saved.get("started", "?"))
    # the map kept for tracking: the serial build's, or (no serial run asked for) the first run's,
    # which equals it byte for byte (tests/maps/test_distributed.py)
    keep = "serial" if "serial" in runs else runs[0]
    recorded = None
    if args.recorded:
        recorded = record_drives(args.preset, args.seed, args.sessions, args.max_frames, Path(args.recorded))
    else:
        n_tiles, warm_s = warm_raster_tiles(args.preset, args.seed, args.sessions, args.max_frames)
        print(f"== simulator raster tiles around the drives: {n_tiles} ready in {warm_s:.0f} s", file=sys.stderr, flush=True)
    results: dict[str, dict] = {}
    for kind in [k for k in args.kinds.split(",") if k]:
        results[kind] = {}
        for name in runs:
            spec = {"name": name, "kind": kind, "preset": args.preset, "seed": args.seed, "sessions": args.sessions,
                    "max_frames": args.max_frames, "sizes": sizes, "out": str(work / f"{kind}-{name.replace(':', '_')}"),
                    "recorded": str(recorded) if recorded else None}
            print(f"== {kind} {name}", file=sys.stderr, flush=True)
            if name.startswith("local:") or name == "serial":
                spec["cluster"] = None if name == "serial" else name
                res = run_build(spec, work)
            else:
                env = dict(os.environ)
                with ProcessCluster(2, work / f"cluster-{kind}-{name.replace(':', '_')}", env=env) as cluster:
                    spec["cluster"] = cluster.address
                    kill_after = None
                    if name == "kill:2":
                        base = results[kind].get("cluster:2") or results[kind].get("local:2") or results[kind].get("serial")
                        kill_after = args.kill_at * base["wall_s"] if base and "wall_s" in base else 30.0
                    res = run_build(spec, work, kill_after, cluster.workers[0].pid if kill_after else None)
            results[kind][name] = res
            if "error" not in res:
                print(f"   {res['wall_s']:.1f} s, {res['entries']} entries, client {res['client_peak_rss_mb']:.0f} MB, "
                      f"workers {[round(w['peak_rss_mb']) for w in res['workers']]} MB", file=sys.stderr, flush=True)
            if name != keep:
                shutil.rmtree(spec["out"], ignore_errors=True)
    tracking = None
    block_map = work / f"block-{keep.replace(':', '_')}"
    if not args.no_track and args.loc_seq and (block_map / "manifest.json").exists():
        print(f"== tracking {args.loc_seq} through the served map", file=sys.stderr, flush=True)
        tracking = track_served(block_map, args.loc_seq, work, args.track_frames)
        tracking["map_run"] = keep
    return write_report(args, cmd, results, tracking, started)


def write_report(args, cmd: str, results: dict, tracking: dict | None, started: str) -> int:
    """docs/bench/city.md (``--out``) and its .json from the runs' results."""
    from blockloc.fileio import atomic_write_text

    projections = {k: projection(ref, r.get("local:2"), k) for k, r in results.items()
                   if (ref := reference_run(r)) is not None}
    text = report(args, cmd, results, projections, tracking, started)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, text)
    atomic_write_text(out.with_suffix(".json"), json.dumps(
        {"command": cmd, "started": started, "results": results, "projections": projections,
         "tracking": tracking}, indent=1, default=str))
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
