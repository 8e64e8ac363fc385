"""Benchmark of map building and serving on a simulated world.

    python -m bench.maps [--preset campus] [--seed 1] [--max-frames N] [--every 5]

One streaming pass over the mapping session (``sim:<preset>/map@<seed>``, scans ray-cast on the
fly) feeds both the block-map builder (Algorithm 1) and the grid builder; the script then writes:
block and grid stores, the global map as one PCD, and the global PCD tiled at 20 m; and measures

- build times (scan simulation + deskew, block algorithm, grid binning, writing),
- grid storage overhead: tiles vs the single global PCD (points and bytes),
- block overlap: stored block points vs the global map's, and the voxel overlap ratio,
- resident map memory per provider policy (block, grid, srt, global) while following the
  localization session's ground truth (``sim:<preset>/loc``), with every load and build finished
  before the next update (points only; no registration target), and the median update time.

Writes docs/bench/maps.md.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from blockloc.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent


def _provider_run(store, backend, positions, velocities, stamps, map_cfg):
    import dataclasses

    from blockloc.maps.policies import make_policy
    from blockloc.maps.provider import MapProvider

    resident, active, update_ms, switches = [], [], [], 0
    policy = make_policy(backend, store, **dataclasses.asdict(map_cfg))
    with MapProvider(store, policy, prefetch=map_cfg.prefetch, lookahead_s=map_cfg.prefetch_lookahead_s,
                     cache_mb=map_cfg.cache_mb) as prov:  # points only: no registration target
        for p, v, t in zip(positions, velocities, stamps):
            t0 = time.perf_counter()
            m = prov.update(p, v, t)
            update_ms.append((time.perf_counter() - t0) * 1e3)
            switches += m.switched
            prov.wait_idle(60.0)
            st = prov.stats()
            resident.append(st["resident_mb"])
            active.append(st["active_points"])
        st = prov.stats()
    return {
        "resident_mb_median": float(np.median(resident)), "resident_mb_max": float(np.max(resident)),
        "active_points_median": float(np.median(active)), "active_points_max": int(np.max(active)),
        "update_ms_median": float(np.median(update_ms[1:])) if len(update_ms) > 1 else float("nan"),
        "first_update_ms": update_ms[0], "switches": switches, "loads": st["loads"],
        "evictions": st["evictions"], "late_frames": st["late_frames"],
        "prefetch_hits": st["prefetch_hits"],
    }


def main(argv: list[str] | None = None) -> int:
    from bench.__main__ import machine
    from bench._track import progress_lines
    from blockloc.config import MapConfig
    from blockloc.app.catalog import open_sequence
    from blockloc.maps.block_maps import BlockMapBuilder, write_block_map
    from blockloc.maps.grid_tiles import GridMapBuilder, tile_global_map
    from blockloc.maps.mapping import mapping_keyframes
    from blockloc.maps.pcd import write_pcd
    from blockloc.maps.summary import overlap_ratio

    ap = argparse.ArgumentParser(prog="python -m bench.maps")
    ap.add_argument("--preset", default="campus")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--max-frames", type=int, default=None, help="mapping frames to use")
    ap.add_argument("--every", type=int, default=5, help="provider: every n-th loc pose")
    ap.add_argument("--block-size", type=float, default=100.0)
    ap.add_argument("--tile-size", type=float, default=20.0)
    ap.add_argument("--cache-mb", type=float, default=256.0, help="provider LRU bound")
    ap.add_argument("--max-files", type=int, default=30000, help="skip 2 m tiling above this")
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench" / "maps.md"))
    args = ap.parse_args(argv)
    cmd = "python -m bench.maps " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    map_cfg = MapConfig(block_size_m=args.block_size, tile_size_m=args.tile_size, cache_mb=args.cache_mb)

    seq = open_sequence(f"sim:{args.preset}/map@{args.seed}")
    blocks = BlockMapBuilder(map_cfg.block_size_m, map_cfg.voxel_size_m)
    grid = GridMapBuilder(map_cfg.tile_size_m, map_cfg.voxel_size_m)
    t_scan = t_block = t_grid = 0.0
    n_raw = 0
    t0 = time.perf_counter()
    it = mapping_keyframes(seq, keyframe_distance_m=map_cfg.keyframe_distance_m,
                           keyframe_angle_deg=map_cfg.keyframe_angle_deg, progress=progress_lines("keyframes"),
                           max_frames=args.max_frames)
    while True:
        t = time.perf_counter()
        kf = next(it, None)
        t_scan += time.perf_counter() - t
        if kf is None:
            break
        n_raw += len(kf.points_map)
        t = time.perf_counter()
        blocks.add(kf.index, kf.position, kf.points_map, kf.intensity)
        t_block += time.perf_counter() - t
        t = time.perf_counter()
        grid.add(kf.points_map, kf.intensity)
        t_grid += time.perf_counter() - t
    t = time.perf_counter()
    blocks.finish()
    t_block += time.perf_counter() - t
    n_kf = grid.num_keyframes

    with tempfile.TemporaryDirectory(prefix="bench-maps-") as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        bstore = write_block_map(blocks, tmp / "block")
        t_bwrite = time.perf_counter() - t
        t = time.perf_counter()
        gpts, ginten = grid.points()
        t_grid += time.perf_counter() - t
        t = time.perf_counter()
        global_bytes = write_pcd(tmp / "global.pcd", gpts, ginten)
        t_global = time.perf_counter() - t
        t = time.perf_counter()
        gstore = tile_global_map(gpts, ginten, map_cfg.tile_size_m, tmp / "grid")
        t_tile = time.perf_counter() - t
        n_cells2 = len(np.unique(np.floor(gpts[:, :2] / 2.0).astype(np.int64), axis=0))
        tile2, t_tile2 = None, float("nan")
        if n_cells2 <= args.max_files:
            t = time.perf_counter()
            tile2 = tile_global_map(gpts, ginten, 2.0, tmp / "grid2")
            t_tile2 = time.perf_counter() - t
        total_s = time.perf_counter() - t0
        block_overlap = overlap_ratio(bstore)
        grid_overlap = overlap_ratio(gstore)

        loc = open_sequence(f"sim:{args.preset}/loc@{args.seed}").ground_truth()
        idx = np.arange(0, len(loc), args.every)
        pos = loc.positions[idx]
        stamps = loc.stamps[idx]
        vel = np.gradient(pos, stamps, axis=0)
        runs = {}
        for backend, store in (("block", bstore), ("grid", gstore), ("srt", gstore), ("global", gstore)):
            runs[backend] = _provider_run(store, backend, pos, vel, stamps, map_cfg)
        n_global = len(gpts)

    kb = lambda b: f"{b / 2**20:,.1f} MiB"  # noqa: E731
    tile_bytes = gstore.total_bytes
    lines = [
        "## Maps: building, storage, resident memory",
        "",
        f"Command: `{cmd}` — ran {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {machine()}.",
        f"Mapping session `sim:{args.preset}/map@{args.seed}`"
        + (f" (first {args.max_frames} frames)" if args.max_frames else "")
        + f": {n_kf:,} keyframes ({map_cfg.keyframe_distance_m} m / {map_cfg.keyframe_angle_deg} deg), "
        f"{n_raw:,} raw points, voxel {map_cfg.voxel_size_m} m. Single runs (a build is minutes long).",
        "",
        "| build step | time |",
        "|---|---|",
        f"| scan simulation + deskew into the map frame ({n_kf:,} keyframes) | {t_scan:.1f} s |",
        f"| block map: Algorithm 1 (S = {map_cfg.block_size_m:g} m) | {t_block:.1f} s |",
        f"| block map: writing {len(bstore.entries)} blocks | {t_bwrite:.1f} s |",
        f"| grid: binning + per-tile voxel filter | {t_grid:.1f} s |",
        f"| grid: tiling the global map at {map_cfg.tile_size_m:g} m ({len(gstore.entries)} tiles) | {t_tile:.1f} s |",
        (f"| grid: tiling the global map at 2 m ({len(tile2.entries):,} tiles) | {t_tile2:.1f} s |"
         if tile2 else f"| grid: tiling at 2 m skipped ({n_cells2:,} files > --max-files) | — |"),
        f"| writing the global PCD | {t_global:.1f} s |",
        f"| everything above | {total_s:.1f} s |",
        "",
        "| storage | points | bytes | overhead vs global PCD |",
        "|---|---|---|---|",
        f"| global map, one PCD | {n_global:,} | {kb(global_bytes)} | — |",
        f"| grid tiles {map_cfg.tile_size_m:g} m ({len(gstore.entries)} files) | {gstore.total_points:,} | "
        f"{kb(tile_bytes)} | points {100 * (gstore.total_points / n_global - 1):+.2f}%, bytes "
        f"{100 * (tile_bytes / global_bytes - 1):+.2f}% (PCD headers) |",
        (f"| grid tiles 2 m ({len(tile2.entries):,} files) | {tile2.total_points:,} | {kb(tile2.total_bytes)} | "
         f"points {100 * (tile2.total_points / n_global - 1):+.2f}%, bytes "
         f"{100 * (tile2.total_bytes / global_bytes - 1):+.2f}% |" if tile2 else
         f"| grid tiles 2 m | — | — | skipped: {n_cells2:,} files |"),
        f"| block map ({len(bstore.entries)} blocks, S = {map_cfg.block_size_m:g} m) | {bstore.total_points:,} | "
        f"{kb(bstore.total_bytes)} | points {100 * (bstore.total_points / n_global - 1):+.1f}% |",
        "",
        f"Block overlap: {100 * block_overlap:.1f}% of stored block points lie in a {map_cfg.voxel_size_m} m "
        f"voxel that another block also holds (grid tiles: {100 * grid_overlap:.2f}%). Block events: "
        + ", ".join(f"{k} {v}" for k, v in bstore.params["events"].items()) + ".",
        "",
        f"Resident map memory while following `sim:{args.preset}/loc@{args.seed}` ground truth "
        f"({len(pos):,} updates, every {args.every}th pose, {loc.path_length() / 1000:.2f} km). Local "
        f"map = the points served (16 bytes/point on disk, 12 in memory); resident = the provider's "
        f"memory (LRU entry cache bounded at {args.cache_mb:g} MB + served and spare regions), "
        f"points only (no registration target). Each update's loads finished before the next; the "
        f"median update time excludes the first (blocking) call.",
        "",
        "| policy | parameters | local map points median | max | resident MB median | max | switches | loads | evictions | update ms median | first update ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    pdesc = {"block": f"S = {map_cfg.block_size_m:g} m, hysteresis {map_cfg.switch_hysteresis_m:g} m",
             "grid": f"s = {map_cfg.tile_size_m:g} m, n = {map_cfg.grid_n}, k = {map_cfg.grid_k}",
             "srt": f"R' = {map_cfg.srt_radius_m:g} m, T = {map_cfg.srt_rebuild_period_s:g} s",
             "global": "whole map"}
    for name, r in runs.items():
        lines.append(f"| {name} | {pdesc[name]} | {r['active_points_median']:,.0f} | {r['active_points_max']:,} | "
                     f"{r['resident_mb_median']:.1f} | {r['resident_mb_max']:.1f} | "
                     f"{r['switches']} | {r['loads']} | {r['evictions']} | {r['update_ms_median']:.3f} | "
                     f"{r['first_update_ms']:.0f} |")
    lines.append("")
    out = Path(args.out)
    atomic_write_text(out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
