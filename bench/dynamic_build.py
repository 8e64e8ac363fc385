"""Moving objects left out by ``map build --remove-dynamic`` (issue 43): writes docs/bench/dynamic_build.md.

    python -m bench.dynamic_build                          # small world seed 2, map_m12, 400 frames
    python -m bench.dynamic_build --seed 3 --frames 200 --track-frames 200 --work /tmp/dynb

Two parts, one run each:

- **The filter against the labels.** The build's filter (:class:`blockloc.maps.build_tasks.DynamicFilter`:
  a task's keyframes plus 8 keyframes each side as evidence) over the drive's keyframes in runs of
  ``KEYFRAMES_PER_RUN``, as the block build's run tasks take them; every keyframe point carries the
  simulator's label (moving or not). SA = static points kept, DA = moving points left out,
  AA = sqrt(SA * DA), on the points the map is built from (before its voxel filter).
- **What it does for tracking.** ``blockloc map build`` of the same drive with and without
  ``--remove-dynamic``, then ``blockloc track --init gt`` of a session of the same day on each map:
  ATE, failures, rejected scans, and the build's time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "dynamic_build.md"


def filter_scores(seq_name: str, frames: int) -> dict:
    """SA / DA / AA (%) of the build's filter on the keyframes of ``seq_name``'s first ``frames``
    frames, with point counts and the filter's CPU seconds."""
    from blockloc.app.catalog import open_sequence
    from blockloc.geometry import up_from_gravity
    from blockloc.maps.block_maps import KEYFRAMES_PER_RUN
    from blockloc.maps.build_tasks import dynamic_filter
    from blockloc.maps.dynamic_removal import DynamicParams, static_masks
    from blockloc.maps.mapping import mapping_poses_or_fail, plan_keyframes, scan_to_map
    from blockloc.sim.changes import LABEL_MOVING

    seq = open_sequence(seq_name)
    if not callable(getattr(seq, "frame_labels", None)):
        raise SystemExit(f"{seq_name}: no point labels (a changed day of the simulator has them)")
    plan = plan_keyframes(seq, keyframe_distance_m=1.0, keyframe_angle_deg=15.0, stop=frames)
    traj = mapping_poses_or_fail(seq)
    T_body_lidar = np.asarray(seq.info.T_body_lidar, np.float64)
    up = up_from_gravity(seq.info.gravity_map)
    params = DynamicParams()
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frame -> (map points, moving labels)

    def read(f: int):
        if f not in cache:
            frame, lab = seq.frame_labels(f)
            pts = scan_to_map(frame.points, frame.time_offsets, frame.stamp, traj, T_body_lidar, deskew=True)
            cache[f] = (pts, np.asarray(lab) == LABEL_MOVING)
        return cache[f]

    kept_static = static = kept_moving = moving = 0
    cpu = 0.0
    for k0 in range(0, len(plan.frames), KEYFRAMES_PER_RUN):
        keys = np.arange(k0, min(k0 + KEYFRAMES_PER_RUN, len(plan.frames)))
        filt = dynamic_filter(plan, keys, params)
        evidence = [(o, read(f)[0]) for f, o in zip(filt.frames, filt.origins)]
        own = [filt.frames.index(int(f)) for f in plan.frames[keys]]
        c0 = time.process_time()
        masks = static_masks(evidence, own, params, up)
        cpu += time.process_time() - c0
        for i, keep in zip(own, masks):
            lab = read(filt.frames[i])[1]
            static += int((~lab).sum())
            kept_static += int((keep & ~lab).sum())
            moving += int(lab.sum())
            kept_moving += int((keep & lab).sum())
        lo = int(plan.frames[max(0, k0 - 8)])
        for f in [f for f in cache if f < lo]:
            del cache[f]
    sa = 100.0 * kept_static / max(static, 1)
    da = 100.0 * (moving - kept_moving) / max(moving, 1)
    return {"keyframes": int(len(plan.frames)), "static": static, "moving": moving, "sa": sa, "da": da,
            "aa": float(np.sqrt(sa * da)), "left_out": (static - kept_static) + (moving - kept_moving),
            "cpu_s": cpu}


