"""Benchmark of global initialization (block-map paper, Table I) on simulated sessions.

For N random frames of a localization session: hint = ground truth + uniform +-E m in x and y,
yaw unknown, a W x W m window. Methods on the same frames in the same run:
- ``hinted``: what ``blockloc init --pose-hint``, ``track --init-pose``, the demo and the node run:
  the place index inside the hint's window, then branch and bound where no place answers
  (``blockloc.global_init.hinted``); ``--cold K`` also times K first calls of fresh processes
  (``blockloc init ... --json``, its ``cold`` figures), once more with an empty cache;
- ``bbs+s0``: our branch and bound with the greedy initial score S0, then NDT refinement;
- ``bbs``: the same without S0 (plain BBS: threshold only from found leaves);
- ``fpfh+ransac``: open3d FPFH features + RANSAC against the map around the hint, then the same NDT.
Success: <= 0.3 m and <= 2 deg from ground truth after refinement. Also: relocalization without a
hint over the whole map on M frames (the place index, then the regions; ``--reloc-regions`` also the
regions alone), counting wrong poses reported as verified. Writes the markdown fragment
``docs/bench/global_init.md``.

    python -m bench.global_init                  # the whole fragment: small world, campus, notes
    python -m bench.global_init --frames 100 --reloc-frames 20   # one section
    python -m bench.global_init --frames 0 --reloc-frames 30 --reloc-regions   # no-hint only
    python -m bench.global_init --frames 100 --reloc-frames 0 --methods hinted --cold 5   # hinted only
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def machine() -> str:
    cpu = platform.processor() or ""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, {platform.system()}"


def ensure_map(seq_name: str, out: Path, kind: str, source: str = "builder") -> Path:
    """The map store at ``out``, built first if missing.

    source "builder": ``blockloc.maps`` (block or grid) from the mapping session and its offline-SLAM
    poses, as users build maps; "gt": a control map of 100 m grid tiles from every 5th scan of the
    mapping session placed with its ground truth (0.2 m voxels), to separate init errors from map errors.
    """
    from blockloc.config import load_config
    from blockloc.app.catalog import open_sequence
    from bench._track import progress_lines
    from blockloc.app.runs import build_map

    if (out / "manifest.json").exists():
        return out
    if source == "gt":
        from blockloc.geometry import transform_points
        from blockloc.global_init.scan_prep import deskew_rotation
        from blockloc.voxels import voxel_downsample
        from blockloc.maps.store import MapWriter

        seq = open_sequence(seq_name)
        gt = seq.ground_truth()
        parts = []
        imu = seq.imu()
        for i in range(0, len(seq), 5):
            body, t_ref = deskew_rotation(seq.frame(i), imu, seq.info)
            parts.append(transform_points(gt.interpolate(t_ref)[0], body))
        pts = voxel_downsample(np.concatenate(parts), 0.2)[0]
        keys = np.floor(pts[:, :2] / 100.0).astype(int)
        with MapWriter(out, "grid", params={"tile_size_m": 100.0, "voxel_size_m": 0.2, "source": "ground truth"}) as w:
            for k in np.unique(keys, axis=0):
                sel = np.all(keys == k, axis=1)
                w.add(f"{(k[0] + 0.5) * 100:.1f}_{(k[1] + 0.5) * 100:.1f}", pts[sel].astype(np.float32))
            w.commit()
        return out
    cfg = load_config(preset="sim")
    build_map(open_sequence(seq_name), kind, out, cfg.map, progress=progress_lines(f"{kind} map build tasks"))
    return out


def fpfh_ransac(map_pts: np.ndarray, scan_body: np.ndarray, voxel: float = 1.0, seed: int = 0,
                iterations: int = 1_000_000, confidence: float = 1.0, mutual: bool = False) -> np.ndarray:
    """T_map_body from FPFH + RANSAC (open3d), coarse; map (M, 3) map frame, scan (N, 3) body frame."""
    from blockloc.open3d_loader import open3d

    o3d = open3d()
    o3d.utility.random.seed(seed)
    reg = o3d.pipelines.registration

    def prep(p):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
        pc = pc.voxel_down_sample(voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        f = reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
        return pc, f

    src, fs = prep(scan_body)
    tgt, ft = prep(map_pts)
    res = reg.registration_ransac_based_on_feature_matching(
        src, tgt, fs, ft, mutual, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        reg.RANSACConvergenceCriteria(iterations, confidence))
    return np.asarray(res.transformation)


def kiss_matcher(scan_body: np.ndarray, map_pts: np.ndarray, voxel: float) -> tuple[np.ndarray, bool]:
    """T_map_body (4, 4) from KISS-Matcher (FPFH + graph-theoretic outlier pruning, pip ``kiss-matcher``)
    of a scan (N, 3), body frame, against map points (M, 3), map frame; and its own ``valid`` flag."""
    import kiss_matcher as km

    matcher = km.KISSMatcher(km.KISSMatcherConfig(voxel_size=voxel))
    sol = matcher.estimate(np.ascontiguousarray(scan_body, np.float32), np.ascontiguousarray(map_pts, np.float32))
    T = np.eye(4)
    T[:3, :3] = np.asarray(sol.rotation, float)
    T[:3, 3] = np.asarray(sol.translation, float).ravel()
    return T, bool(sol.valid)


def refine_ndt(map_pts: np.ndarray, scan_body: np.ndarray, T0: np.ndarray, params) -> np.ndarray:
    """T_map_body after the relocalizer's NDT (``params``: its InitParams) of a scan (N, 3), body frame,
    against map points (M, 3), map frame, from the coarse T0 (4, 4): the same refinement for every anchor."""
    from blockloc.global_init.refine import Refiner
    from blockloc.registration.engines import make_engine
    from blockloc.voxels import voxel_select

    engine = make_engine("ndt", resolution_m=params.ndt_resolution_m, num_threads=params.num_threads)
    src = scan_body[voxel_select(scan_body, params.scan_voxel_m)][: params.max_ndt_points]
    return Refiner(engine, map_pts).align(src, T0).T_map_body


BBS3D_METHOD = "3D-BBS (CPU), then NDT"


def bbs3d_rows(args, loc, frames, hints, seq, imu, gt, params, rows, methods) -> str:
    """3D-BBS on the first ``--bbs3d-frames`` hinted frames with the hints ours got; appends its rows
    (refined by the same NDT) to ``rows`` and returns the note under the table (or why it did not run)."""
    from bench import _bbs3d
    from blockloc.global_init.relocalize import pose_error
    from blockloc.global_init.scan_prep import prepare_for_init
    from blockloc.voxels import voxel_select

    try:
        _bbs3d.ensure_built()
    except _bbs3d.Unavailable as e:
        print(f"3D-BBS not run: {e}", flush=True)
        return f"3D-BBS was not run: {e}."
    lo_L, hi_L = loc.map.bounds_L()
    whole = loc.map.points_in_box(lo_L, hi_L)
    whole = whole[voxel_select(whole, 0.1)]  # its published target leaf size
    whole_L = whole @ loc.map.R_L_map.T
    z_range = (float(whole_L[:, 2].min()), float(whole_L[:, 2].max()))
    rows[BBS3D_METHOD] = []
    methods.append(BBS3D_METHOD)
    searches, claimed = [], 0
    with _bbs3d.BBS3D(whole_L, threads=os.cpu_count() or 2) as drv:
        for k, i in enumerate(frames[: args.bbs3d_frames]):
            f = seq.frame(int(i))
            scan = prepare_for_init(f, imu, seq.info)
            T_gt = gt.interpolate(scan.stamp)[0]
            c = (loc.map.R_L_map @ np.r_[hints[k], 0.0])[:2]
            t, c0, d0 = time.perf_counter(), time.process_time(), drv.cpu_s()
            T0, res = _bbs3d.localize_hinted(drv, scan.points_body, scan.gravity_body, loc.map.R_L_map, c,
                                             args.window, z_range, timeout_s=args.bbs3d_timeout)
            if res.localized:  # its claim; without it there is no pose to refine (a time-out returns none)
                c = (loc.map.R_L_map @ T0[:3, 3])[:2]
                near = loc.map.points_in_box(c - params.refine_range_m, c + params.refine_range_m)
                T = refine_ndt(near, scan.points_body, T0, params) if len(near) >= 100 else T0
            dt = time.perf_counter() - t
            cpu = time.process_time() - c0 + drv.cpu_s() - d0  # ours (levelling, NDT) and the driver's threads
            e_t, e_r = pose_error(T, T_gt) if res.localized else (math.inf, math.inf)
            rows[BBS3D_METHOD].append((int(i), e_t, e_r, dt, 0, cpu))
            searches.append(res.search_s)
            claimed += res.localized
            print(f"[3d-bbs {k + 1}] frame {i}: {e_t:.2f} m {e_r:.2f} deg {dt:.2f} s (search {res.search_s:.2f} s, "
                  f"score {res.score_pct:.2f}, localized {res.localized}, timed out {res.timed_out})", flush=True)
        prep = drv.prep_s
    return (f"3D-BBS rows: the public CPU implementation (KOKIAOKI/3d_bbs {_bbs3d.COMMIT[:7]}, built by "
            f"`bench/_bbs3d.py`), published outdoor settings (finest voxel 1 m, 6 levels, scan voxel 2 m, score "
            f"threshold 0.9, roll/pitch +-0.02 rad, yaw free), {os.cpu_count()} OpenMP threads, timeout "
            f"{args.bbs3d_timeout:g} s; the same {args.window:g} m window around the same hint over the map's height "
            f"range, then the same NDT refinement. Its voxel maps of the whole map ({len(whole):,} points at 0.1 m) "
            f"took {prep:.1f} s, once. Its own search time: median {np.median(searches):.2f} s; it claimed "
            f"success on {claimed} of {len(searches)}.")


def cold_starts(seq_name: str, map_dir: Path, frames, hints, window_m: float) -> dict:
    """First calls of fresh processes, as a user meets them: ``blockloc init --seq SEQ --frame I --map
    MAP --pose-hint X,Y --window W --json`` per frame, with the on-disk caches the warm runs left
    (pyramids, bucketed points; the place index is the store's), then the first frame once more with
    an empty ``BLOCKLOC_CACHE`` (the entries' pyramids and points rebuilt from the blocks). Returns
    {"runs": [...], "empty_cache": {...}}: each the ``cold`` figures of ``init --json`` (seconds),
    ``process_s`` (the whole command's wall clock, interpreter start included) and the error."""
    import json
    import shutil
    import subprocess
    import tempfile

    exe = [shutil.which("blockloc")] if shutil.which("blockloc") else [sys.executable, "-m", "blockloc.cli"]

    def one(i, hint, env):
        cmd = exe + ["init", "--seq", seq_name, "--frame", str(int(i)), "--map", str(map_dir), "--pose-hint",
                     f"{hint[0]:.3f},{hint[1]:.3f}", "--window", f"{window_m:g}", "--json"]
        t = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
        wall = time.perf_counter() - t
        try:
            out = json.loads(p.stdout.strip().splitlines()[-1])
        except (ValueError, IndexError):
            raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()[-500:]}") from None
        row = dict(out.get("cold", {}), frame=int(i), process_s=wall, compile_s=out.get("compile_s", 0.0),
                   verified=bool(out.get("verified")), error_m=out.get("error_m", math.inf),
                   error_deg=out.get("error_deg", math.inf), time_s=out.get("time_s"))
        print(f"[cold] frame {i}: {row}", flush=True)
        return row

    runs = [one(i, h, dict(os.environ)) for i, h in zip(frames, hints)]
    with tempfile.TemporaryDirectory(prefix="blockloc-cold-") as empty:
        fresh = one(frames[0], hints[0], dict(os.environ, BLOCKLOC_CACHE=empty))
    return {"runs": runs, "empty_cache": fresh}


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--session", default="loc")
    ap.add_argument("--seq", default=None,
                    help="the localization sequence (a --seq value, e.g. a session written by blockloc sim); "
                         "default sim:PRESET/SESSION@SEED; give --map with it")
    ap.add_argument("--map", default=None, help="map store (built from the map session if missing)")
    ap.add_argument("--map-kind", default="block")
    ap.add_argument("--map-source", default="builder", help="builder | gt (see ensure_map)")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--reloc-frames", type=int, default=20)
    ap.add_argument("--reloc-regions", action="store_true",
                    help="no-hint also with the regions alone (no place index), side by side")
    ap.add_argument("--follow-up", type=int, default=0, metavar="K",
                    help="no hint: a frame the place index leaves unverified goes on with up to K next frames "
                         "as a session's no-hint start does (app.recovery: an ambiguity tested by the next scan)")
    ap.add_argument("--kiss-matcher-frames", type=int, default=0,
                    help="the anchor KISS-Matcher on the first K no-hint frames (whole map and oracle local map)")
    ap.add_argument("--kiss-voxel", type=float, default=0.5, help="KISS-Matcher's voxel size (m)")
    ap.add_argument("--kiss-map-max-points", type=int, default=3_000_000,
                    help="KISS-Matcher against the whole map only up to this many map points")
    ap.add_argument("--bbs3d-frames", type=int, default=0,
                    help="3D-BBS (CPU, built by bench/_bbs3d.py) on the first K hinted frames, same hints")
    ap.add_argument("--bbs3d-timeout", type=float, default=10.0, help="3D-BBS's own timeout per frame (s)")
    ap.add_argument("--edge-frames", type=int, default=0,
                    help="no-hint relocalization of K frames at the edge of --edge-map (a map built from part of "
                         "the mapping drive): frames whose true position is --edge-range m from its nearest keyframe")
    ap.add_argument("--edge-map", default=None, help="the partial map of --edge-frames")
    ap.add_argument("--edge-range", default="4,15", help="MIN,MAX metres from the partial map's nearest keyframe")
    ap.add_argument("--hint-error", type=float, default=15.0)
    ap.add_argument("--window", type=float, default=40.0)
    ap.add_argument("--methods", default="hinted,bbs+s0,bbs,fpfh+ransac,bbs+s0/all",
                    help="hinted (the place index in the window, then bbs+s0), bbs+s0, bbs (plain), fpfh+ransac, "
                         "bbs+s0/all (occupancy of all points, no band); the bbs rows search the window alone")
    ap.add_argument("--cold", type=int, default=0,
                    help="hinted: also K first calls in fresh processes (blockloc init --json) on the first K "
                         "frames, and one with an empty cache")
    ap.add_argument("--fpfh-frames", type=int, default=None, help="FPFH on the first K frames only")
    ap.add_argument("--projection", default="band", help="band | all (the scan/map 2D projection)")
    ap.add_argument("--target-cache-mb", type=float, default=None,
                    help="refinement targets' per-entry statistics kept in memory, MB (InitParams.target_cache_mb; "
                         "0: every target built from its points, as before)")
    ap.add_argument("--refine-workers", type=int, default=None,
                    help="threads refining candidates side by side (InitParams.refine_workers; 1: one after "
                         "another; same results either way)")
    ap.add_argument("--out", default=str(REPO / "docs" / "bench" / "global_init.md"))
    ap.add_argument("--rng", type=int, default=0)
    ap.add_argument("--append", action="store_true", help="append to --out instead of replacing it")
    ap.add_argument("--title", default="Global initialization (block-map paper, Table I)")
    return ap


def run(argv: list[str]) -> dict:
    """One section of the fragment (one world, one map): writes or appends it to --out and returns
    its figures (per method: success rate, median errors and times, the frames that failed)."""
    ap = parser()
    args = ap.parse_args(argv)
    if args.kiss_matcher_frames > 0:
        import importlib.util

        if importlib.util.find_spec("kiss_matcher") is None:
            ap.error("--kiss-matcher-frames: needs the package kiss-matcher (pip install -e '.[bench]')")

    import logging

    logging.basicConfig(level=logging.WARNING)
    from blockloc.app.catalog import open_sequence
    from blockloc.global_init.scan_prep import prepare_for_init
    from blockloc.voxels import voxel_select
    from blockloc.errors import GlobalInitError
    from blockloc.global_init.relocalize import GlobalLocalizer, InitParams, pose_error
    from blockloc.global_init.verify import InitResult
    from blockloc.maps.store import open_map

    if args.seq is not None and args.map is None:
        ap.error("--seq: give the map it is localized in with --map")
    seq_name = args.seq or f"sim:{args.preset}/{args.session}@{args.seed}"
    cache = Path(os.environ.get("BLOCKLOC_CACHE", Path.home() / ".cache" / "blockloc")) / "bench"
    kind = "grid" if args.map_source == "gt" else args.map_kind
    # Keyed by the code that renders and builds it (as the tests' maps are): a simulator change
    # must not leave the benchmark on a map of the world before it.
    from blockloc.cache import fingerprint

    key = fingerprint("blockloc.sim", "blockloc.maps", "blockloc.datasets", params=(args.preset, args.seed, kind))
    map_dir = Path(args.map or cache / f"map_{args.preset}_{args.seed}_{kind}_{args.map_source}-{key}")
    t0 = time.perf_counter()
    ensure_map(f"sim:{args.preset}/map@{args.seed}", map_dir, args.map_kind, args.map_source)
    t_map = time.perf_counter() - t0
    store = open_map(map_dir)
    from blockloc.maps.mounting import with_map_mounting

    # as `blockloc init` and `track` see it (map.use_map_mounting): a map built with an estimated
    # LiDAR mounting localizes the same robot's scans with that mounting (none recorded: as is)
    seq = with_map_mounting(open_sequence(seq_name), store, True)
    gt = seq.ground_truth()
    imu = seq.imu()
    params = InitParams(projection=args.projection)
    if args.target_cache_mb is not None:
        params.target_cache_mb = args.target_cache_mb
    if args.refine_workers is not None:
        params.refine_workers = max(1, args.refine_workers)
    index_build_s = None
    methods = [m for m in args.methods.split(",") if m]
    if (args.reloc_frames > 0 or "hinted" in methods) and not store.files.is_remote:
        from blockloc.global_init.place_index import PLACE_INDEX_NAME, write_place_index

        if not store.has_extra(PLACE_INDEX_NAME):  # as `blockloc map build` writes it
            t0 = time.perf_counter()
            store, _ = write_place_index(map_dir, seq.info.gravity_map, params.place_index_params)
            index_build_s = time.perf_counter() - t0
    loc = GlobalLocalizer.for_store(store, seq.info.gravity_map, params)
    t0 = time.perf_counter()
    # the pyramids, the on-disk copy of the points refinement reads and the entries' refinement
    # statistics (warm figures: what an earlier process on this map left in the cache; the cold
    # first call of a fresh process is --cold's)
    loc.precompute()
    t_pre = time.perf_counter() - t0
    loc_all = None
    if "bbs+s0/all" in args.methods:
        loc_all = GlobalLocalizer.for_store(store, seq.info.gravity_map, InitParams(projection="all"))
        loc_all.map.precompute()

    rng = np.random.default_rng(args.rng)
    frames = np.sort(rng.choice(np.arange(20, len(seq)), size=min(args.frames, len(seq) - 20), replace=False))
    rows = {m: [] for m in methods}
    hints = []
    hint_search: dict[str, int] = {}  # how the hinted search ended, frames
    refused: dict[str, list] = {}  # method or search -> [(frame, why)]: scans the search refused to start from
    load_before = os.getloadavg()
    for k, i in enumerate(frames):
        f = seq.frame(int(i))
        scan = prepare_for_init(f, imu, seq.info)
        pts, t_ref, g = scan.points_body, scan.stamp, scan.gravity_body
        T_gt = gt.interpolate(t_ref)[0]  # the pose at mid-sweep, the time the result is stamped
        hint = T_gt[:2, 3] + rng.uniform(-args.hint_error, args.hint_error, 2)
        hints.append(hint)
        for m in methods:
            cpu = math.nan
            if m in ("hinted", "bbs+s0", "bbs", "bbs+s0/all"):
                L = loc_all if m == "bbs+s0/all" else loc
                L.params.use_s0 = m != "bbs"
                L.params.use_place_index = m == "hinted"  # the bbs rows: the window's branch and bound alone
                t, c = time.perf_counter(), time.process_time()
                try:
                    res = L.localize(pts, g, hint, None, args.window, 360.0)
                except GlobalInitError as exc:  # a scan the search cannot start from (too few band cells)
                    res = None
                    refused.setdefault(m, []).append((int(i), str(exc)))
                dt, cpu = time.perf_counter() - t, time.process_time() - c
                T = None if res is None or not res.verified else res.T_map_body  # not verified: a failure
                extra = 0 if res is None else res.stats.get("nodes_visited", 0)
                if m == "hinted":
                    how = "scan refused" if res is None else res.stats.get("hint_search", "?")
                    hint_search[how] = hint_search.get(how, 0) + 1
            elif m == "fpfh+ransac":
                if args.fpfh_frames is not None and k >= args.fpfh_frames:
                    continue
                t = time.perf_counter()
                c = (loc.map.R_L_map @ np.r_[hint, 0.0])[:2]
                d = 0.5 * args.window + params.max_range_m
                mp = loc.map.points_in_box(c - d, c + d)
                scan = pts[voxel_select(pts, 0.5)]
                T = refine_ndt(mp, pts, fpfh_ransac(mp, scan), params)
                dt = time.perf_counter() - t
                extra = 0
            else:
                raise SystemExit(f"unknown method {m}")
            e_t, e_r = pose_error(T, T_gt) if T is not None else (math.inf, math.inf)
            rows[m].append((int(i), e_t, e_r, dt, extra, cpu))
        # error, wall and CPU per frame: a run stopped before its table still leaves its figures
        line = "  ".join(f"{m} {rows[m][-1][1]:.2f}m {rows[m][-1][2]:.2f}deg {rows[m][-1][3]:.2f}s "
                         f"cpu {rows[m][-1][5]:.2f}s" for m in methods if rows[m]
                         and rows[m][-1][0] == int(i))
        print(f"[{k + 1}/{len(frames)}] frame {i}: {line}", flush=True)
    bbs_note = bbs3d_rows(args, loc, frames, hints, seq, imu, gt, params, rows, methods) if args.bbs3d_frames else ""

    load_after = os.getloadavg()
    cold = cold_starts(seq_name, map_dir, frames[: args.cold], hints[: args.cold], args.window) \
        if args.cold > 0 and "hinted" in methods else None

    # Relocalization without a hint over the whole map: the place index (then, when it finds
    # nothing verified, the regions), and with --reloc-regions also the regions alone.
    loc.params.use_s0 = True
    loc.params.use_place_index = True
    reloc_modes = {"place index": loc}
    if args.reloc_regions:
        reloc_modes["regions only"] = GlobalLocalizer.for_store(
            store, seq.info.gravity_map, InitParams(projection=args.projection, use_place_index=False,
                                                    max_search_s=0.0))  # the whole-map search, unbounded
    reloc = {name: [] for name in reloc_modes}
    starts: list[dict] = []  # --follow-up: the session's no-hint start from each frame
    cpu_s = {name: [] for name in reloc_modes}  # CPU time per frame (a loaded machine stretches the wall clock)
    index_load_s = None
    tcache = loc.target_cache  # its entries at the start of the no-hint frames (filled by the hinted ones)
    cache_before = (len(tcache), tcache.misses, tcache.loaded) if tcache is not None else None
    rframes = np.sort(rng.choice(np.arange(20, len(seq)), size=min(args.reloc_frames, len(seq) - 20), replace=False))
    # The anchor: KISS-Matcher against the whole map (when it fits) and, as its best case, against the
    # local map around the ground truth (what a perfect candidate generator would hand it); each result
    # refined by the same NDT. KISS-Matcher's ``valid`` is its claim of success.
    kiss_modes = []
    if args.kiss_matcher_frames > 0:
        if store.total_points <= args.kiss_map_max_points:
            kiss_modes.append("kiss-matcher, whole map")
        kiss_modes.append("kiss-matcher, local map at ground truth (oracle)")
    kiss = {name: [] for name in kiss_modes}
    whole_map = None
    for k_r, i in enumerate(rframes):
        f = seq.frame(int(i))
        scan = prepare_for_init(f, imu, seq.info)
        T_gt = gt.interpolate(scan.stamp)[0]
        for name in (kiss_modes if k_r < args.kiss_matcher_frames else []):
            if name.endswith("whole map") and whole_map is None:
                whole_map = loc.map.points_in_box(*loc.map.bounds_L())
            t = time.perf_counter()
            if name.endswith("whole map"):
                target = whole_map
            else:
                c = (loc.map.R_L_map @ T_gt[:3, 3])[:2]
                target = loc.map.points_in_box(c - params.max_range_m, c + params.max_range_m)
            T0, valid = kiss_matcher(scan.points_body, target, args.kiss_voxel)
            c = (loc.map.R_L_map @ T0[:3, 3])[:2]
            near = loc.map.points_in_box(c - params.refine_range_m, c + params.refine_range_m)
            T = refine_ndt(near, scan.points_body, T0, params) if len(near) >= 100 else T0
            dt = time.perf_counter() - t
            e_t, e_r = pose_error(T, T_gt)
            kiss[name].append((int(i), e_t, e_r, dt, 0, 0, valid, False, 0))
            print(f"[reloc {name}] frame {i}: {e_t:.2f} m {e_r:.2f} deg {dt:.2f} s valid {valid}", flush=True)
        for name, rl in reloc_modes.items():
            t_cpu = time.process_time()
            try:
                res = rl.localize(scan.points_body, scan.gravity_body, None, None, args.window, 360.0)
            except GlobalInitError as exc:  # counted as not found, as a session's start goes on to the next scan
                refused.setdefault(name, []).append((int(i), str(exc)))
                res = InitResult(None, 0.0, 0.0, [], False, time.process_time() - t_cpu, False)
            cpu_s[name].append(time.process_time() - t_cpu)  # every thread of the process
            dt = res.time_s  # search and refinement (not the index's first load)
            if name == "place index" and index_load_s is None:
                index_load_s = res.stats.get("index_load_s")
            e_t, e_r = pose_error(res.T_map_body, T_gt) if res.T_map_body is not None else (math.inf, math.inf)
            reloc[name].append((int(i), e_t, e_r, dt, res.stats.get("regions_searched", 0),
                                res.stats.get("regions", 0), bool(res.verified), bool(res.ambiguous),
                                res.stats.get("place_stage", 0)))
            print(f"[reloc {name}] frame {i}: {e_t:.2f} m {e_r:.2f} deg {dt:.2f} s cpu {cpu_s[name][-1]:.2f} s "
                  f"load {os.getloadavg()[0]:.1f} verified {res.verified} "
                  f"ambiguous {res.ambiguous} place stage {res.stats.get('place_stage')} regions "
                  f"{res.stats.get('regions_searched')}/{res.stats.get('regions')}", flush=True)
            if name == "place index" and args.follow_up > 0:
                starts.append(session_start(rl, seq, imu, gt, int(i), res, scan, e_t, e_r, dt, cpu_s[name][-1],
                                            args.follow_up))

    cmd = "python -m bench.global_init " + " ".join(shlex.quote(a) for a in argv)
    lines = [
        f"## {args.title}",
        "",
        f"Machine: {machine()}. Command: `{cmd}`.",
        (f"Data: `{seq_name}` against the `{store.kind}` map at `{map_dir}` " if args.seq else
         f"Data: simulated `{seq_name}` against the `{store.kind}` map ({args.map_source}) of `sim:{args.preset}/map@{args.seed}` ")
        +
        f"({len(store)} entries, {store.total_points:,} points); map build {t_map:.1f} s (0 if cached), "
        f"pyramids, points and refinement statistics precompute/cache load {t_pre:.2f} s.",
        f"{len(frames)} random frames; hint = ground truth + uniform +-{args.hint_error:g} m in x and y "
        f"({args.window:g} x {args.window:g} m window), yaw unknown (360 deg). Success: verified and <= 0.3 m and "
        f"<= 2 deg after NDT refinement. Projection: `{args.projection}`. Candidates refined "
        f"{'one after another' if params.refine_workers <= 1 else f'in {params.refine_workers} threads'} "
        f"(`refine_workers`). Load average (1 min) "
        f"{load_before[0]:.1f} before, {load_after[0]:.1f} after the hinted frames.",
        "",
        "Rows: `hinted` what `blockloc init --pose-hint`, `track --init-pose`, the demo and the node run: the "
        "place index's places inside the window ranked, small windows around the best searched, branch and "
        "bound over the whole window only where they give nothing verified (`blockloc/global_init/hinted.py`). "
        "`bbs+s0` ours (branch and bound on the admissible sliding-max pyramid, pruning from the "
        "greedy initial score S0); `bbs` the same without S0; `fpfh+ransac` open3d FPFH (1 m voxels) + RANSAC "
        "(1M iterations) against the map around the hint; all three then refined by the same NDT. "
        "`bbs+s0/all` projects all points (plain 2D occupancy) instead of the height band above local ground: "
        "the measurement behind the band. Times are per frame, search + refinement, warm (pyramids and the "
        "index loaded by the frames before): wall clock, and CPU time of the process (every thread).",
        "",
        "| method | frames | success | median trans. error (m) | median rot. error (deg) | median time (s) | p90 time (s) "
        "| p95 time (s) | median / p95 CPU (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    if not any(rows.values()):  # no hinted frames (--frames 0): only the no-hint table below
        lines = lines[:4]
    results = {"preset": args.preset, "map_points": int(store.total_points), "methods": {}, "reloc": None}
    for m in methods:
        r = np.array([x[1:4] for x in rows[m]], float).reshape(-1, 3)
        if not len(r):
            continue
        cpu = np.array([x[5] for x in rows[m]], float)
        ok = (r[:, 0] <= 0.3) & (r[:, 1] <= 2.0)
        results["methods"][m] = {
            "frames": len(r), "success": float(ok.mean()), "err_m": float(np.median(r[:, 0])),
            "err_deg": float(np.median(r[:, 1])), "time_s": float(np.median(r[:, 2])),
            "p95_s": float(np.percentile(r[:, 2], 95)), "cpu_s": float(np.median(cpu)),
            "cpu_p95_s": float(np.percentile(cpu, 95)),
            "nodes": float(np.median([x[4] for x in rows[m]])),
            "failed": [(x[0], x[1]) for x, good in zip(rows[m], ok) if not good]}
        cpu_txt = f"{np.median(cpu):.2f} / {np.percentile(cpu, 95):.2f}" if np.all(np.isfinite(cpu)) else "-"
        lines.append(f"| {m} | {len(r)} | {100 * ok.mean():.1f}% | {np.median(r[:, 0]):.3f} | "
                     f"{np.median(r[:, 1]):.3f} | {np.median(r[:, 2]):.2f} | {np.percentile(r[:, 2], 90):.2f} | "
                     f"{np.percentile(r[:, 2], 95):.2f} | {cpu_txt} |")
    if bbs_note:
        lines.append("\n" + bbs_note)
    nodes = [f"{m} {np.median([x[4] for x in rows[m]]):,.0f}" for m in ("hinted", "bbs+s0", "bbs", "bbs+s0/all")
             if m in rows and rows[m]]
    if nodes:
        lines.append(f"\nMedian search nodes scored: {', '.join(nodes)}.")
    if hint_search:
        results["hint_search"] = hint_search
        lines.append("\nHow the hinted searches ended: " + ", ".join(f"{n} {k}" for k, n in sorted(
            hint_search.items(), key=lambda kv: -kv[1])) + " (`stats.hint_search`).")
    if cold:
        results["cold"] = cold
        lines += cold_lines(cold, seq_name, map_dir, args.window)
    if any(reloc.values()):
        from blockloc.global_init.place_index import PLACE_INDEX_NAME

        extra = store.extras.get(PLACE_INDEX_NAME) if hasattr(store, "extras") else None
        map_bytes = sum(e.bytes for e in store.entries)
        size = (f"index {extra.bytes / 1e6:.2f} MB = {100 * extra.bytes / max(map_bytes, 1):.1f}% of the map's "
                f"{map_bytes / 1e6:.1f} MB" if extra is not None else "index built on the fly (not in the store)")
        built = f", built in {index_build_s:.1f} s" if index_build_s is not None else ""
        loaded = f", loaded in {index_load_s:.2f} s (once per process)" if index_load_s is not None else ""
        lines += ["", f"No-hint relocalization, yaw unknown, over the whole map ({size}{built}{loaded}). A frame "
                  "succeeds when the result is verified and within 0.3 m / 2 deg; **wrong verified** counts "
                  "verified results more than 1 m or 5 deg off (must be 0). Time: search and refinement per frame, "
                  f"wall clock and CPU (the process's, every thread); load average (1 min) at the end "
                  f"{os.getloadavg()[0]:.1f}.",
                  "",
                  "| search | frames | success | verified | wrong verified | ambiguous | median time (s) | p95 time (s) "
                  "| median / p95 CPU (s) |",
                  "|---|---|---|---|---|---|---|---|---|"]
        results["reloc"] = {}
        for name, rows_r in reloc.items():
            r = np.array([x[1:6] for x in rows_r], float).reshape(-1, 5)
            ver = np.array([x[6] for x in rows_r], bool)
            amb = np.array([x[7] for x in rows_r], bool)
            ok = ver & (r[:, 0] <= 0.3) & (r[:, 1] <= 2.0)
            wrong = ver & ((r[:, 0] > 1.0) | (r[:, 1] > 5.0))
            results["reloc"][name] = {
                "frames": len(r), "success": float(ok.mean()), "wrong_verified": int(wrong.sum()),
                "time_s": float(np.median(r[:, 2])), "p95_s": float(np.percentile(r[:, 2], 95)),
                "rank": float(np.median(r[:, 3])), "regions": int(r[0, 4]),
                "last_rank_share": float(np.mean(r[:, 3] == r[:, 4])),
                "failed": [(x[0], x[1]) for x, good in zip(rows_r, ok) if not good]}
            label = ("place index, then regions" if name == "place index" else
                     f"regions of {params.reloc_window_m:g} m only (cheap-score order)")
            cpu = np.asarray(cpu_s[name], float)
            results["reloc"][name].update(cpu_s=float(np.median(cpu)), cpu_p95_s=float(np.percentile(cpu, 95)))
            lines.append(f"| {label} | {len(r)} | {100 * ok.mean():.1f}% | {int(ver.sum())} | {int(wrong.sum())} | "
                         f"{int(amb.sum())} | {np.median(r[:, 2]):.2f} | {np.percentile(r[:, 2], 95):.2f} | "
                         f"{np.median(cpu):.2f} / {np.percentile(cpu, 95):.2f} |")
        for name, rows_r in kiss.items():
            r = np.array([x[1:4] for x in rows_r], float).reshape(-1, 3)
            ver = np.array([x[6] for x in rows_r], bool)
            ok = ver & (r[:, 0] <= 0.3) & (r[:, 1] <= 2.0)
            wrong = ver & ((r[:, 0] > 1.0) | (r[:, 1] > 5.0))
            near = (r[:, 0] <= 0.3) & (r[:, 1] <= 2.0)
            results["reloc"][name] = {"frames": len(r), "success": float(ok.mean()), "within": float(near.mean()),
                                      "wrong_verified": int(wrong.sum()), "time_s": float(np.median(r[:, 2])),
                                      "p95_s": float(np.percentile(r[:, 2], 95))}
            lines.append(f"| {name} (voxel {args.kiss_voxel:g} m, then NDT) | {len(r)} | {100 * ok.mean():.1f}% | "
                         f"{int(ver.sum())} (valid) | {int(wrong.sum())} | - | {np.median(r[:, 2]):.2f} | "
                         f"{np.percentile(r[:, 2], 95):.2f} | - |")
        if kiss:
            lines.append(f"\nKISS-Matcher rows: the first {args.kiss_matcher_frames} of these frames; `verified` is "
                         "its own `valid` flag, success needs it and 0.3 m / 2 deg after the same NDT refinement; "
                         "the oracle row hands it the map within "
                         f"{params.max_range_m:g} m of the true position, its best case as a candidate verifier. "
                         "Its time includes the map's FPFH features, computed per call.")
            if store.total_points > args.kiss_map_max_points:
                lines.append(f"KISS-Matcher against the whole map was not run: {store.total_points:,} points > "
                             f"{args.kiss_map_max_points:,} (`--kiss-map-max-points`).")
        if starts:
            lines += start_lines(starts, args.follow_up, results)
        if tcache is not None:
            taken = tcache.misses - cache_before[1]
            read = tcache.loaded - cache_before[2]
            results["target_cache"] = {"entries": len(tcache), "mb": tcache.nbytes / 1e6,
                                       "built_in_reloc": taken - read, "read_in_reloc": read}
            lines.append(f"\nRefinement targets assembled from per-entry voxel statistics kept in memory "
                         f"(`global_init/targets.py`, at most {params.target_cache_mb:g} MB): warm figures. At the "
                         f"first no-hint frame {cache_before[0]} of the map's {len(store)} entries were kept (the "
                         f"frames before took them); during the no-hint frames {taken} entries were taken in, "
                         f"{read} read from the on-disk cache (`GlobalLocalizer.precompute`, before the frames) and "
                         f"{taken - read} built (their cost is in those frames' times); at the end "
                         f"{len(tcache)} entries, {tcache.nbytes / 1e6:.0f} MB.")
        elif params.target_cache_mb <= 0:
            lines.append("\nRefinement targets built from the map points for each search (`--target-cache-mb 0`).")
        failed = results["reloc"]["place index"]["failed"]
        if failed:
            lines.append("\nNot found (place index): " + ", ".join(
                f"frame {i} ({e:.2f} m off)" for i, e in failed[:10]) + (" ..." if len(failed) > 10 else "") + ".")
    if refused:
        results["refused"] = refused
        lines.append("\nScans the search refused to start from (failures; a session goes on to the next scan): "
                     + "; ".join(f"{name}: " + ", ".join(f"frame {i} ({why})" for i, why in v)
                                 for name, v in refused.items()) + ".")
    if args.edge_frames > 0:
        lines += edge_section(args, seq, gt, imu, results)
    text = "\n".join(lines) + "\n"
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    if args.append and out.exists():
        text = out.read_text() + "\n" + text
    tmp.write_text(text)
    tmp.replace(out)
    print(text)
    return results


def session_start(loc, seq, imu, gt, i: int, res, scan, e_t: float, e_r: float, dt: float, cpu: float,
                  k: int) -> dict:
    """What a session's no-hint start from frame ``i`` meets (``blockloc track`` without a pose): the
    result of frame ``i`` (``res``, its errors, wall and CPU seconds) and, when it is not verified, up
    to ``k`` next frames through ``app.recovery.Recovery`` (an ambiguity is tested by the next scan,
    ``global_init.second_scan``; otherwise the search runs again). Returns the frame verified (or
    None), its errors, the frames used and the seconds summed over them."""
    from blockloc.app.recovery import GlobalInitSettings, Recovery
    from blockloc.global_init.relocalize import pose_error
    from blockloc.global_init.second_scan import Ambiguity

    out = {"frame": i, "found_at": i if res.verified else None, "err": (e_t, e_r), "frames": 1, "time_s": dt,
           "cpu_s": cpu, "second_scan": False}
    if res.verified:
        return out
    rec = Recovery(loc, GlobalInitSettings(), seq.info, imu, gt, {"map_faults": 0})
    rec.ambiguity = Ambiguity.of(res, loc.params, scan.points_body, scan.stamp, i)
    for j in range(i + 1, min(i + 1 + k, len(seq))):
        info: dict = {}
        c = time.process_time()
        T, r, stamp = rec.global_init(seq.frame(j), None, None, info)
        out["cpu_s"] += time.process_time() - c
        out["time_s"] += info["time_s"]
        out["frames"] += 1
        if T is not None:
            out["found_at"] = j
            out["err"] = pose_error(T, gt.interpolate(np.array([stamp]))[0])
            out["second_scan"] = bool(info.get("second_scan", {}).get("verified"))
            break
    print(f"[start] frame {i}: verified at {out['found_at']} ({out['frames']} frames, second scan "
          f"{out['second_scan']}) {out['err'][0]:.2f} m {out['time_s']:.2f} s", flush=True)
    return out


def start_lines(starts: list[dict], k: int, results: dict) -> list[str]:
    """The session-start row of ``--follow-up`` (:func:`session_start`)."""
    found = [s for s in starts if s["found_at"] is not None]
    ok = [s for s in found if s["err"][0] <= 0.3 and s["err"][1] <= 2.0]
    wrong = [s for s in found if s["err"][0] > 1.0 or s["err"][1] > 5.0]
    t = np.array([s["time_s"] for s in starts])
    cpu = np.array([s["cpu_s"] for s in starts])
    n = np.array([s["frames"] for s in starts])
    results["session_start"] = {"frames": len(starts), "success": len(ok) / max(len(starts), 1),
                                "wrong_verified": len(wrong), "time_s": float(np.median(t)),
                                "p95_s": float(np.percentile(t, 95)), "follow_up": k,
                                "failed": [s["frame"] for s in starts if s not in ok]}
    return ["", f"Session start (`--follow-up {k}`): from each of these frames, what `blockloc track` without a pose "
            f"meets: the frame's search, and while nothing is verified up to {k} next frames (an ambiguity tested by "
            "the next scan, registered to it: `global_init/second_scan.py`; otherwise the search again). Success: the "
            "first verified pose within 0.3 m / 2 deg; time: summed over the frames used.",
            "",
            "| start | frames | success | wrong verified | settled by a second scan | frames used (max) | median / p95 "
            "time (s) | median CPU (s) |",
            "|---|---|---|---|---|---|---|---|",
            f"| place index + up to {k} next scans | {len(starts)} | {100 * len(ok) / max(len(starts), 1):.1f}% | "
            f"{len(wrong)} | {sum(s['second_scan'] for s in starts)} | {int(n.max())} | {np.median(t):.2f} / "
            f"{np.percentile(t, 95):.2f} | {np.median(cpu):.2f} |",
            "",
            "Not started: " + (", ".join(f"frame {s['frame']}" for s in starts if s not in ok) or "none") + "."]


def cold_lines(cold: dict, seq_name: str, map_dir: Path, window_m: float) -> list[str]:
    """The cold-start paragraph and table of :func:`cold_starts`' figures."""
    runs, fresh = cold["runs"], cold["empty_cache"]
    lines = ["", f"Cold start, hinted (the first search of a fresh process): `blockloc init --seq {seq_name} --frame I "
             f"--map {map_dir} --pose-hint X,Y --window {window_m:g} --json` on the first {len(runs)} of these frames "
             "and hints, one process each; its `cold` figures (seconds: `map_open_s` the store and the localizer, "
             "`index_load_s` the place index from the store, `search_s` the first search, which reads the entries' "
             "pyramids and points from the on-disk cache, `total_s` their sum; numba compilation excluded, "
             "`compile_s`), and the whole command's wall clock (interpreter start, imports, the scan's preparation "
             "included). Last row: the first frame again with an empty `BLOCKLOC_CACHE` (the entries' pyramids and "
             "points rebuilt from the blocks).",
             "",
             "| run | frames | verified | total_s | map_open_s | index_load_s | search_s | first-call CPU (s) "
             "| compile_s | command wall (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]

    def med(rs, k):
        v = [float(r.get(k, math.nan)) for r in rs]
        return f"{np.median(v):.2f}" if len(v) > 1 else f"{v[0]:.2f}"

    for name, rs in (("warm on-disk caches (median)", runs), ("empty cache", [fresh])):
        lines.append(f"| {name} | {len(rs)} | {sum(r['verified'] for r in rs)} | {med(rs, 'total_s')} | "
                     f"{med(rs, 'map_open_s')} | {med(rs, 'index_load_s')} | {med(rs, 'search_s')} | "
                     f"{med(rs, 'first_call_cpu_s')} | {med(rs, 'compile_s')} | {med(rs, 'process_s')} |")
    worst = max(float(r["total_s"]) for r in runs)
    lines.append(f"\nSlowest cold first search with the caches: {worst:.2f} s (total_s).")
    return lines


def edge_section(args, seq, gt, imu, results: dict) -> list[str]:
    """No-hint relocalization at the map's edge (issue 42): ``--edge-frames`` frames of the session whose
    true position lies ``--edge-range`` metres from the nearest keyframe of ``--edge-map`` (a map built
    from part of the mapping drive), spread evenly over those frames; success, wrong verified (more than
    1 m or 5 deg off) and the share of the scan on mapped ground at the result. Returns the markdown lines."""
    from scipy.spatial import cKDTree

    from blockloc.global_init.place_index import PLACE_INDEX_NAME, write_place_index
    from blockloc.errors import GlobalInitError
    from blockloc.global_init.relocalize import GlobalLocalizer, InitParams, pose_error
    from blockloc.global_init.verify import InitResult
    from blockloc.global_init.scan_prep import prepare_for_init
    from blockloc.maps.store import open_map

    if not args.edge_map:
        raise SystemExit("--edge-frames needs --edge-map (a map built from part of the mapping drive)")
    lo_m, hi_m = (float(v) for v in args.edge_range.split(","))
    store = open_map(args.edge_map)
    if not store.has_extra(PLACE_INDEX_NAME):
        store, _ = write_place_index(args.edge_map, seq.info.gravity_map)
    kf = np.concatenate([e.keyframes for e in store.entries if e.keyframes is not None and len(e.keyframes)])
    tree = cKDTree(kf[:, :2])
    # the true position at each frame's stamp (mid-sweep is close enough to pick frames)
    pos = gt.interpolate(np.clip(seq.frame_stamps(), gt.stamps[0], gt.stamps[-1]))[:, :2, 3]
    d_frame, _ = tree.query(pos)
    pool = np.flatnonzero((d_frame >= lo_m) & (d_frame <= hi_m))
    pool = pool[pool >= 20]
    if len(pool) == 0:
        return ["", f"No frame of the session lies {lo_m:g}-{hi_m:g} m from the partial map's keyframes."]
    frames = pool[np.unique(np.linspace(0, len(pool) - 1, min(args.edge_frames, len(pool))).astype(int))]
    loc = GlobalLocalizer.for_store(store, seq.info.gravity_map, InitParams())
    rows = []
    for k, i in enumerate(frames):
        scan = prepare_for_init(seq.frame(int(i)), imu, seq.info)
        T_gt = gt.interpolate(scan.stamp)[0]
        d_kf = float(tree.query(T_gt[:2, 3])[0])
        t_cpu = time.process_time()
        res = loc.localize(scan.points_body, scan.gravity_body, None, None, args.window, 360.0)
        cpu = time.process_time() - t_cpu
        e_t, e_r = pose_error(res.T_map_body, T_gt) if res.T_map_body is not None else (math.inf, math.inf)
        overlap = res.candidates[0].overlap if res.candidates else float("nan")
        rows.append((int(i), d_kf, e_t, e_r, res.time_s, cpu, bool(res.verified), bool(res.ambiguous), overlap))
        print(f"[edge {k + 1}/{len(frames)}] frame {i} ({d_kf:.1f} m from the map's keyframes): {e_t:.2f} m "
              f"{e_r:.2f} deg {res.time_s:.2f} s verified {res.verified} ambiguous {res.ambiguous} "
              f"overlap {overlap:.2f}", flush=True)
    r = np.array([x[1:6] for x in rows], float)
    ver = np.array([x[6] for x in rows], bool)
    ok = ver & (r[:, 1] <= 0.3) & (r[:, 2] <= 2.0)
    wrong = ver & ((r[:, 1] > 1.0) | (r[:, 2] > 5.0))
    ov = np.array([x[8] for x in rows], float)
    results["edge"] = {"frames": len(rows), "success": float(ok.mean()), "wrong_verified": int(wrong.sum()),
                       "time_s": float(np.median(r[:, 3])), "failed": [x[0] for x, g in zip(rows, ok) if not g]}
    load = os.getloadavg()[0]
    return ["", f"No-hint relocalization at the map's edge: the map `{args.edge_map}` ({len(store)} entries, "
            f"{store.total_points:,} points, {len(kf)} keyframes: part of the mapping drive); {len(rows)} frames of "
            f"`{seq.info.name if hasattr(seq.info, 'name') else 'the session'}` whose true position is "
            f"{lo_m:g}-{hi_m:g} m from the nearest keyframe (spread evenly over them). Overlap: the share of the "
            f"scan's points on mapped ground at the best result. Load average (1 min) at the end {load:.1f}.",
            "",
            "| frames | success | verified | wrong verified | ambiguous | median overlap | median / p95 wall (s) | "
            "median CPU (s) |",
            "|---|---|---|---|---|---|---|---|",
            f"| {len(rows)} | {100 * ok.mean():.0f}% | {int(ver.sum())} | {int(wrong.sum())} | "
            f"{int(sum(x[7] for x in rows))} | {np.nanmedian(ov):.2f} | {np.median(r[:, 3]):.2f} / "
            f"{np.percentile(r[:, 3], 95):.2f} | {np.median(r[:, 4]):.2f} |",
            "",
            "Not found at the edge: " + (", ".join(f"frame {x[0]} ({x[1]:.1f} m out, {x[2]:.2f} m off)"
                                                   for x, g in zip(rows, ok) if not g) or "none") + "."]


CAMPUS_TITLE = "Campus world: hinted init and no-hint relocalization over the whole map"


def notes(small: dict, campus: dict | None) -> str:
    """The notes under the tables, written from the figures just measured."""
    m = small["methods"]
    lines = ["### Notes (global initialization)", ""]
    if "bbs+s0" in m:
        o = m["bbs+s0"]
        met = o["success"] >= 0.98 and o["err_m"] <= 0.05 and o["time_s"] <= 0.87
        lines.append(
            f"- Against the block-map paper's Table I (40 x 40 m window, i9, NCLT): ours 0.87 s / 0.05 m, plain BBS "
            f"9.82 s / 5.00 m, FPFH+RANSAC 4,036 s / 0.26 m. Here, small world, 2 cores: BBS+S0 median "
            f"{o['time_s']:.2f} s and {o['err_m']:.3f} m with {100 * o['success']:.0f}% success (issue targets "
            f">= 98%, <= 0.05 m, <= 0.87 s: {'met' if met else '**missed**'}).")
    if "bbs" in m and "bbs+s0" in m:
        a, b = m["bbs+s0"], m["bbs"]
        lines.append(
            f"- Plain BBS: {100 * b['success']:.0f}% success, {b['err_m']:.3f} m, {b['time_s']:.2f} s, "
            f"{b['nodes']:,.0f} nodes against BBS+S0's {a['nodes']:,.0f}. The bound is admissible in both, so both find "
            "the same optimum; a depth-first search that dives best-child-first raises the threshold at its first "
            "leaves, so S0 saves few nodes here. The paper's plain-BBS failure "
            + ("does not reproduce." if b["success"] >= 0.9 else "reproduces."))
    if "fpfh+ransac" in m:
        f = m["fpfh+ransac"]
        lines.append(
            f"- FPFH+RANSAC (open3d): {100 * f['success']:.0f}% success, {f['time_s']:.2f} s median. Single sparse "
            "scans and the denser accumulated map give different descriptors.")
    if "bbs+s0/all" in m and "bbs+s0" in m:
        a, b = m["bbs+s0"], m["bbs+s0/all"]
        lines.append(
            f"- Projection: the height band above local ground (0.3-3.0 m) against an occupancy of all points: "
            f"{100 * a['success']:.0f}% vs {100 * b['success']:.0f}% success, {a['time_s']:.2f} vs {b['time_s']:.2f} s "
            f"median ({a['nodes']:,.0f} vs {b['nodes']:,.0f} nodes: with the ground kept each node sums many more "
            "scan cells).")
    for name, res in (("small world", small), ("campus", campus)):
        h = ((res or {}).get("methods") or {}).get("hinted")
        if h:
            met = h["success"] >= 0.99 and h["time_s"] <= 0.3 and h["p95_s"] <= 1.0
            lines.append(f"- Hinted ({name}, +-15 m, yaw unknown; issue 42: >= 99%, median <= 0.3 s, p95 <= 1 s "
                         f"warm): {100 * h['success']:.0f}% of {h['frames']} frames, median {h['time_s']:.2f} s, p95 "
                         f"{h['p95_s']:.2f} s, CPU {h['cpu_s']:.2f} s ({'met' if met else '**missed**'}; wall "
                         "clock depends on the machine's load, given beside the table).")
    if campus:
        c, r = campus["methods"].get("bbs+s0"), campus["reloc"]
        if c:
            lines.append(f"- Campus ({campus['map_points']:,} map points, full HDL-32E density), hinted: "
                         f"{100 * c['success']:.0f}% of {c['frames']} frames, {c['err_m']:.3f} m, {c['time_s']:.2f} s median.")
        r = (r or {}).get("place index")
        if r:
            lines.append(
                f"- Campus, no hint (place index): {100 * r['success']:.0f}% of {r['frames']} frames, "
                f"{r['time_s']:.1f} s median, {r['wrong_verified']} wrong verified.")
    for name, res in (("small", small), ("campus", campus)):
        for meth, v in ((res or {}).get("methods") or {}).items():
            if v["failed"]:
                lines.append(f"- Failed frames ({name}, {meth}): " + ", ".join(
                    f"{i} ({e:.2f} m off)" for i, e in v["failed"][:8]) + (" ..." if len(v["failed"]) > 8 else "") + ".")
    lines += [
        "- Verification: NDT fitness >= 0.75 and the static structure's (>= 2 m above ground) inlier ratio >= 0.6, "
        "static-band coverage >= 0.9 and see-through <= 0.35 at the refined pose, no rival fitting as well; fitness alone "
        "accepted wrong places hundreds of metres away on campus.",
        "- Result time stamp: the pose is the body at mid-sweep (scan rotation-deskewed there with the gyro); "
        "errors are against ground truth at that time.", ""]
    return "\n".join(lines)


def suite() -> int:
    """``python -m bench.global_init`` with no arguments (as ``python -m bench all`` runs it): the small
    world with every method, then the campus world (hinted and no-hint, ours only), then the notes."""
    from bench.campus import default_map_dir, ensure_map as ensure_campus_map
    from blockloc.config import load_config
    from blockloc.fileio import atomic_write_text

    small = run([])
    cfg = load_config("sim", overrides={"map": {"block_size_m": 100.0}})
    campus_map = default_map_dir("campus", 1, cfg.map)  # the store bench.campus tracks in: built once
    ensure_campus_map("campus", 1, campus_map, cfg.map)
    campus = run(["--preset", "campus", "--frames", "100", "--reloc-frames", "10", "--methods", "hinted", "--cold", "3",
                  "--map", str(campus_map), "--append", "--title", CAMPUS_TITLE])
    out = REPO / "docs" / "bench" / "global_init.md"
    atomic_write_text(out, out.read_text() + "\n" + notes(small, campus))
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        return suite()
    run(argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
