"""Dynamic points against the best public remover (issue 43): writes docs/bench/dynamic.md.

    python -m bench.dynamic                                   # small world seed 2, map_m12, 2 x 150 scans
    python -m bench.dynamic --starts 250 --frames 40 --work /tmp/dyn   # a few minutes on a quiet machine

Steps, per stretch: ``blockloc export dynamicmap --seq sim:P/SESSION@S --start A --frames N --step K
--out WORK/...`` (kept and reused when there), then :func:`bench._dynamic.run_dynamic_comparison`
on those scans: the raw map, our remover (``blockloc.maps.dynamic_removal``) and DUFOMap (``pip
install dufomap``; its published parameters voxel 0.1 m, d_s 0.2, d_p 1), each scored with the
benchmark's SA / DA / AA (0.05 m nearest-neighbour transfer) in the same run.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "dynamic.md"


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(prog="python -m bench.dynamic")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--session", default="map_m12", help="a labelled day: map_m12, loc_m3, loc_m12")
    ap.add_argument("--starts", default="250,600",
                    help="first frame of each stretch, comma-separated (250: seed 2's busiest stretch, on "
                         "which our parameters were chosen; 600: held out)")
    ap.add_argument("--frames", type=int, default=150, help="scans exported per stretch")
    ap.add_argument("--step", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path(os.environ.get("BENCH_WORK", "/tmp")) / "blockloc-bench-dynamic")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    from bench.__main__ import machine
    from bench._dynamic import DUFOMAP_PARAMS, run_dynamic_comparison
    from blockloc.fileio import atomic_write_text

    seq = f"sim:{args.preset}/{args.session}@{args.seed}"
    cmd = "python -m bench.dynamic " + " ".join(argv if argv is not None else sys.argv[1:])
    started = time.gmtime()
    lines = [
        f"## Dynamic points against DUFOMap (DynamicMap Benchmark format), {seq}", "",
        f"`{cmd.strip()}` ({time.strftime('%Y-%m-%d %H:%M UTC', started)}, {machine()}). One run per "
        f"stretch of `{seq}` (seed {args.seed}): the pedestrians and moving cars of the simulator's "
        "12-month day are dynamic; everything else, changed structure included, is static on its own day.", "",
        "SA = static points kept, DA = dynamic points removed, AA = sqrt(SA * DA), HA their harmonic mean "
        "(%); a ground-truth point counts as kept when a point of the cleaned map lies within 0.05 m "
        "(the benchmark's `export_eval_pcd` radius). Wall and CPU seconds of the method alone (CPU: "
        "this process, all its threads), with the 1-min load average after it.", "",
    ]
    for start in (int(x) for x in args.starts.split(",") if x.strip()):
        seq_dir = args.work / f"{args.preset}_{args.session}_s{args.seed}_{start}_{args.frames}x{args.step}"
        export = ["blockloc", "export", "dynamicmap", "--seq", seq, "--start", str(start), "--frames",
                  str(args.frames), "--step", str(args.step), "--out", str(seq_dir)]
        if not (seq_dir / "gt_cloud.pcd").is_file():
            subprocess.run(export, check=True, stdout=subprocess.DEVNULL)
        load0 = os.getloadavg()[0]
        rows = run_dynamic_comparison(seq_dir, args.work / f"outputs_{start}")
        r0 = rows[0]
        lines += [f"### Frames {start}.. (every {args.step} frames, {args.frames} scans)", "",
                  f"Data: `{' '.join(export).replace(str(args.work), 'WORK')}` (default ranges 2.5-50 m): "
                  f"{r0['static_points'] + r0['dynamic_points']:,} ground-truth points, {r0['dynamic_points']:,} "
                  f"dynamic. Load average {load0:.1f} at the start.", "",
                  "| method | SA [%] | DA [%] | AA [%] | HA [%] | points kept | wall [s] | CPU [s] | load |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| {r['method']} | {r['sa']:.2f} | {r['da']:.2f} | {r['aa']:.2f} | {r['ha']:.2f} | "
                         f"{r['kept_points']:,} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['load1']:.1f} |")
        lines.append("")
    from blockloc.maps.dynamic_removal import DynamicParams

    p = DynamicParams()
    lines += [f"DUFOMap {_dufomap_version()}: `dufomap({DUFOMAP_PARAMS['resolution']}, {DUFOMAP_PARAMS['d_s']}, "
              f"{DUFOMAP_PARAMS['d_p']})`, every scan `run` in order, then `oncePropagateCluster(if_propagate=True, "
              "if_cluster=False)` and each scan's `segment` (label 0 kept), as its offline tool does. The row "
              "`DUFOMap d_p 0` is not its published setting: a sensitivity check (our reading of the d_p 1 result: a voxel is free "
              "only with no unknown voxel beside it, and a 32-beam scan leaves unknown cells between its rings "
              "beyond ~10 m). "
              f"blockloc: voxel {p.voxel_m} m, ray margin {p.margin_m} m, log-odds {p.l_occ} / {p.l_free}, "
              f"min_free {p.min_free}, {p.grow_rounds} vertical growing rounds at ratio {p.grow_ratio} "
              "(`blockloc.maps.dynamic_removal`): chosen on seed 2's stretch from frame 250 (about 30 variants of "
              "ratio, growth and free weight screened there by exact point masks); no other stretch or seed was "
              "looked at before its run.", ""]
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return args.out


def _dufomap_version() -> str:
    try:
        from importlib.metadata import version

        return version("dufomap")
    except Exception:  # noqa: BLE001 (any metadata failure: just no version)
        return "(version unknown)"


if __name__ == "__main__":
    main()
