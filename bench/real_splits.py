"""The real walk over three splits (issue 41: every figure on several seeds or splits): writes
docs/bench/real_splits.md.

    python -m bench.real_splits

The BALM/Hilti walk (``shared/data/balm_hilti_walk``, 177 real scans, no IMU) as ``python -m
bench.real`` runs it (``blockloc/presets/handheld.yaml``, 8 m blocks, every scan a keyframe placed
with its reference pose, block backend, LiDAR-only from the reference pose at the first held-out
scan), on three splits of the walk into map scans and held-out scans:

- ``second half``: map 0-88, localize 89-176 (the split of ``real.md`` and the walk tests);
- ``first half``: map 89-176, localize 0-88;
- ``middle third``: map 0-58 and 118-176 (two drives of one map), localize 59-117.

Nothing is tuned here: the config is ``bench.real``'s.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "real_splits.md"
#: name: (map scan ranges [start, stop), held-out [start, stop))
SPLITS = {
    "second half": ([(0, 89)], (89, 177)),
    "first half": ([(89, 177)], (0, 89)),
    "middle third": ([(0, 59), (118, 177)], (59, 118)),
}


def build_split_map(seq, out: Path, cfg, ranges: list[tuple[int, int]]):
    """A block map of the scans in ``ranges`` (each a drive of the one sequence), every scan a
    keyframe placed with its reference pose."""
    from blockloc.maps.build_plan import build_map_from_drives
    from blockloc.maps.build_tasks import Drive

    drives = [Drive.of(seq, start=a, stop=b, name=f"walk[{a}:{b}]") for a, b in ranges]
    return build_map_from_drives(drives, "block", out, block_size_m=cfg.map.block_size_m,
                                 voxel_size_m=cfg.map.voxel_size_m, keyframe_distance_m=0.0,
                                 keyframe_angle_deg=0.0, deskew=False, overwrite=True)


def run_split(seq, cfg, ranges, held) -> dict:
    from bench.real import track_walk

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        store = build_split_map(seq, Path(tmp) / "map", cfg, ranges)
        build_s = time.perf_counter() - t0
        r = track_walk(seq, store, cfg, held[0], held[1], "gt")
        r["map_entries"], r["map_points"], r["build_s"] = len(store.entries), store.total_points, build_s
    return r


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(prog="python -m bench.real_splits")
    ap.add_argument("--splits", default=",".join(SPLITS), help=f"comma separated: {', '.join(SPLITS)}")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    from bench.__main__ import machine
    from bench.real import _walk, walk_config_handheld
    from blockloc.fileio import atomic_write_text

    names = [s.strip() for s in args.splits.split(",") if s.strip()]
    unknown = [n for n in names if n not in SPLITS]
    if unknown:
        ap.error(f"--splits {', '.join(unknown)}: expected some of {', '.join(SPLITS)}")
    cfg = walk_config_handheld()
    seq = _walk(cfg)
    cmd = "python -m bench.real_splits " + " ".join(argv if argv is not None else sys.argv[1:])
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    rows = {n: run_split(seq, cfg, *SPLITS[n]) for n in names}
    lines = ["## The real walk over three splits: map scans and held-out scans (issue 41)", "",
             f"Command: `{cmd.strip()}` (started {started}). Machine: {machine()}.", "",
             "LiDAR-only from the reference pose at the first held-out scan; `blockloc/presets/handheld.yaml` with 8 m "
             "blocks (`bench.real`'s config, nothing tuned here); every map scan a keyframe placed with its reference "
             "pose. ATE: `blockloc eval`'s, as `real.md` reports it; position error: the estimate against the "
             "reference pose of each scan. The reference is BALM's refined poses, not surveyed truth.", "",
             "| split | map scans | held-out scans | blocks | ATE [m] | position error RMS / max [m] | rotation [deg] | "
             "scans not ok | update median [ms] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for n, r in rows.items():
        ranges, held = SPLITS[n]
        m = r["metrics"]
        not_ok = {k: v for k, v in r["statuses"].items() if k != "ok"}
        lines.append(f"| {n} | {', '.join(f'{a}-{b - 1}' for a, b in ranges)} | {held[0]}-{held[1] - 1} | "
                     f"{r['map_entries']} | {m['ate_trans_rmse_m']:.4f} | {np.sqrt(np.mean(r['err_m'] ** 2)):.4f} / "
                     f"{r['err_m'].max():.4f} | {m['ate_rot_rmse_deg']:.3f} | "
                     f"{', '.join(f'{k} {v}' for k, v in not_ok.items()) or '0'} | {r['update_ms']['median']:.1f} |")
    pos = [float(np.sqrt(np.mean(r["err_m"] ** 2))) for r in rows.values()]
    lines += ["", f"Over the {len(rows)} splits: position error RMS median {statistics.median(pos):.4f} m, "
                  f"worst {max(pos):.4f} m.", ""]
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return args.out


if __name__ == "__main__":
    main()
