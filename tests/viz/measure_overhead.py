"""Measure what recording / serving costs a real tracking run (not a test: timings never are).

    PYTHONPATH=. python -m tests.viz.measure_overhead [--frames N] [--repeats R] [--modes none,mcap,live,live+client]

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
import asyncio
import json
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def _observer_for(mode: str, out: Path):
    if mode == "none":
        return None, None
    if mode == "mcap":
        from blockloc.viz.mcap_recorder import McapRecorder

        return McapRecorder(out / "run.mcap"), None
    if mode.startswith("live"):
        from blockloc.viz.live import LiveServer

        server = LiveServer(port=0)
        client = None
        if mode == "live+client":
            from tests.viz.ws_client import FoxgloveClient

            client = FoxgloveClient(f"ws://127.0.0.1:{server.port}", topics=None)
            client.start()
            client.wait_connected(10.0)
        return server, client
    raise SystemExit(f"unknown mode {mode!r}")


def run_once(mode: str, frames: int | None) -> dict:
    from blockloc.demo import prepare_small_world
    from blockloc.pipeline import LocalizationPipeline
    from blockloc.viz.events import FrameEvent, RunInfo

    paths, cfg = prepare_small_world()
    tmp = Path(tempfile.mkdtemp(prefix=f"viz-overhead-{mode}-"))
    observer, client = _observer_for(mode, tmp)
    spent = {"wall": 0.0, "cpu": 0.0, "maps": 0}

    class Pipe(LocalizationPipeline):
        def _make_tracker(self):
            super()._make_tracker()
            if observer is None:
                return
            store = self.store
            entries = [{"id": str(e.id), "bounds_min": e.bounds_min, "bounds_max": e.bounds_max,
                        "centroid": e.centroid, "footprint": None} for e in store.entries]
            observer.start(RunInfo(sequence=self.seq_name, T_body_lidar=self.info.T_body_lidar, map_kind="block",
                                   map_entries=entries, ground_truth=self.gt, config={}, out_dir=tmp))
            insert, last = self.tracker.insert_frame, {"version": None, "map": None}
            update = self.provider.update

            def provider_update(*a, **k):
                last["map"] = update(*a, **k)
                return last["map"]

            self.provider.update = provider_update

            def insert_frame(frame):
                est = insert(frame)
                lm = last["map"]
                lm_pts, lm_id, entries_now = None, None, ()
                if lm is not None:
                    lm_id, entries_now = lm.region_id, tuple(lm.entry_ids)
                    if lm.version != last["version"]:
                        last["version"] = lm.version
                        lm_pts = lm.points
                d = est.as_dict()
                w0, c0 = time.perf_counter(), time.thread_time()
                observer.frame(FrameEvent(index=est.index, stamp=est.stamp, T_map_body=est.T_map_body,
                                          covariance=est.covariance, velocity_map=est.velocity_map,
                                          status=d["status"], diagnostics=d, scan_lidar=frame.points,
                                          local_map_points=lm_pts, local_map_id=lm_id, active_entries=entries_now))
                spent["wall"] += time.perf_counter() - w0
                spent["cpu"] += time.thread_time() - c0
                spent["maps"] += lm_pts is not None
                return est

            self.tracker.insert_frame = insert_frame

    pipe = Pipe(paths.dataset / "loc", cfg=cfg, map_path=paths.block_map, backend="block", init="gt",
                max_frames=frames)
    res = pipe.run()
    t0 = time.perf_counter()
    if observer is not None:
        observer.finish(res.metrics)
    finish_s = time.perf_counter() - t0
    n = res.metrics["frames"]
    out = {"mode": mode, "frames": n, "track_s": res.metrics["track_s"], "finish_s": finish_s,
           "observer_ms_per_frame": 1e3 * spent["wall"] / n, "observer_cpu_ms_per_frame": 1e3 * spent["cpu"] / n,
           "observer_share_of_track_pct": 100 * spent["wall"] / res.metrics["track_s"],
           "local_maps": spent["maps"]}
    if mode == "mcap":
        size = (tmp / "run.mcap").stat().st_size
        span = float(res.trajectory.stamps[-1] - res.trajectory.stamps[0])
        out.update(file_mb=size / 1e6, mb_per_min=size / 1e6 / (span / 60.0), sensor_s=span)
    if client is not None:
        client.stop()
        out["client_messages"] = sum(client.counts.values())
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--modes", default="none,mcap")
    args = ap.parse_args()
    modes = args.modes.split(",")
    rows: dict[str, list[dict]] = {m: [] for m in modes}
    for r in range(args.repeats):
        for m in (modes if r % 2 == 0 else modes[::-1]):
            row = run_once(m, args.frames)
            rows[m].append(row)
            print(json.dumps(row), flush=True)
    base = statistics.median(x["track_s"] / x["frames"] for x in rows[modes[0]])
    for m in modes:
        per = statistics.median(x["track_s"] / x["frames"] for x in rows[m])
        print(f"{m:12s} median {per * 1e3:.2f} ms/frame  overhead {100 * (per / base - 1):+.1f}% vs {modes[0]}")


if __name__ == "__main__":
    main()
