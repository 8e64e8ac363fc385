"""What recording (MCAP) and serving (Foxglove WebSocket) cost a real tracking run (issue 18).

    python -m bench.recording                       # none, mcap, live+client; 3 repeats; docs/bench/recording.md
    python -m bench.recording --frames 300 --repeats 3 --modes none,mcap,live+client
    python -m bench.recording --modes mcap --repeats 1 --report runs/viz   # + report.html, no fragment
    python -m bench.recording --synthetic --repeats 2  # 20k scans, 200k map / 30 s, JSON lines only

Tracks the cached `small` world (block map, init at ground truth) and feeds every frame to the
observer from inside the tracking loop, as the session engine will: the scan is the frame's points
in the lidar frame (the deskewed copy has the same size) and the local map is sent whenever the
provider's version changes. Modes alternate within each repeat to spread machine noise.
Prints, per run, the wall and CPU time spent inside ``observer.frame`` and its share of the
tracking wall time of the same run (robust to a loaded machine); then the tracking wall time per
frame of each mode against the first mode (meaningful only on a quiet machine).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _viewer_process(url: str):
    """A Foxglove WS client subscribed to every topic, in its own process as a viewer would be."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "tests.viz.ws_client", url], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    if proc.stdout.readline().strip() != "subscribed":
        raise SystemExit("the viewer process did not subscribe")
    return proc


def _viewer_count(proc) -> int:
    out, _ = proc.communicate(timeout=120)
    return sum(json.loads(out.strip().splitlines()[-1]).values())


class _Capture:
    """Keeps every event (for profiling an observer offline on real frames)."""

    def __init__(self) -> None:
        self.info, self.events = None, []

    def start(self, info):
        self.info = info

    def frame(self, ev):
        self.events.append(ev)

    def finish(self, metrics):
        import pickle

        with open("/tmp/blockloc_viz_events.pkl", "wb") as f:
            pickle.dump((self.info, self.events), f)


def _observer_for(mode: str, out: Path):
    if mode == "none":
        return None, None
    if mode == "capture":
        return _Capture(), None
    if mode == "mcap":
        from blockloc.viz.mcap_recorder import McapRecorder

        return McapRecorder(out / "run.mcap"), None
    if mode.startswith("live"):
        from blockloc.viz.live import LiveServer

        server = LiveServer(port=0)
        return server, (_viewer_process(server.url) if mode == "live+client" else None)
    raise SystemExit(f"unknown mode {mode!r}")


def _entries(store) -> list[dict]:
    """RunInfo.map_entries of a store, each footprint the convex hull of its points (x/y)."""
    from scipy.spatial import ConvexHull

    out = []
    for e in store.entries:
        xy = store.load_points([e.id])[:, :2]
        hull = xy[ConvexHull(xy).vertices] if len(xy) >= 3 else None
        out.append({"id": str(e.id), "bounds_min": e.bounds_min, "bounds_max": e.bounds_max,
                    "centroid": e.centroid, "footprint": hull})
    return out