def _run(cmd: list[str], log: Path) -> tuple[float, float]:
    """Run ``cmd`` (output to ``log``); (wall, CPU of the child) seconds."""
    w0, c0 = time.perf_counter(), os.times()
    with open(log, "w") as fh:
        subprocess.run(cmd, check=True, stdout=fh, stderr=subprocess.STDOUT)
    c1 = os.times()
    return time.perf_counter() - w0, (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system)


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(prog="python -m bench.dynamic_build")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--session", default="map_m12", help="the labelled mapping drive (map_m12)")
    ap.add_argument("--track", default="loc_m12", help="the session of the same day tracked on both maps")
    ap.add_argument("--frames", type=int, default=400, help="frames of the mapping drive the filter is scored on")
    ap.add_argument("--track-frames", type=int, default=400, help="frames tracked (0: no tracking part)")
    ap.add_argument("--work", type=Path, default=Path(os.environ.get("BENCH_WORK", "/tmp")) / "blockloc-bench-dynbuild")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    from bench.__main__ import machine
    from blockloc.fileio import atomic_write_text

    args.work.mkdir(parents=True, exist_ok=True)
    seq = f"sim:{args.preset}/{args.session}@{args.seed}"
    cmd = "python -m bench.dynamic_build " + " ".join(argv if argv is not None else sys.argv[1:])
    started = time.gmtime()
    load0 = os.getloadavg()[0]
    w0 = time.perf_counter()
    s = filter_scores(seq, args.frames)
    wall = time.perf_counter() - w0
    lines = [f"## Moving objects left out by `map build --remove-dynamic`, {seq}", "",
             f"`{cmd.strip()}` ({time.strftime('%Y-%m-%d %H:%M UTC', started)}, {machine()}); one run, "
             f"load average {load0:.1f} at the start.", "",
             f"### The build's filter against the simulator's labels (first {args.frames} frames: "
             f"{s['keyframes']} keyframes)", "",
             "Every keyframe's points in the map frame, before the voxel filter; moving = the label says "
             "the point hit a pedestrian or a moving vehicle. Evidence per run of keyframes as the block "
             "build's run tasks take them, with 8 keyframes on each side.", "",
             "| static points | moving points | SA [%] | DA [%] | AA [%] | points left out | filter CPU [s] | wall, reading included [s] |",
             "|---|---|---|---|---|---|---|---|",
             f"| {s['static']:,} | {s['moving']:,} | {s['sa']:.2f} | {s['da']:.2f} | {s['aa']:.2f} | "
             f"{s['left_out']:,} | {s['cpu_s']:.1f} | {wall:.0f} |", ""]
    if args.track_frames:
        rows = []
        for name, flag in (("kept", "--keep-dynamic"), ("left out", "--remove-dynamic")):
            slug = "keep" if flag == "--keep-dynamic" else "remove"
            mp = args.work / f"map_{args.preset}_{args.session}_{args.seed}_{slug}"
            bw = bc = float("nan")
            if not (mp / "manifest.json").is_file():
                bw, bc = _run(["blockloc", "map", "build", "--seq", seq, "--kind", "block", flag, "--out", str(mp)],
                              args.work / f"build_{slug}.log")
            run = args.work / f"run_{args.preset}_{args.track}_{args.seed}_{slug}_f{args.track_frames}"
            if not (run / "metrics.json").is_file():
                _run(["blockloc", "track", "--seq", f"sim:{args.preset}/{args.track}@{args.seed}", "--map", str(mp),
                      "--init", "gt", "--no-record", "--max-frames", str(args.track_frames), "--out", str(run)],
                     args.work / f"track_{slug}.log")
            m = json.loads((run / "metrics.json").read_text())
            manifest = json.loads((mp / "manifest.json").read_text())
            rd = (manifest.get("parameters") or {}).get("remove_dynamic") or {}
            rows.append((name, m, bw, bc, rd.get("moving_points")))
        lines += [f"### Tracking `sim:{args.preset}/{args.track}@{args.seed}` (first {args.track_frames} frames, "
                  "`--init gt`) on the map with moving objects kept and left out", "",
                  "| moving objects | ATE [m] | rotation [deg] | failures | rejected scans | points left out by the build | build wall / CPU [s] |",
                  "|---|---|---|---|---|---|---|"]
        for name, m, bw, bc, mv in rows:
            ate = m["ate_trans_rmse_m"]
            lines.append(f"| {name} | {ate:.4f} | {m.get('ate_rot_rmse_deg', float('nan')):.3f} | "
                         f"{m.get('failures', '-')} | {m.get('rejected', '-')} | "
                         f"{'-' if mv is None else f'{mv:,}'} | {bw:.0f} / {bc:.0f} |")
        lines += ["", "Build times are blank (nan) for a map kept from an earlier run in the work directory.", ""]
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return args.out


if __name__ == "__main__":
    main()
