"""``blockloc map build | tile | info | plot | serve | index``."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

log = logging.getLogger("blockloc")


def build_command(seqs: list[str] | None, kind: str, out: str | Path, config: str | None,
                  data_root: str | None, block_size: float | None, tile_size: float | None,
                  voxel: float | None, max_frames: int | None, overwrite: bool, *,
                  poses: list[str] | None = None, from_pcd: Path | None = None,
                  sensor_range_m: float = 60.0, cluster: str | None = None,
                  gravity: str | None = None, calibrate_mounting: bool | None = None,
                  refine_poses: bool | None = None, remove_dynamic: bool | None = None) -> None:
    """``blockloc map build``: the store, then its place index (a local store). gravity: with
    ``from_pcd``, the global map's gravity (``down|up|X,Y,Z``, default up: z up); a ``--seq``
    build takes its first sequence's. calibrate_mounting: None keeps ``map.calibrate_mounting``;
    refine_poses: None keeps ``map.refine_poses``; remove_dynamic: None keeps ``map.remove_dynamic``."""
    import dataclasses
    import sys

    from blockloc.app.runs import add_place_index, build_map_from_specs, drive_sequence_name, parse_drive
    from blockloc.commands.common import config_for, console, progress
    from blockloc.errors import MapError
    from blockloc.maps.remote import is_url
    from blockloc.maps.summary import map_summary

    seqs = list(seqs or [])
    poses = list(poses or [])
    if bool(seqs) == (from_pcd is not None):
        raise MapError("map build: give --seq SEQ (a mapping sequence) or --from-pcd GLOBAL.pcd --poses TRAJ")
    if kind not in ("block", "grid"):
        raise MapError(f"--kind {kind!r}: expected block or grid")
    check_positive(("--block-size", "block size", block_size), ("--tile-size", "tile size", tile_size),
                   ("--sensor-range", "sensor range", sensor_range_m))
    if from_pcd is not None and calibrate_mounting:
        raise MapError("--calibrate-mounting needs --seq drives (a global PCD has no scans to register)")
    if from_pcd is not None and refine_poses:
        raise MapError("--refine-poses needs --seq drives (a global PCD has no scans to register)")
    if from_pcd is not None and remove_dynamic:
        raise MapError("--remove-dynamic needs --seq drives (a global PCD has no scans to see through)")
    if from_pcd is not None:
        if len(poses) != 1 or poses[0] in ("", "-"):
            raise MapError("--from-pcd needs one --poses TRAJ (the mapping trajectory)")
        if cluster:
            raise MapError("--cluster builds from --seq drives; --from-pcd runs in this process")
        gravity_map = parse_gravity("up" if gravity is None else gravity)
    elif gravity is not None:
        raise MapError("--gravity goes with --from-pcd (a --seq build takes its sequence's gravity)")
    elif poses and len(poses) != len(seqs):
        raise MapError(f"--poses given {len(poses)} time(s) for {len(seqs)} --seq: give one "
                       "--poses per --seq, in the same order ('-': the sequence's own poses)")
    if not is_url(str(out)):  # an object store is checked by its writer (no local path to look at)
        out = Path(out)
        check_out(out, overwrite, max(MAP_BUILD_MIN_BYTES, 2 * _size(from_pcd)))
    cfg = config_for(drive_sequence_name(seqs[0]) if seqs else None, config)
    overrides = {k: v for k, v in (("block_size_m", block_size), ("tile_size_m", tile_size),
                                   ("voxel_size_m", voxel)) if v is not None}
    map_cfg = dataclasses.replace(cfg.map, **overrides)
    if from_pcd is not None:
        from blockloc.maps.from_pcd import build_map_from_global_pcd

        with progress(f"{kind} map keyframes") as report:
            store = build_map_from_global_pcd(
                from_pcd, Path(poses[0]), kind, out, sensor_range_m=sensor_range_m,
                keyframe_distance_m=map_cfg.keyframe_distance_m,
                keyframe_angle_deg=map_cfg.keyframe_angle_deg, block_size_m=map_cfg.block_size_m,
                tile_size_m=map_cfg.tile_size_m, voxel_size_m=map_cfg.voxel_size_m,
                overwrite=overwrite, progress=report)
        if not is_url(str(out)):  # the place index goes with every local map (as below)
            store = add_place_index(out, gravity_map, cfg)
        print_summary(map_summary(store), console())
        return
    from blockloc.maps.build_tasks import drive_info, forget_drives
    from blockloc.maps.distributed import open_executor

    drives = [parse_drive(s, poses[i] if poses and poses[i] not in ("", "-") else None,
                          data_root=data_root, dataset_cfg=cfg.dataset, max_frames=max_frames)
              for i, s in enumerate(seqs)]
    if not is_url(str(out)):  # the place index below needs the first drive's gravity: read it from
        # the drive as the build opens it (opening it again after the build, as before, read
        # its data twice and gave each of its warnings twice)
        gravity_map = drive_info(drives[0]).gravity_map
        if cluster:  # the workers open their own: none kept here meanwhile
            forget_drives(drives[:1])
    with open_executor(cluster) as ex:
        if cluster:
            link = ex.dashboard_link
            print(f"dask: {ex.description}; dashboard "
                  + (link if link else "not available (it needs the bokeh package)"),
                  file=sys.stderr, flush=True)
        with progress(f"{kind} map build tasks") as report:
            store = build_map_from_specs(drives, kind, out, map_cfg, overwrite=overwrite,
                                         progress=report, executor=ex,
                                         calibrate_mounting=calibrate_mounting, refine_poses=refine_poses,
                                         remove_dynamic=remove_dynamic)
    if not is_url(str(out)):  # the place index (no-hint relocalization) goes with a local map
        store = add_place_index(out, gravity_map, cfg)
    print_summary(map_summary(store), console())


#: Free space a map build needs at least (a store of the tiny test drive is ~1 MiB; a build
#: from a global PCD needs about the PCD's size: every point lands in some tile or block).
MAP_BUILD_MIN_BYTES = 16 * 2**20


def check_out(out: Path, overwrite: bool, need_bytes: int = MAP_BUILD_MIN_BYTES) -> None:
    """Before any work: ``--out`` is absent, or ``--overwrite`` is given and it is a map store
    blockloc made holding no other file (or an empty directory); its folder is writable with
    ``need_bytes`` free, and no other blockloc run uses it: MapError naming it otherwise."""
    from blockloc.errors import BlocklocError, MapError
    from blockloc.fileio import MAP_STORE, check_replaceable
    from blockloc.outdir import claim_output

    if out.exists() and not overwrite:
        raise MapError(f"--out {out}: already exists (choose another --out, or --overwrite to replace the map there)")
    try:
        check_replaceable(out, "--out", MAP_STORE, "a map store")
    except BlocklocError as exc:
        raise MapError(f"{exc}; --overwrite replaces only a map store") from None
    claim_output(out, "--out", need_bytes=need_bytes)


def _size(path: Path | None) -> int:
    """Bytes of an input file (0 when absent: its reader names it)."""
    try:
        return Path(path).stat().st_size if path is not None else 0
    except OSError:
        return 0


def check_positive(*options: tuple[str, str, float | None]) -> None:
    """MapError naming the first (option, what, value) whose value is given and is not a positive
    number of metres (before any work)."""
    import math

    from blockloc.errors import MapError

    for option, what, value in options:
        if value is not None and not (value > 0 and math.isfinite(value)):
            raise MapError(f"{option} {value:g}: expected a positive {what} in metres")


def tile_command(global_pcd: Path, tile_size: float, out: Path, overwrite: bool) -> None:
    from blockloc.commands.common import console, progress
    from blockloc.maps.grid_tiles import tile_pcd_file
    from blockloc.maps.summary import map_summary

    check_positive(("--tile-size", "tile size", tile_size))
    check_out(out, overwrite, max(MAP_BUILD_MIN_BYTES, 2 * _size(global_pcd)))
    with progress("tiles") as report:
        store = tile_pcd_file(global_pcd, tile_size, out, overwrite=overwrite, progress=report)
    print_summary(map_summary(store), console())


def info_command(map_path: str, json_out: bool, quick: bool) -> None:
    from blockloc.commands.common import console
    from blockloc.commands.lifelong import history_lines, history_records
    from blockloc.maps.store import open_map
    from blockloc.maps.summary import map_summary

    summary = map_summary(open_map(map_path), with_overlap=not quick)
    if json_out:
        print(json.dumps({**summary, "versions": history_records(map_path)}))
    else:
        print_summary(summary, console())
        for line in history_lines(map_path):  # lifelong maps: the version history
            print(line)


def plot_command(map_path: str, seq: str | None, out: Path | None, data_root: str | None) -> None:
    from blockloc.fileio import check_figure_path
    from blockloc.maps.plot import plot_map
    from blockloc.maps.store import open_map

    png = check_figure_path(out or Path(str(map_path).rstrip("/") + ".png"), "--out")  # before any work
    from blockloc.fileio import is_blockloc_figure
    from blockloc.outdir import check_file_replaceable, check_writable

    check_writable(png, "--out")  # a read-only mount, a folder not the user's: said now, naming --out
    check_file_replaceable(png, "--out", is_blockloc_figure, "the figures")
    store = open_map(map_path)
    traj = None
    if seq:
        from blockloc.commands.common import config_for
        from blockloc.app.catalog import open_sequence

        s = open_sequence(seq, data_root=data_root, dataset_cfg=config_for(seq, None).dataset)
        traj = s.ground_truth() or s.mapping_poses()
    print(str(plot_map(store, png, traj)))


def serve_command(map_path: Path, host: str, port: int) -> None:
    import sys

    from blockloc.maps.server import serve

    def ready(url: str, stores: list) -> None:
        for s in stores:
            print(f"serving {url}/{s + '/' if s else ''}", file=sys.stderr)
        print("press Ctrl-C to stop", file=sys.stderr, flush=True)

    from blockloc.commands.common import Interrupted

    signum = serve(map_path, host, port, on_ready=ready)
    # stopped as every command is stopped: exit 130 (Ctrl-C) / 143 (SIGTERM), one line
    raise Interrupted("map server stopped", exit_code=128 + int(signum))


def mounting_lines(params: dict) -> list[tuple[str, str]]:
    """(drive, which LiDAR mounting the map was built with and where it came from) for each drive
    of a map's manifest parameters: estimated (from how many pairs, how far from the nominal),
    nominal (not estimated, or the estimate failed: why) or LiDAR poses (nothing to estimate). A
    map built before builds recorded ``mounting_source`` names only its estimates."""
    estimates = params.get("mounting") or {}
    sources = params.get("mounting_source") or {}
    lines = []
    for drive in dict.fromkeys([*sources, *estimates]):
        m = estimates.get(drive)
        if m is not None:
            axes = m.get("translation_estimated", "xyz")  # a build before issue 41 took all three
            what = (f"estimated from {m['used']} of {m['pairs']} keyframe pairs, rotation "
                    f"{m['rotation_deg']} deg, translation {m['translation_m']} m from the nominal "
                    "(body frame)")
            if axes != "xyz":  # the drive did not determine every axis (blockloc.maps.mounting)
                u = ", ".join("-" if v is None else f"{1000 * v:.0f}" for v in m["translation_uncertainty_m"])
                kept = ", ".join(a for a in "xyz" if a not in axes)
                what += (f"; translation nominal on body {kept} (the drive determines x, y, z to {u} mm, "
                         f"not {1000 * m['translation_tolerance_m']:.0f} mm)")
            if m.get("refined_with_poses"):
                what += "; then rotation and body x translation estimated again with the refined poses"
            lines.append((drive, what))
            continue
        src = sources[drive]
        if src.get("source") == "lidar poses":
            lines.append((drive, "the sequence's own (its poses are the LiDAR's: nothing to estimate)"))
        else:
            lines.append((drive, "nominal, the sequence's own" + (f" ({src['reason']})" if "reason" in src else "")))
    return lines


def print_summary(summary: dict[str, Any], console) -> None:
    from rich.table import Table

    t = Table(title=f"{summary['kind']} map {summary['path']}", show_header=False)
    t.add_column("", style="bold")
    t.add_column("")
    unit = "blocks" if summary["kind"] == "block" else "tiles"
    t.add_row(unit, f"{summary['entries']:,}")
    t.add_row("points", f"{summary['points']:,}")
    t.add_row("bytes", f"{summary['bytes']:,} ({summary['bytes'] / 2**20:.1f} MiB, headers "
                       f"{summary['header_overhead_pct']:.2f}%)")
    ppe = summary["points_per_entry"]
    t.add_row(f"points per {unit[:-1]}", f"min {ppe['min']:,}  median {ppe['median']:,.0f}  "
                                         f"max {ppe['max']:,}")
    t.add_row("bounds", f"{summary['bounds_min']} .. {summary['bounds_max']}")
    if "overlap_ratio" in summary:
        t.add_row("overlap", f"{100 * summary['overlap_ratio']:.1f}% of stored points repeat "
                             "another entry's")
    params = {k: v for k, v in summary["parameters"].items() if not isinstance(v, (dict, list))}
    t.add_row("parameters", ", ".join(f"{k}={v}" for k, v in params.items()))
    for drive, text in mounting_lines(summary["parameters"]):
        t.add_row("LiDAR mounting", f"{drive}: {text}")
    for drive, r in (summary["parameters"].get("pose_refinement") or {}).items():
        t.add_row("mapping poses", f"{drive}: " + (
            f"as given ({r['skipped']})" if "skipped" in r else
            f"refined against the drive's scans ({r['odometry_pairs']} neighbour and {r['loop_pairs']} "
            f"revisit pairs), moved {r['shift_median_m']} m median, {r['shift_max_m']} m at most"))
    rd = summary["parameters"].get("remove_dynamic")
    if rd:
        raw = max(int(rd.get("raw_points", 0)), 1)
        t.add_row("moving objects", f"left out: {rd['moving_points']:,} of {rd.get('raw_points', 0):,} keyframe "
                                    f"points ({100 * rd['moving_points'] / raw:.1f}%; voxel {rd['voxel_m']} m, "
                                    f"{rd['context_keyframes']} keyframes each side as evidence)")
    skipped = summary["parameters"].get("skipped_keyframes") or []
    if skipped:  # scans a build could not read: counted and named (also in the manifest)
        t.add_row("skipped keyframes", f"{len(skipped)}: " + "; ".join(
            f"{k['sequence']} frame {k['frame']} ({k['error']})" for k in skipped[:3])
            + (f"; and {len(skipped) - 3} more (see manifest.json)" if len(skipped) > 3 else ""))
    if summary["legacy_layout"]:
        t.add_row("layout", "released block-map layout (no manifest, no checksums)")
    console.print(t)


# ----------------------------------------------------------------------------- map index
GRAVITY_WORDS = {"down": (0.0, 0.0, 9.81), "up": (0.0, 0.0, -9.81)}


def parse_gravity(text: str):
    """``down`` (the map's z axis points down: NCLT, the simulator), ``up`` or ``X,Y,Z`` (m/s^2)
    -> gravity (3,) in the map frame; MapError naming --gravity otherwise."""
    import numpy as np

    from blockloc.errors import MapError

    word = text.strip().lower()
    if word in GRAVITY_WORDS:
        return np.array(GRAVITY_WORDS[word])
    try:
        g = np.array([float(v) for v in word.split(",")])
    except ValueError:
        g = np.zeros(0)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-6:
        raise MapError(f"--gravity {text!r}: expected down, up or X,Y,Z (a non-zero vector, map frame, m/s^2)")
    return g


def index_command(map_path: str, gravity: str | None, config: str | None, precompute: bool = False) -> None:
    """``blockloc map index MAP``: (re)build the place index of an existing local map store.
    Gravity: ``--gravity``, else that of the sequence the map was built from (its manifest's
    ``sequence``). ``precompute``: then fill the global-init caches of every entry (pyramids,
    sorted points, refinement statistics) so that no later search builds them."""
    from blockloc.app.runs import add_place_index, mapping_sequence
    from blockloc.commands.common import config_for, console
    from blockloc.errors import BlocklocError, MapError
    from blockloc.maps.store import open_map

    store = open_map(map_path)
    if store.files.is_remote:
        raise MapError(f"{map_path}: a place index can be added only to a local map store")
    from blockloc.outdir import claim_output

    claim_output(Path(map_path), "MAP", need_bytes=max(MAP_BUILD_MIN_BYTES // 4, store.total_bytes // 4))
    source = mapping_sequence(store.params)
    if gravity is not None:
        g = parse_gravity(gravity)
    elif source:
        from blockloc.app.catalog import open_sequence

        try:
            g = open_sequence(str(source)).info.gravity_map
        except BlocklocError as exc:
            raise MapError(f"{map_path}: cannot open its mapping sequence {source!r} for gravity ({exc}); "
                           "give --gravity down|up|X,Y,Z") from None
    else:
        raise MapError(f"{map_path}: the manifest names no mapping sequence; give --gravity down|up|X,Y,Z")
    cfg = config_for(str(source) if source else None, config)
    store = add_place_index(map_path, g, cfg)
    from blockloc.global_init.place_index import PLACE_INDEX_NAME

    e = store.extras[PLACE_INDEX_NAME]
    console().print(f"place index of {map_path}: {e.file}, {e.bytes / 1e6:.2f} MB "
                    f"({100.0 * e.bytes / max(sum(x.bytes for x in store.entries), 1):.1f}% of the map's bytes)")
    if precompute:
        import time

        from blockloc.app.assemble import make_localizer
        from blockloc.commands.common import progress

        loc = make_localizer(store, g, cfg)  # the settings `init`, `track` and `node` search with
        t0 = time.perf_counter()
        with progress("global-init caches (entries)", len(store.entries)) as report:
            n, kept = loc.precompute(progress=report)
        console().print(f"global-init caches of {map_path}: {n} entries in {time.perf_counter() - t0:.1f} s, "
                        f"refinement statistics of {kept} on disk, under {loc.map.cache_dir} (searches with "
                        "this map's --config read them)")