def write_run_report(out: Path, res, store, cfg_dict: dict) -> Path:
    """report.html of a pipeline result (what the session engine will do at the end of a run)."""
    from blockloc.viz.report import write_report

    pts = store.load_points(store.ids)
    images = {name: out / f"{name}.png" for name in ("trajectories", "errors") if (out / f"{name}.png").exists()}
    return write_report(out / "report.html", metrics=res.metrics, estimate=res.trajectory,
                        ground_truth=store_gt.get("gt"), diagnostics=res.diagnostics, config=cfg_dict,
                        map_xy=pts[::max(1, len(pts) // 100_000), :2], map_entries=_entries(store), images=images)


store_gt: dict = {}


class _Timed:
    """An observer wrapper that times what the session spends in the observer's calls."""

    def __init__(self, inner, spent: dict) -> None:
        self.inner, self.spent, self.finish_s = inner, spent, 0.0

    def start(self, info) -> None:
        store_gt["gt"] = info.ground_truth
        self.inner.start(info)

    def frame(self, event) -> None:
        w0, c0 = time.perf_counter(), time.thread_time()
        self.inner.frame(event)
        self.spent["wall"] += time.perf_counter() - w0
        self.spent["cpu"] += time.thread_time() - c0
        self.spent["maps"] += event.local_map_points is not None

    def finish(self, metrics: dict) -> None:
        t0 = time.perf_counter()
        self.inner.finish(metrics)
        self.finish_s = time.perf_counter() - t0


def run_once(mode: str, frames: int | None, report_dir: Path | None = None) -> dict:
    from blockloc.app.assemble import build_session
    from blockloc.app.catalog import open_sequence
    from blockloc.app.runs import prepare_small_world
    from blockloc.maps.store import open_map

    world, cfg = prepare_small_world()
    tmp = report_dir if report_dir is not None else Path(tempfile.mkdtemp(prefix=f"viz-overhead-{mode}-"))
    observer, client = _observer_for(mode, tmp)
    spent = {"wall": 0.0, "cpu": 0.0, "maps": 0}
    timed = _Timed(observer, spent) if observer is not None else None
    store = open_map(world.block_map)
    seq = open_sequence(world.loc, dataset_cfg=cfg.dataset)
    session = build_session(cfg, seq, store, backend="block", observers=[timed] if timed else [],
                                  out_dir=report_dir)
    res = session.run(0, frames, init="gt")
    finish_s = timed.finish_s if timed is not None else 0.0
    n = res.metrics["frames"]
    out = {"mode": mode, "frames": n, "track_s": res.metrics["track_s"], "finish_s": finish_s,
           "observer_ms_per_frame": 1e3 * spent["wall"] / n, "observer_cpu_ms_per_frame": 1e3 * spent["cpu"] / n,
           "observer_share_of_track_pct": 100 * spent["wall"] / res.metrics["track_s"],
           "local_maps": spent["maps"]}
    if mode == "mcap":
        size = (tmp / "run.mcap").stat().st_size
        span = float(res.trajectory.stamps[-1] - res.trajectory.stamps[0])
        out.update(file_mb=size / 1e6, mb_per_min=size / 1e6 / (span / 60.0), sensor_s=span)
    if report_dir is not None:
        write_run_report(report_dir, res, store, cfg.to_dict())
    if client is not None:
        out["client_messages"] = _viewer_count(client)
    return out


def synthetic_once(kind: str, background: bool, pace_s: float = 0.006) -> dict:
    """The brief's realistic sizes without tracking: 20k-point scans at 10 Hz, a 200k-point local
    map every 30 s, 60 s of sensor time; each frame() followed by ``pace_s`` of busy work (a fast
    tracker holding the GIL). Reports this process's CPU and wall time inside frame(), the
    worker's CPU per frame and the file size per minute."""
    import psutil

    from blockloc.viz.live import LiveServer
    from blockloc.viz.mcap_recorder import McapRecorder
    from tests.viz.synthetic import make_run

    run = make_run(duration_s=60.0, scan_points=20_000, map_points=200_000, map_every_s=30.0,
                   map_on_block_change=False)
    tmp = Path(tempfile.mkdtemp(prefix="viz-synthetic-"))
    client = None
    if kind == "mcap":
        obs = McapRecorder(tmp / "run.mcap", background=background)
    else:
        obs = LiveServer(port=0, background=background)
        if kind == "live+client":
            client = _viewer_process(obs.url)
    obs.start(run.info)
    worker0 = 0.0
    if background:
        time.sleep(1.0)
        t = psutil.Process(obs.worker.proc.pid).cpu_times()
        worker0 = t.user + t.system  # its start-up (imports, RunInfo) is not per-frame work
    cpu, wall = [], []
    for ev in run.events:
        c0, w0 = time.thread_time(), time.perf_counter()
        obs.frame(ev)
        cpu.append(time.thread_time() - c0)
        wall.append(time.perf_counter() - w0)
        end = time.perf_counter() + pace_s
        while time.perf_counter() < end:
            pass
    worker_cpu = None
    if background:
        while obs.worker.unread_bytes():
            time.sleep(0.05)
        time.sleep(1.0)
        t = psutil.Process(obs.worker.proc.pid).cpu_times()
        worker_cpu = (t.user + t.system - worker0) / len(run.events)
    obs.finish({})
    out = {"kind": kind, "background": background, "frames": len(run.events),
           "frame_cpu_ms": 1e3 * float(np.mean(cpu)), "frame_wall_ms_median": 1e3 * float(np.median(wall)),
           "frame_wall_ms_mean": 1e3 * float(np.mean(wall)),
           "worker_cpu_ms_per_frame": None if worker_cpu is None else 1e3 * worker_cpu}
    if kind == "mcap":
        out["file_mb_per_min"] = (tmp / "run.mcap").stat().st_size / 1e6 / ((run.events[-1].stamp - run.events[0].stamp) / 60)
    if client is not None:
        out["client_messages"] = _viewer_count(client)
    return out


def write_fragment(path: Path, cmd: str, rows: dict[str, list[dict]], load: tuple[float, float]) -> None:
    """docs/bench/recording.md: per mode medians over the repeats, overhead against the first mode."""
    from bench.__main__ import machine
    from blockloc.fileio import atomic_write_text

    modes = list(rows)
    med = lambda m, k: statistics.median(x[k] for x in rows[m] if x.get(k) is not None)  # noqa: E731
    per = {m: statistics.median(x["track_s"] / x["frames"] for x in rows[m]) for m in modes}
    lines = [
        "## Recording and live view (issue 18)", "",
        f"Command: `{cmd}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}). Machine: {machine()}. "
        f"Load average (1 min) {load[0]:.1f} before and {load[1]:.1f} after.", "",
        f"The `small` world's `loc` session tracked from ground truth, block backend, {rows[modes[0]][0]['frames']} "
        f"frames, {len(rows[modes[0]])} runs per mode, modes alternating within each repeat. `mcap`: run.mcap "
        "written by the recorder's worker process; `live+client`: the Foxglove WebSocket server with a viewer "
        "process subscribed to every topic. In-loop = wall time the tracking thread spends handing a frame "
        "to the observer; overhead = tracking wall time per frame against `none` in the same run.", "",
        "| mode | median wall per frame [ms] | overhead vs none | in-loop per frame [ms] | in-loop share of "
        "tracking | file [MB per minute of sensor time] | viewer messages |",
        "|---|---|---|---|---|---|---|",
    ]
    for m in modes:
        size = med(m, "mb_per_min") if any("mb_per_min" in x for x in rows[m]) else None
        msgs = med(m, "client_messages") if any("client_messages" in x for x in rows[m]) else None
        lines.append(f"| {m} | {1e3 * per[m]:.1f} | {100 * (per[m] / per[modes[0]] - 1):+.1f}% | "
                     f"{med(m, 'observer_ms_per_frame'):.2f} | {med(m, 'observer_share_of_track_pct'):.1f}% | "
                     f"{'-' if size is None else f'{size:.1f}'} | {'-' if msgs is None else f'{msgs:.0f}'} |")
    atomic_write_text(path, "\n".join(lines) + "\n")


def main() -> None:
    import os
    import shlex
    import sys

    ap = argparse.ArgumentParser(prog="python -m bench.recording")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--modes", default="none,mcap,live+client")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "docs" / "bench" / "recording.md")
    ap.add_argument("--synthetic", action="store_true",
                    help="the brief's realistic sizes without tracking (mcap/live+client, worker and in-process)")
    ap.add_argument("--report", type=Path, default=None,
                    help="with --modes mcap: write run.mcap, the pipeline's results and report.html here")
    args = ap.parse_args()
    if args.synthetic:
        for r in range(args.repeats):
            for kind in ("mcap", "live+client"):
                for bg in (True, False):
                    print(json.dumps(synthetic_once(kind, bg)), flush=True)
        return
    cmd = "python -m bench.recording " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    load0 = os.getloadavg()[0]
    modes = args.modes.split(",")
    rows: dict[str, list[dict]] = {m: [] for m in modes}
    for r in range(args.repeats):
        for m in (modes if r % 2 == 0 else modes[::-1]):
            row = run_once(m, args.frames, args.report if m == "mcap" else None)
            rows[m].append(row)
            print(json.dumps(row), flush=True)
    base = statistics.median(x["track_s"] / x["frames"] for x in rows[modes[0]])
    for m in modes:
        per = statistics.median(x["track_s"] / x["frames"] for x in rows[m])
        print(f"{m:12s} median {per * 1e3:.2f} ms/frame  overhead {100 * (per / base - 1):+.1f}% vs {modes[0]}")
    if args.report is None:
        write_fragment(args.out, cmd, rows, (load0, os.getloadavg()[0]))
        print(args.out)


if __name__ == "__main__":
    main()
