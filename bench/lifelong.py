"""Lifelong maps: change detection against the simulator's ground truth. Writes docs/bench/lifelong.md.

    python -m bench.lifelong                              # tiny preset, seed 1, loc_m12
    python -m bench.lifelong --preset small --session loc_m3 --stride 2

Steps, as a user types them (the map and the run are kept in --work and reused when there):
``blockloc map build --seq sim:P/map@S --kind block``, ``blockloc track --seq sim:P/SESSION@S
--init gt --no-record``; then the detection (``blockloc.maps.changes.detect_changes``, what
``blockloc map changes`` runs, here through the API to score its voxels) is scored against the
session's ``changes()``:

- per change of the truth (boxes in the map frame): found when 5 or more voxels of its class
  (removed / added) lie in its box grown by 0.75 m; with the nearest distance of the run's
  trajectory to the box (a change never in view cannot be found);
- precision per class: the share of detected voxels inside some truth box of that class grown by
  1 m. The simulator also changes the foliage of every crown between days (``foliage_change``),
  which has no box: voxels carved there count against precision.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "lifelong.md"


def _run(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def _inside(c: np.ndarray, box, pad: float) -> np.ndarray:
    x0, x1, y0, y1, z0, z1 = box
    return ((c[:, 0] > x0 - pad) & (c[:, 0] < x1 + pad) & (c[:, 1] > y0 - pad) & (c[:, 1] < y1 + pad)
            & (c[:, 2] > z0 - pad) & (c[:, 2] < z1 + pad))


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--session", default="loc_m12")
    ap.add_argument("--stride", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path("/tmp/blockloc-bench-lifelong"))
    args = ap.parse_args(argv)
    from bench.__main__ import machine
    from blockloc.maps.changes.detect import unpack_keys
    from blockloc.maps.changes.pipeline import detect_changes
    from blockloc.maps.changes.runs import read_run
    from blockloc.maps.store import open_map
    from blockloc.sim.changes import open_session

    P, S, sess = args.preset, args.seed, args.session
    work = args.work / f"{P}_{S}"
    work.mkdir(parents=True, exist_ok=True)
    mp, run_dir = work / "map", work / f"run_{sess}"
    cmds = [["blockloc", "map", "build", "--seq", f"sim:{P}/map@{S}", "--kind", "block", "--out", str(mp)],
            ["blockloc", "track", "--seq", f"sim:{P}/{sess}@{S}", "--map", str(mp), "--init", "gt",
             "--no-record", "--out", str(run_dir)]]
    reused = []
    for cmd, done in zip(cmds, (mp / "manifest.json", run_dir / "metrics.json")):
        if done.exists():
            reused.append(True)
        else:
            _run(cmd)
            reused.append(False)
    run = read_run(run_dir)
    seq = open_session(P, sess, S)
    t0 = time.perf_counter()
    res = detect_changes(open_map(mp), seq, run, stride=args.stride)
    t_detect = time.perf_counter() - t0
    vc = res.voxels
    cls = {"removed": (unpack_keys(vc.removed) + 0.5) * vc.voxel_m,
           "added": (unpack_keys(vc.added) + 0.5) * vc.voxel_m}
    truth = seq.changes()
    traj = run.T_map_body[:, :3, 3]
    rows, hits = [], {"removed": 0, "added": 0}
    for c in truth:
        box = c.box_map()
        k = "removed" if c.action == "removed" else "added"
        n = int(_inside(cls[k], box, 0.75).sum())
        centre = np.array([(box[0] + box[1]) / 2, (box[2] + box[3]) / 2])
        half = np.array([(box[1] - box[0]) / 2, (box[3] - box[2]) / 2])
        d = np.maximum(np.abs(traj[:, :2] - centre) - half, 0.0)
        dist = float(np.min(np.hypot(d[:, 0], d[:, 1]))) if len(traj) else float("nan")
        rows.append((c.kind, c.action, dist, n, n >= 5))
    prec = {}
    for k, c in cls.items():
        boxes = [t.box_map() for t in truth if (t.action == "removed") == (k == "removed")]
        inside = np.zeros(len(c), bool)
        for b in boxes:
            inside |= _inside(c, b, 1.0)
        prec[k] = (int(inside.sum()), len(c))
    in_range = [r for r in rows if r[2] <= 25.0]
    lines = ["## Lifelong maps: change detection against the simulator's truth", "",
             f"Machine: {machine()}. Command: `python -m bench.lifelong --preset {P} --seed {S} --session {sess} "
             f"--stride {args.stride}`, run {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. "
             f"One run (seed {S}); the map and the run come from "
             + "; ".join(f"`{' '.join(c)}`" + (" (kept from an earlier run)" if r else "") for c, r in zip(cmds, reused))
             + ".", "",
             f"Detection: {res.frames_trusted} trusted frames, {res.scans_used} scans used (stride {args.stride}), "
             f"{res.scans_rejected} dropped by the consistency gate, {t_detect:.0f} s wall on this (shared) machine.", "",
             "| change | action | nearest approach of the run (m) | voxels of its class in its box | found |",
             "|---|---|---|---|---|"]
    for kind, action, dist, n, ok in rows:
        lines.append(f"| {kind} | {action} | {dist:.1f} | {n} | {'yes' if ok else 'no'} |")
    lines += ["", f"Changes within 25 m of the run found: {sum(r[4] for r in in_range)} of {len(in_range)}.", "",
              "| class | detected voxels | inside a truth box of the class (+1 m) | precision |", "|---|---|---|---|"]
    for k, (inside, total) in prec.items():
        lines.append(f"| {k} | {total} | {inside} | {inside / total:.2f} |" if total else f"| {k} | 0 | 0 | - |")
    lines += ["", "Per block (`changes.json`):", "", "| block | removed m3 | added m3 | dynamic voxels | confidence | confirmed |",
              "|---|---|---|---|---|---|"]
    for b in res.blocks:
        lines.append(f"| {b['block']} | {b['removed_m3']} | {b['added_m3']} | {b['dynamic_voxels']} | "
                     f"{b['confidence']} | {b['confirmed']} |")
    lines += ["", "Not yet measured: the DUFOMap comparison, several seeds, the small and campus presets."]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    tmp = OUT.with_suffix(".md.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(OUT)
    (work / f"bench_{sess}.json").write_text(json.dumps({"rows": rows, "precision": prec}, default=str))
    print("\n".join(lines))
    return OUT


if __name__ == "__main__":
    main(sys.argv[1:])
