"""Benchmark on real recordings (issue 14): the BALM/Hilti walk end to end, the opencalib PCD
fixture, the NDT figures on the HDL-32E pair (quoted) and LiDAR-only tracking on the small world.

    python -m bench real                       # everything, writes docs/bench/real.md + real.png
    python -m bench.real --parts walk,init     # some parts only (development; --out elsewhere)

The walk (``<shared data>/balm_hilti_walk``, a scan folder with ``poses_T_world_lidar.tum``) is
split as ``tests/tracking/walk.py`` splits it: a block map of scans 0-88 placed with their
reference poses (every scan a keyframe, 8 m blocks), then scans 89-176 localized LiDAR-only
(a) from the reference pose at scan 89 and (b) from global init of scan 89 around a hint, yaw
unknown. Global init runs on every 4th held-out scan with hints +-8 m (uniform, seeded), yaw
unknown. Timings are taken on whatever machine runs it: the fragment records the load average.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "real.md"
NDT_FRAGMENT = ROOT / "docs" / "bench" / "ndt.md"
PARTS = ("walk", "init", "nohint", "blas", "thresholds", "fixture", "sim")
THRESHOLD_SEED = 100  # hints of the threshold study: another draw than the init runs' (--seed)
TOL_M, TOL_DEG = 0.3, 2.0  # global init success (the issue's, and bench.global_init's)
RPE_DELTAS_M = (1.0, 5.0, 10.0)  # the held-out half is ~37 m long
OPENCALIB_DIR = "opencalib_car5"


# --------------------------------------------------------------------------- small helpers


def init_frames(start: int, stop: int, every: int) -> list[int]:
    """Scans start, start+every, ... below stop (the held-out scans global init is run on)."""
    return list(range(start, stop, every))


def draw_hints(ref_xy: np.ndarray, max_error_m: float, seed: int) -> np.ndarray:
    """(N, 2) hints: each reference position (N, 2), map frame, m, plus a uniform offset in
    [-max_error_m, max_error_m] on x and on y, from a generator seeded with ``seed``."""
    rng = np.random.default_rng(seed)
    ref_xy = np.asarray(ref_xy, float).reshape(-1, 2)
    return ref_xy + rng.uniform(-max_error_m, max_error_m, ref_xy.shape)


def init_outcome(verified: bool, err_m: float, err_deg: float) -> str:
    """'ok' (verified and within 0.3 m / 2 deg), 'wrong' (verified but farther: the dangerous
    answer) or 'unverified' (nothing accepted: the caller knows to try again)."""
    if not verified:
        return "unverified"
    return "ok" if err_m <= TOL_M and err_deg <= TOL_DEG else "wrong"


def stats_ms(values) -> dict:
    """Median, p90, p95 and max of a list of times (any unit; NaNs dropped)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if not len(v):
        return {"median": math.nan, "p90": math.nan, "p95": math.nan, "max": math.nan, "n": 0}
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
            "p95": float(np.percentile(v, 95)), "max": float(v.max()), "n": len(v)}


def quote_ndt(text: str) -> dict:
    """The latest ``bench.ndt`` run from its fragment's text: {"run": the command line with its
    date, "machine": the machine line, "rows": [(method, starts, median ms, within, error cm,
    error deg)]} for the alignment table's default NDT and VGICP rows."""
    run = next((ln for ln in text.splitlines() if ln.startswith("Command:")), "")
    mach = next((ln for ln in text.splitlines() if ln.startswith("Machine:")), "")
    rows = []
    for ln in text.splitlines():
        cells = [c.strip() for c in ln.strip().strip("|").split("|")]
        if len(cells) == 8 and cells[1] in ("tracking", "wide") and (
                cells[0].startswith("NDT DIRECT7, coarse-to-fine") or cells[0].startswith("small_gicp VGICP")):
            rows.append((cells[0], cells[1], cells[2], cells[5], cells[6], cells[7]))
    return {"run": run, "machine": mach, "rows": rows}


def verdict(ok: bool) -> str:
    return "met" if ok else "**missed**"


def block_footprints(keyframes: list[np.ndarray], map_xy: np.ndarray, cell_m: float = 0.5,
                     min_points: int = 5, min_area_m2: float = 4.0):
    """Where the block backend serves each block: the map's occupied cells, each labelled with the
    block of its nearest keyframe (the policy's choice, hysteresis ignored).

    keyframes: per block, (K, 2|3) keyframe positions, map frame, m. map_xy: (M, 2) map points,
    map frame, m. A cell is occupied with at least ``min_points`` points; the occupancy is closed
    (gaps of one cell filled), its holes filled, and pieces under ``min_area_m2`` dropped (stray
    returns). Returns (labels (H, W) int, -1 empty; cell-centre x (W,); cell-centre y (H,)).
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    kf = np.concatenate([np.asarray(k, float)[:, :2] for k in keyframes])
    owner = np.concatenate([np.full(len(k), i) for i, k in enumerate(keyframes)])
    lo = map_xy.min(axis=0) - 2 * cell_m
    nx, ny = (np.ceil((map_xy.max(axis=0) + 2 * cell_m - lo) / cell_m).astype(int) + 1)
    ij = np.floor((map_xy - lo) / cell_m).astype(int)
    counts = np.zeros((ny, nx), int)
    np.add.at(counts, (ij[:, 1], ij[:, 0]), 1)
    occ = ndimage.binary_fill_holes(ndimage.binary_closing(counts >= min_points, iterations=1))
    pieces, n = ndimage.label(occ)
    sizes = ndimage.sum(occ, pieces, np.arange(1, n + 1))
    occ &= np.isin(pieces, 1 + np.flatnonzero(sizes * cell_m ** 2 >= min_area_m2))
    cy, cx = np.nonzero(occ)
    xc, yc = lo[0] + (np.arange(nx) + 0.5) * cell_m, lo[1] + (np.arange(ny) + 0.5) * cell_m
    labels = np.full((ny, nx), -1, int)
    labels[cy, cx] = owner[cKDTree(kf).query(np.stack([xc[cx], yc[cy]], axis=1))[1]]
    return labels, xc, yc


def _load() -> float:
    return os.getloadavg()[0]


def _machine() -> str:
    from bench.__main__ import machine

    return machine()


# --------------------------------------------------------------------------- the walk


def _walk(cfg):
    from tests.conftest import shared_data_dir
    from tests.tracking.walk import WALK_DIR, open_walk

    return open_walk(shared_data_dir() / WALK_DIR, cfg)


def track_walk(seq, store, cfg, start: int, stop: int, mode: str, hint=None) -> dict:
    """Localize scans start..stop-1 LiDAR-only in ``store``: init ``mode`` ("gt" or "pose" with
    ``hint`` = (x, y, None)), then one ``Session.step`` per scan (scans read beforehand, so the
    reader is not timed). Per scan: the tracker's update time, its core (deskew + registration +
    smoother), wall time of the step, CPU time of this thread and of the process."""
    from blockloc.evaluation.report import evaluate_trajectories
    from blockloc.geometry import Trajectory, inv_T, rotation_angle
    from blockloc.app.assemble import build_session

    session = build_session(cfg, seq, store, backend="block", keep_estimates=True)
    load0 = _load()
    try:
        t0 = time.perf_counter()
        init = dict(session.initialize(mode, start, hint))
        init["wall_s"] = time.perf_counter() - t0
        frames = list(seq.frames(start, stop))
        ests, thread_ms, proc_ms, step_ms = [], [], [], []
        for f in frames:
            c0, p0, w0 = time.thread_time(), time.process_time(), time.perf_counter()
            ests.append(session.step(f))
            step_ms.append((time.perf_counter() - w0) * 1e3)
            thread_ms.append((time.thread_time() - c0) * 1e3)
            proc_ms.append((time.process_time() - p0) * 1e3)
        counters = dict(session.tracker.counters)
    finally:
        session.close()
    est = Trajectory(np.array([e.stamp for e in ests]), np.array([e.T_map_body for e in ests]))
    m = evaluate_trajectories(seq.ground_truth(), est, rpe_deltas_m=RPE_DELTAS_M, interpolate=False)
    d = [e.diagnostics for e in ests]
    ref = seq.ground_truth().poses[[e.index for e in ests]]
    err = np.linalg.norm(est.poses[:, :3, 3] - ref[:, :3, 3], axis=1)
    statuses = {s: sum(x.status == s for x in d) for s in sorted({x.status for x in d})}
    P = seq.ground_truth().poses

    def turn(i: int) -> float:  # the reference's rotation from scan i-1 to i, deg
        return float(np.degrees(rotation_angle((inv_T(P[i - 1]) @ P[i])[:3, :3]))) if i > 0 else 0.0

    def cv_miss(i: int) -> float:  # what a constant-velocity extrapolation of the reference misses at i, deg
        if i < 2:
            return 0.0
        pred = P[i - 1] @ inv_T(P[i - 2]) @ P[i - 1]
        return float(np.degrees(rotation_angle((inv_T(pred) @ P[i])[:3, :3])))
    return {
        "mode": mode, "init": init, "scans": len(ests), "statuses": statuses, "counters": counters,
        "metrics": m, "trajectory": est, "err_m": err, "worst_scan": int(ests[int(err.argmax())].index),
        "update_ms": stats_ms([x.update_ms for x in d]),
        "core_ms": stats_ms([x.deskew_ms + x.registration_ms + x.smoother_ms for x in d]),
        "registration_ms": stats_ms([x.registration_ms for x in d]),
        "smoother_ms": stats_ms([x.smoother_ms for x in d]), "map_ms": stats_ms([x.map_ms for x in d]),
        "deskew_ms": stats_ms([x.deskew_ms for x in d]),
        "rest_ms": stats_ms([x.update_ms - x.map_ms - x.deskew_ms - x.registration_ms - x.smoother_ms for x in d]),
        "switches": [(int(e.index), str(e.diagnostics.block_id)) for e in ests if e.diagnostics.switched],
        "step_ms": stats_ms(step_ms), "thread_cpu_ms": stats_ms(thread_ms), "process_cpu_ms": stats_ms(proc_ms),
        "retried": [(int(e.index), int(e.diagnostics.rotation_retries), e.diagnostics.rotation_retry)
                    for e in ests if e.diagnostics.rotation_retries],
        "not_ok": [(int(e.index), e.diagnostics.status, turn(int(e.index)), float(x), turn(int(e.index) - 1),
                    cv_miss(int(e.index))) for e, x in zip(ests, err) if e.diagnostics.status != "ok"],
        "load": (load0, _load()),
    }


class _Timed:
    """Wraps a callable and adds its wall time to ``totals[name]`` (a profile of one stage)."""

    def __init__(self, fn, totals: dict, name: str) -> None:
        self.fn, self.totals, self.name = fn, totals, name

    def __call__(self, *a, **kw):
        t0 = time.perf_counter()
        try:
            return self.fn(*a, **kw)
        finally:
            self.totals[self.name] = self.totals.get(self.name, 0.0) + time.perf_counter() - t0


def localizer(seq, store, cfg, **params):
    """The GlobalLocalizer ``blockloc init`` builds from ``cfg`` (``params`` override InitParams)."""
    from blockloc.app.assemble import init_params as make_init_params
    from blockloc.app.assemble import build_engine
    from blockloc.global_init.relocalize import GlobalLocalizer

    gi, rc = cfg.global_init, cfg.registration
    engine = build_engine(rc, resolution_m=gi.ndt_resolution_m)
    init_params = dataclasses.replace(make_init_params(gi, rc), **params)
    return GlobalLocalizer.for_store(store, seq.info.gravity_map, init_params, engine=engine)


def decide(cands: list[tuple], thresholds) -> str | None:
    """What verification with these thresholds (``blockloc.global_init.verify.Thresholds``)
    answers for one search whose every candidate was refined: cands = [(correct, fitness,
    structure fitness, converged, ndt score[, static-band coverage, see-through])] (NaN coverage /
    see-through: not judged, passes); the best candidate by NDT score among those passing
    (``verify.passes``, as ``GlobalLocalizer`` ranks verified ones) decides: 'ok' or 'wrong'; None
    when none passes (unverified)."""
    from blockloc.global_init.verify import passes

    def consistency(c):
        return (c[5], c[6]) if len(c) > 6 else (math.nan, math.nan)

    passing = [c for c in cands if passes(c[3], c[1], c[2], *consistency(c), thresholds)]
    if not passing:
        return None
    return "ok" if max(passing, key=lambda c: c[4])[0] else "wrong"


def threshold_study(seq, store, cfg, frames: list[int], hints: np.ndarray, window_m: float) -> dict:
    """Every candidate of every search refined with verification off: the fitness and
    above-ground inlier ratio of correct (within 0.3 m / 2 deg) and wrong candidates, and what the
    default and the configured thresholds would answer (``decide``)."""
    from blockloc.config import GlobalInitConfig
    from blockloc.global_init.relocalize import pose_error
    from blockloc.global_init.verify import Thresholds
    from blockloc.global_init.scan_prep import prepare_for_init

    loc = localizer(seq, store, cfg, min_fitness=0.0, min_structure_fitness=0.0, ambiguity_score_ratio=0.0)
    gt = seq.ground_truth()
    searches = []
    for i, hint in zip(frames, hints):
        scan = prepare_for_init(seq.frame(i), seq.imu(), seq.info)
        res = loc.localize(scan.points_body, scan.gravity_body, (float(hint[0]), float(hint[1])), None,
                           window_m, 360.0)
        Tg = gt.interpolate(np.array([scan.stamp]))[0]
        searches.append([(init_outcome(True, *pose_error(c.T_map_body, Tg)) == "ok", c.fitness, c.structure_fitness,
                          c.converged, c.ndt_score, c.coverage, c.see_through) for c in res.candidates])
    good = np.array([c[1:3] for s in searches for c in s if c[0]]).reshape(-1, 2)
    bad = np.array([c[1:3] for s in searches for c in s if not c[0]]).reshape(-1, 2)
    answers = {}
    for name, th in (("default", Thresholds.of(GlobalInitConfig())), ("configured", Thresholds.of(cfg.global_init))):
        a = [decide(s, th) for s in searches]
        answers[name] = {"thresholds": dataclasses.astuple(th), "ok": a.count("ok"), "wrong": a.count("wrong"),
                         "unverified": a.count(None)}
    cov_good = np.array([c[5] for s in searches for c in s if c[0]], float)
    cov_bad = np.array([c[5] for s in searches for c in s if not c[0]], float)
    see_good = np.array([c[6] for s in searches for c in s if c[0]], float)
    see_bad = np.array([c[6] for s in searches for c in s if not c[0]], float)

    def fin(a):
        return a[np.isfinite(a)]
    return {"searches": len(searches), "with_correct": sum(any(c[0] for c in s) for s in searches),
            "good_min": good.min(axis=0).tolist() if len(good) else None,
            "bad_max": bad.max(axis=0).tolist() if len(bad) else None,
            "good_n": len(good), "bad_n": len(bad), "answers": answers,
            "coverage": {"good_min": float(fin(cov_good).min()) if len(fin(cov_good)) else None,
                         "good_n": len(fin(cov_good)), "bad_max": float(fin(cov_bad).max()) if len(fin(cov_bad)) else None,
                         "bad_n": len(fin(cov_bad)),
                         "good_see_max": float(fin(see_good).max()) if len(fin(see_good)) else None,
                         "bad_see_min": float(fin(see_bad).min()) if len(fin(see_bad)) else None}}


def global_init_walk(seq, store, cfg, frames: list[int], hints: np.ndarray | None, window_m: float) -> dict:
    """Global init of each frame around its hint ((N, 2), yaw unknown) as ``blockloc init`` runs
    it (same config, engine and scan preparation), or with ``hints`` None without one (the place
    index, then the regions: ``blockloc init`` without ``--pose-hint``); per frame: outcome, errors, the time of the
    scan's preparation (leveling by its floor) and of the search, the search's own split, and
    within the refinement: cropping the map around the candidates, building the NDT target,
    aligning and verifying."""
    from blockloc.global_init.relocalize import pose_error
    from blockloc.global_init.scan_prep import prepare_for_init

    gi, rc = cfg.global_init, cfg.registration
    loc = localizer(seq, store, cfg)
    engine = loc.engine
    t0 = time.perf_counter()
    loc.map.precompute()
    precompute_s = time.perf_counter() - t0
    gt = seq.ground_truth()
    imu = seq.imu()
    # warm-up (compiled kernels loaded, the first NDT target built): not counted
    scan = prepare_for_init(seq.frame(frames[0]), imu, seq.info)
    index_s = 0.0
    if hints is None:  # the place index: built (this map has none) or loaded once, not timed
        t0 = time.perf_counter()
        _ = loc.place_index
        index_s = time.perf_counter() - t0
    loc.localize(scan.points_body, scan.gravity_body, None if hints is None else tuple(hints[0]), None,
                 window_m, 360.0)
    prof: dict = {}
    loc.map.points_in_box = _Timed(loc.map.points_in_box, prof, "crop_s")
    engine.build_target = _Timed(engine.build_target, prof, "target_s")
    engine.align = _Timed(engine.align, prof, "align_s")
    rows = []
    load0 = _load()
    for i, hint in zip(frames, hints if hints is not None else [None] * len(frames)):
        frame = seq.frame(i)
        prof.clear()
        t0 = time.perf_counter()
        scan = prepare_for_init(frame, imu, seq.info)
        t1 = time.perf_counter()
        res = loc.localize(scan.points_body, scan.gravity_body,
                           None if hint is None else (float(hint[0]), float(hint[1])), None, window_m, 360.0)
        t2 = time.perf_counter()
        Tg = gt.interpolate(np.array([scan.stamp]))[0]
        e_m, e_deg = pose_error(np.asarray(res.T_map_body), Tg) if res.T_map_body is not None else (math.inf, math.inf)
        st = res.stats
        rows.append({"frame": int(i), "hint_off_m": math.nan if hint is None else float(np.linalg.norm(hint - Tg[:2, 3])),
                     "place_stage": st.get("place_stage", 0), "fallback": hint is None and "regions" in st,
                     "verified": bool(res.verified), "ambiguous": bool(res.ambiguous), "err_m": e_m,
                     "err_deg": e_deg, "outcome": init_outcome(res.verified, e_m, e_deg),
                     "prep_s": t1 - t0, "search_s": t2 - t1, "total_s": t2 - t0,
                     "pyramid_s": st.get("pyramid_time_s", 0.0), "bnb_s": st.get("bnb_time_s", 0.0),
                     "refine_s": st.get("refine_time_s", 0.0), "nodes": st.get("nodes_visited", 0),
                     "angles": st.get("num_angles", 0), "fitness": float(res.fitness),
                     "candidates": len(res.candidates),
                     "coverage": res.candidates[0].coverage if res.candidates else math.nan,
                     "see_through": res.candidates[0].see_through if res.candidates else math.nan, **{k: prof.get(k, 0.0) for k in ("crop_s", "target_s", "align_s")}})
        print(f"  init scan {i}: {rows[-1]['outcome']} {e_m:.3f} m {e_deg:.2f} deg "
              f"{rows[-1]['total_s']:.2f} s", flush=True)
    ok = [r["outcome"] == "ok" for r in rows]
    out = {"rows": rows, "share_ok": float(np.mean(ok)), "ok": int(sum(ok)),
           "wrong": sum(r["outcome"] == "wrong" for r in rows),
           "unverified": sum(r["outcome"] == "unverified" for r in rows),
           "ambiguous": sum(r["ambiguous"] for r in rows),
           "precompute_s": precompute_s, "index_s": index_s, "load": (load0, _load()), "threads": rc.num_threads,
           "min_fitness": gi.min_fitness, "min_structure_fitness": gi.min_structure_fitness,
           "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "default")}
    for k in ("total_s", "search_s", "prep_s", "bnb_s", "refine_s", "pyramid_s", "crop_s", "target_s", "align_s"):
        out[k] = stats_ms([r[k] for r in rows])
    return out


def walk_config_handheld():
    """The config the walk runs with here: ``blockloc/presets/handheld.yaml`` plus the walk's block size
    (what ``blockloc ... --config handheld --block-size 8`` uses). Equal to
    ``tests.tracking.walk.walk_config()`` but for the global-init thresholds (and ``lidar.deskew``,
    a no-op on scans without per-point times): tests/bench/test_bench_real.py checks it."""
    from blockloc.config import load_config
    from tests.tracking.walk import BLOCK_SIZE_M

    return load_config("handheld", overrides={"map": {"block_size_m": BLOCK_SIZE_M}})


def _variant(cfg, threads: int, init_defaults: bool = False):
    """``cfg`` with ``registration.num_threads`` = threads (and the default global-init
    verification thresholds when ``init_defaults``)."""
    from blockloc.config import GlobalInitConfig

    gi = cfg.global_init
    if init_defaults:
        d = GlobalInitConfig()
        gi = dataclasses.replace(gi, min_fitness=d.min_fitness, min_structure_fitness=d.min_structure_fitness)
    return dataclasses.replace(cfg, registration=dataclasses.replace(cfg.registration, num_threads=threads),
                               global_init=gi)


INIT_KEYS = ("init_default", "init_1", "init_2", "init_blas1")


def run_walk(args, parts) -> dict:
    """Map, tracking runs and global init on the walk (whatever of it ``parts`` asks for)."""
    import tempfile

    from blockloc.maps.store import open_map
    from tests.tracking.walk import HELD_OUT, MAP_SCANS, build_walk_map

    cfg = walk_config_handheld()
    seq = _walk(cfg)
    ref = seq.ground_truth()
    out: dict = {"config": cfg, "ref": ref, "threads": list(args.threads)}
    frames = init_frames(HELD_OUT[0], HELD_OUT[1], args.init_every)
    hints = draw_hints(ref.poses[frames][:, :2, 3], args.hint_error, args.seed)
    out["init_frames"], out["hints"] = frames, hints
    window = args.window or cfg.global_init.window_m
    main_threads = args.threads[0]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        build_walk_map(seq, Path(tmp) / "map", cfg, MAP_SCANS)
        out["map_build_s"] = time.perf_counter() - t0
        store = open_map(Path(tmp) / "map")
        if args.json is not None:  # the child run: global init only, written as JSON
            return {"init_blas1": global_init_walk(seq, store, _variant(cfg, main_threads), frames, hints, window)}
        out["map"] = {"entries": len(store.entries), "points": store.total_points,
                      "keyframes": [None if e.keyframes is None else np.asarray(e.keyframes) for e in store.entries],
                      "ids": store.ids, "bytes": store.total_bytes}
        rng = np.random.default_rng(1)
        pts = store.load_points(store.ids)
        out["map_xy"] = pts[rng.choice(len(pts), min(len(pts), 120_000), replace=False), :2]
        out["map_xy_all"] = pts[:, :2]
        if "walk" in parts:
            for n in args.threads:
                print(f"== walk, init gt, registration.num_threads={n}", flush=True)
                out[f"gt_{n}"] = track_walk(seq, store, _variant(cfg, n), *HELD_OUT, "gt")
                _say_track(out[f"gt_{n}"])
            hint = (float(hints[0, 0]), float(hints[0, 1]), None)
            print(f"== walk, init from the hint {hint[:2]}", flush=True)
            try:
                out["hint"] = track_walk(seq, store, _variant(cfg, main_threads), *HELD_OUT, "pose", hint)
                _say_track(out["hint"])
            except Exception as exc:  # noqa: BLE001 - a failed init is a result to report
                out["hint"] = {"error": f"{type(exc).__name__}: {exc}"}
                print("   ", out["hint"]["error"], flush=True)
            out["hint_xy"] = hints[0]
            print("== the whole walk from scan 0 (for comparison: its first half is the map's)", flush=True)
            out["whole"] = track_walk(seq, store, _variant(cfg, main_threads), 0, HELD_OUT[1], "gt")
            out["whole"]["held_out_rmse_m"] = float(np.sqrt(np.mean(out["whole"]["err_m"][HELD_OUT[0]:] ** 2)))
            _say_track(out["whole"])
        if "init" in parts:
            print(f"== global init on {len(frames)} scans, default verification thresholds", flush=True)
            out["init_default"] = global_init_walk(seq, store, _variant(cfg, main_threads, init_defaults=True),
                                                   frames, hints, window)
            for n in args.threads:
                print(f"== global init on {len(frames)} scans, registration.num_threads={n}", flush=True)
                out[f"init_{n}"] = global_init_walk(seq, store, _variant(cfg, n), frames, hints, window)
        if "nohint" in parts:
            nohint = init_frames(HELD_OUT[0], HELD_OUT[1], args.nohint_every)
            print(f"== global init without a hint on {len(nohint)} scans (place index, then regions)", flush=True)
            out["nohint_frames"] = nohint
            out["nohint"] = global_init_walk(seq, store, _variant(cfg, main_threads), nohint, None, window)
        if "thresholds" in parts:
            study = init_frames(HELD_OUT[0], HELD_OUT[1], 1)
            print(f"== verification thresholds: every candidate of {len(study)} searches", flush=True)
            out["thresholds"] = threshold_study(seq, store, cfg, study,
                                                draw_hints(ref.poses[study][:, :2, 3], args.hint_error,
                                                           THRESHOLD_SEED), window)
    if "init" in parts and "blas" in parts:
        out["init_blas1"] = _blas_child(args)
    return out


def _blas_child(args) -> dict:
    """The main global-init run again in a child process with ``OPENBLAS_NUM_THREADS=1`` (numpy's
    BLAS threads can only be set before numpy loads)."""
    import json
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "init.json"
        cmd = [sys.executable, "-m", "bench.real", "--parts", "init", "--threads", str(args.threads[0]),
               "--init-every", str(args.init_every), "--hint-error", str(args.hint_error), "--seed", str(args.seed),
               "--json", str(path)] + (["--window", str(args.window)] if args.window else [])
        print("== global init again with OPENBLAS_NUM_THREADS=1 (child process)", flush=True)
        subprocess.run(cmd, cwd=ROOT, check=True, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
        return json.loads(path.read_text())["init_blas1"]


def _say_track(r: dict) -> None:
    print(f"   ATE {r['metrics']['ate_trans_rmse_m']:.4f} m, statuses {r['statuses']}, update median "
          f"{r['update_ms']['median']:.1f} ms, thread CPU {r['thread_cpu_ms']['median']:.1f} ms, "
          f"counters {r['counters']}", flush=True)


# --------------------------------------------------------------------------- the other parts


def read_fixture(repeats: int = 3) -> list[dict]:
    """Each opencalib PCD read ``repeats`` times: points, rings, per-point time span, the time
    field, median read time."""
    from blockloc.datasets.pointclouds import read_point_cloud
    from tests.conftest import shared_data_dir

    root = shared_data_dir() / OPENCALIB_DIR
    files = sorted(root.rglob("*.pcd"))
    rows = []
    for p in files:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            c = read_point_cloud(p)
            times.append(time.perf_counter() - t0)
        span = float(c.time_offsets.max() - c.time_offsets.min()) if c.time_offsets is not None else math.nan
        rows.append({"file": str(p.relative_to(root)), "points": len(c), "dropped": c.num_dropped,
                     "ring_min": None if c.ring is None else int(c.ring.min()),
                     "ring_max": None if c.ring is None else int(c.ring.max()),
                     "rings": None if c.ring is None else len(np.unique(c.ring)),
                     "time_field": c.time_field, "span_s": span, "read_ms": 1e3 * float(np.median(times)),
                     "bytes": p.stat().st_size})
    return rows


def run_small_without_imu() -> dict:
    """The `small` world's loc session tracked LiDAR-only (its IMU withheld) from ground truth."""
    from blockloc.app.assemble import build_session
    from blockloc.app.catalog import open_sequence
    from blockloc.app.runs import prepare_small_world
    from blockloc.maps.store import open_map
    from tests.tracking.noimu import WithoutImu

    paths, cfg = prepare_small_world()
    seq = WithoutImu(open_sequence(paths.loc, dataset_cfg=cfg.dataset))
    session = build_session(cfg, seq, open_map(paths.block_map), backend="block")
    load0 = _load()
    res = session.run(0, None, init="gt")
    statuses = {}
    for d in res.diagnostics:
        statuses[d["status"]] = statuses.get(d["status"], 0) + 1
    return {"metrics": res.metrics, "statuses": statuses, "lidar_only": bool(session.tracker.lidar_only),
            "counters": dict(session.tracker.counters), "load": (load0, _load())}


# --------------------------------------------------------------------------- the plot


def plot_walk(walk: dict, path: Path) -> Path:
    """Top view: the map (subsampled), each block's footprint (occupied cells nearest to its
    keyframes), the reference trajectory and both estimates of the held-out half."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from blockloc.fileio import save_figure
    from tests.tracking.walk import HELD_OUT, MAP_SCANS

    fig, ax = plt.subplots(figsize=(13, 9))
    xy = walk["map_xy"]
    ax.scatter(xy[:, 0], xy[:, 1], s=0.3, color="0.45", alpha=0.45, linewidths=0, rasterized=True)
    kfs = walk["map"]["keyframes"]
    cmap = plt.get_cmap("tab10")
    if all(k is not None for k in kfs):
        labels, xc, yc = block_footprints(kfs, walk["map_xy_all"])
        for b, k in enumerate(kfs):
            color = cmap(b % 10)
            ax.contour(xc, yc, (labels == b).astype(float), levels=[0.5], colors=[color], linewidths=1.6)
            ax.plot(k[:, 0], k[:, 1], "^", color=color, ms=3, alpha=0.8)
            c = np.median(k[:, :2], axis=0)
            ax.annotate(f"block {walk['map']['ids'][b]}", c, color=color, fontsize=10, weight="bold",
                        xytext=(6, 6), textcoords="offset points")
    P = walk["ref"].positions
    ax.plot(P[MAP_SCANS[0]:MAP_SCANS[1], 0], P[MAP_SCANS[0]:MAP_SCANS[1], 1], "-", color="0.35", lw=1.0,
            label=f"reference, map scans {MAP_SCANS[0]}-{MAP_SCANS[1] - 1} (keyframes: triangles)")
    ax.plot(P[HELD_OUT[0]:HELD_OUT[1], 0], P[HELD_OUT[0]:HELD_OUT[1], 1], "k-", lw=2.2,
            label=f"reference, held-out scans {HELD_OUT[0]}-{HELD_OUT[1] - 1}")
    for key, style, name in ((f"gt_{walk['threads'][0]}", "r--", "LiDAR-only from --init gt"),
                             ("hint", "b:", "LiDAR-only from a hint")):
        r = walk.get(key)
        if r and "trajectory" in r:
            E = r["trajectory"].positions
            ax.plot(E[:, 0], E[:, 1], style, lw=1.4,
                    label=f"{name} (ATE {r['metrics']['ate_trans_rmse_m']:.3f} m)")
    g = walk.get(f"gt_{walk['threads'][0]}")
    if g and g.get("switches"):
        sw = np.array([P[i, :2] for i, _ in g["switches"]])
        ax.plot(sw[:, 0], sw[:, 1], "r*", ms=14, label="block switches (held-out, --init gt): "
                + ", ".join(f"scan {i} to {b}" for i, b in g["switches"]))
    if "hint_xy" in walk:
        h = walk["hint_xy"]
        ax.plot(h[0], h[1], "bx", ms=10, mew=2, label="the hint (scan 89)")
        ax.plot([h[0], P[HELD_OUT[0], 0]], [h[1], P[HELD_OUT[0], 1]], "b-", lw=0.6)
    ax.plot(*P[HELD_OUT[0], :2], "go", ms=7, label="scan 89")
    # the view: the bulk of the map (a few stray far returns would shrink it to a corner)
    lo = np.minimum(np.percentile(xy, 0.5, axis=0), P.min(axis=0)[:2]) - 2.0
    hi = np.maximum(np.percentile(xy, 99.5, axis=0), P.max(axis=0)[:2]) + 2.0
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (world = first scan's frame)")
    ax.set_ylabel("y [m]")
    ax.set_title(f"BALM/Hilti walk: block map of scans 0-88 ({walk['map']['entries']} blocks of 8 m, "
                 f"{walk['map']['points']:,} points), held-out half localized")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


# --------------------------------------------------------------------------- the fragment


def _f(v, fmt="{:.3f}") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)


def targets(walk: dict, sim: dict | None) -> list[tuple[str, str, str, str]]:
    """(target, measured, met/missed, where) for every issue-14 target measured this run."""
    out = []
    n = (walk.get("threads") or [0])[0]
    g = walk.get(f"gt_{n}")
    h = walk.get("hint")
    if g:
        ate = g["metrics"]["ate_trans_rmse_m"]
        out.append(("ATE translation RMSE <= 0.03 m, held-out half, `--init gt`", f"{ate:.4f} m", verdict(ate <= 0.03),
                    "walk"))
    if h and "metrics" in h:
        ate = h["metrics"]["ate_trans_rmse_m"]
        out.append(("ATE translation RMSE <= 0.03 m, held-out half, from a hint", f"{ate:.4f} m", verdict(ate <= 0.03),
                    "walk"))
    for name, r in (("`--init gt`", g), ("from a hint", h)):
        if r and "statuses" in r:
            lost = r["statuses"].get("lost", 0)
            out.append((f"no lost scan ({name}; recoveries allowed)",
                        f"{lost} lost, {r['counters'].get('recoveries', 0)} recoveries, "
                        f"{r['counters'].get('rotation_retries', 0)} scans with rotation retries",
                        verdict(lost == 0), "walk"))
        elif r:
            out.append((f"no lost scan ({name})", r.get("error", "not run"), verdict(False), "walk"))
    for key, label in ((f"init_{n}", "`handheld`"), ("init_default", "default thresholds")):
        ini = walk.get(key)
        if not ini:
            continue
        out.append((f"global init: >= 95% of hinted scans within 0.3 m and 2 deg ({label})",
                    f"{100 * ini['share_ok']:.0f}% ({ini['ok']}/{len(ini['rows'])}; {ini['wrong']} wrong verified)",
                    verdict(ini["share_ok"] >= 0.95), "walk"))
        t = ini["total_s"]["median"]
        out.append((f"global init: median time <= 1 s ({label})", f"{t:.2f} s (leveling + search)",
                    verdict(t <= 1.0), "walk"))
    if g:
        u = g["update_ms"]["median"]
        out.append(("median per-scan update <= 30 ms (~25k-point scans)",
                    f"{u:.1f} ms wall (thread CPU {g['thread_cpu_ms']['median']:.1f} ms)", verdict(u <= 30.0), "walk"))
    if sim:
        m = sim["metrics"]
        ate = m.get("ate_trans_rmse_m")
        fails = max(int(m.get("failures") or 0), sim["statuses"].get("lost", 0))
        out.append(("LiDAR-only on the small world: ATE <= 0.10 m", f"{_f(ate, '{:.4f}')} m",
                    verdict(ate is not None and ate <= 0.10), "small world, IMU withheld"))
        out.append(("LiDAR-only on the small world: no failure", f"{fails} failures",
                    verdict(fails == 0), "small world, IMU withheld"))
    return out


def fragment(args, argv, walk: dict | None, fixture: list | None, sim: dict | None, png: Path | None,
             started: str, load0: float) -> str:
    cmd = "python -m bench real" if not argv else "python -m bench.real " + " ".join(shlex.quote(a) for a in argv)
    L = ["## Real recordings (issue 14)", "",
         f"Command: `{cmd}` ({started}). Machine: {_machine()}. Load average (1 min) {load0:.1f} at the start, "
         f"{_load():.1f} at the end: the cores are shared with other processes, so every time below is an upper "
         "bound; thread CPU time (the tracking thread's own CPU, excluding waits) is the figure least "
         "sensitive to that load.", ""]
    if walk is not None:
        L += _walk_section(args, walk, png)
    if walk is not None and (_init_runs(args, walk) or walk.get("thresholds") or walk.get("nohint")):
        L += _init_section(args, walk)
    L += _ndt_section()
    if fixture is not None:
        L += _fixture_section(fixture)
    if sim is not None:
        L += _sim_section(sim)
    L += ["### Issue-14 targets", "", "| target | measured | verdict | where |", "|---|---|---|---|"]
    L += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in targets(walk or {}, sim)]
    L += [""] + _limits(args, walk or {})
    return "\n".join(L) + "\n"


def _walk_section(args, walk: dict, png: Path | None) -> list[str]:
    from tests.tracking.walk import BLOCK_SIZE_M

    cfg = walk["config"]
    mp = walk["map"]
    L = ["### The BALM/Hilti walk, held-out half, LiDAR-only", "",
         "Data: `balm_hilti_walk/` (177 real scans of a 64-beam spinning LiDAR, 2 Hz keyframes, ~25k points each, "
         "no IMU, no per-point times), opened as a scan folder with `--poses poses_T_world_lidar.tum` (the "
         "pose-graph refined reference; it agrees with scan-to-map registration to ~0.015 m on this split, so it "
         "is not surveyed truth). "
         f"Map: scans 0-88 with their reference poses, every scan a keyframe, {BLOCK_SIZE_M:g} m blocks, "
         f"{cfg.map.voxel_size_m:g} m voxels: {mp['entries']} blocks, {mp['points']:,} points, "
         f"{mp['bytes'] / 2**20:.1f} MiB, built in {walk['map_build_s']:.1f} s. "
         f"Config: `blockloc/presets/handheld.yaml` with `map.block_size_m: {BLOCK_SIZE_M:g}` (NDT "
         f"{cfg.registration.resolution_m:g} m with {cfg.registration.coarse_levels} coarse levels, scans at "
         f"{cfg.lidar.voxel_size_m:g} m, map voxels {cfg.map.voxel_size_m:g} m, block blend {cfg.map.block_blend_m:g} m; "
         "the walk tests' `walk_config()` but for the global-init verification thresholds; the map is built, "
         "as there, with every scan a keyframe), "
         "block backend. "
         f"Scans 89-176 tracked LiDAR-only (constant-velocity prior, rotated retries, recovery by global init).", ""]
    runs = [(f"`--init gt`, {_threads(n)}", walk[f"gt_{n}"]) for n in args.threads if f"gt_{n}" in walk]
    if "hint" in walk:
        runs.append((f"from a hint, {_threads(args.threads[0])}", walk["hint"]))
    if "whole" in walk:
        runs.append(("for comparison: the whole walk 0-176 from `--init gt` at scan 0 (scans 0-88 are the map's)",
                     walk["whole"]))
    L += ["| run | scans | ATE trans. RMSE (m) | max (m) | ATE rot. RMSE (deg) | RPE 1 m (m) | RPE 5 m (m) | "
          "RPE 10 m (m) | lost | recoveries | scans with rotation retries (accepted) |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in runs:
        if "metrics" not in r:
            L.append(f"| {name} | - | {r.get('error', 'not run')} | | | | | | | | |")
            continue
        m, c = r["metrics"], r["counters"]
        lost = r["statuses"].get("lost", 0)
        L.append(f"| {name} | {r['scans']} | {m['ate_trans_rmse_m']:.4f} | {r['err_m'].max():.3f} (scan "
                 f"{r['worst_scan']}) | {m['ate_rot_rmse_deg']:.3f} | {_f(m.get('rpe_1m_trans_rmse_m'), '{:.4f}')} | "
                 f"{_f(m.get('rpe_5m_trans_rmse_m'), '{:.4f}')} | {_f(m.get('rpe_10m_trans_rmse_m'), '{:.4f}')} | "
                 f"{lost} | {c.get('recoveries', 0)} | {c.get('rotation_retries', 0)} "
                 f"({c.get('rotation_recoveries', 0)}) |")
    L += ["", "Per-scan time (ms): `update` = the tracker's whole `insert_frame`, split into the map provider's "
          "call, deskew, NDT registration (with rotated retries), the smoother and the rest (scan preparation, "
          "pose covariance, bookkeeping); `core` = deskew + registration + smoother (the figure `bench.tracking` "
          "reports); `step` = the session's step, wall clock (its maximum: the first scan, which loads compiled "
          "kernels and builds the first NDT target). CPU: this thread's, and the whole process's (with the NDT "
          "kernel's worker threads and the map provider's prefetch thread).", "",
          "| run | update median / p90 | map / deskew / NDT / smoother / rest (medians) | core median / p90 | "
          "step max | thread CPU median / p90 | process CPU median | load average (start, end) |",
          "|---|---|---|---|---|---|---|---|"]
    for name, r in runs:
        if "metrics" not in r:
            continue
        u, c, t = r["update_ms"], r["core_ms"], r["thread_cpu_ms"]
        split = " / ".join(f"{r[k]['median']:.1f}" for k in ("map_ms", "deskew_ms", "registration_ms", "smoother_ms",
                                                             "rest_ms"))
        L.append(f"| {name} | {u['median']:.1f} / {u['p90']:.1f} | {split} | {c['median']:.1f} / {c['p90']:.1f} | "
                 f"{r['step_ms']['max']:.0f} | {t['median']:.1f} / {t['p90']:.1f} | {r['process_cpu_ms']['median']:.1f} | "
                 f"{r['load'][0]:.1f}, {r['load'][1]:.1f} |")
    L.append("")
    for name, r in runs:
        if "metrics" not in r:
            continue
        if r["retried"]:
            L.append(f"- {name}: rotation retries at scans " + ", ".join(
                f"{i} ({n} tried{', accepted ' + a if a else ''})" for i, n, a in r["retried"]) + ".")
        if r["not_ok"]:
            L.append(f"- {name}: scans not `ok`: " + ", ".join(
                f"{i} {st} ({e:.2f} m off; the reference turned {t0:.0f} deg into the scan before and {t:.0f} deg "
                f"into this one, a constant-velocity extrapolation of the reference misses it by {cv:.0f} deg)"
                for i, st, t, e, t0, cv in r["not_ok"]) + ".")
    h = walk.get("hint")
    if h and "init" in h:
        ini = h["init"]
        off = np.linalg.norm(walk["hint_xy"] - walk["ref"].poses[89][:2, 3])
        L.append(f"- From a hint: scan 89 initialized by global init around ({walk['hint_xy'][0]:.2f}, "
                 f"{walk['hint_xy'][1]:.2f}), {off:.2f} m from the reference, yaw unknown, in {ini.get('time_s', 0):.2f} s "
                 f"(verified {ini.get('verified')}, {_f(ini.get('error_m'))} m / {_f(ini.get('error_deg'), '{:.2f}')} deg "
                 "off the reference), then tracked like the `--init gt` run.")
    if png is not None:
        L += ["", f"![the walk: map, blocks, reference and estimates]({png.name})", "",
              "The plot: map points (grey, subsampled); each block's footprint, the occupied 0.5 m cells of the map "
              "whose nearest map keyframe belongs to that block (where the block backend serves it, hysteresis "
              "ignored; the stored block bounds reach sensor range and overlap); the map's keyframes (triangles); "
              "the reference and both estimates of the held-out half (they lie on the reference at this scale)."]
    return L + [""]


def _threads(n: int) -> str:
    return f"{n} NDT thread{'s' if n > 1 else ''}"


def _init_runs(args, walk: dict) -> list[tuple[str, dict]]:
    """(label, result) of every global-init run present, the main one (handheld, first thread
    count) first."""
    n0, t = args.threads[0], _threads
    runs = [(f"`handheld`, {t(n0)}", walk.get(f"init_{n0}"))]
    runs += [(f"`handheld`, {t(n)}", walk.get(f"init_{n}")) for n in args.threads[1:]]
    runs += [(f"`handheld`, {t(n0)}, `OPENBLAS_NUM_THREADS=1`", walk.get("init_blas1")),
             (f"default thresholds (0.75 / 0.6), {t(n0)}", walk.get("init_default"))]
    return [(name, r) for name, r in runs if r]


def _init_section(args, walk: dict) -> list[str]:
    frames = walk["init_frames"]
    gi = walk["config"].global_init
    L = ["### Global init on held-out walk scans", "",
         f"Scans {frames[0]}, {frames[1]}, ... {frames[-1]} ({len(frames)} scans, every {args.init_every}th held-out "
         f"scan); hint = reference position + uniform +-{args.hint_error:g} m on x and y (seed {args.seed}), yaw "
         f"unknown (360 deg), {args.window or gi.window_m:g} m window; the scan levelled by its floor plane (no IMU: "
         "`prepare_for_init`), then branch and bound + NDT refinement + verification, as `blockloc init` runs it. "
         "Success: verified and within 0.3 m and 2 deg of the reference; a wrong verified answer is one accepted "
         "farther away. Pyramids precomputed (not timed) and one warm-up search before the timed ones. "
         "Time = leveling + search (`blockloc init --json` reports the search only). Verification thresholds "
         f"(NDT fitness / above-ground inlier ratio): `blockloc/presets/handheld.yaml` {gi.min_fitness:g} / "
         f"{gi.min_structure_fitness:g}; the defaults 0.75 / 0.6 in the last row.", "",
         "| run | scans | within 0.3 m / 2 deg | wrong verified | unverified | median / p95 time (s) | "
         "median leveling / BnB / map crop / NDT target / NDT align (s) | load (start, end) |",
         "|---|---|---|---|---|---|---|---|"]
    for name, r in _init_runs(args, walk):
        L.append(f"| {name} | {len(r['rows'])} | {100 * r['share_ok']:.0f}% ({r['ok']}) | {r['wrong']} | "
                 f"{r['unverified']} | {r['total_s']['median']:.2f} / {r['total_s']['p95']:.2f} | "
                 + " / ".join(f"{r[k]['median']:.2f}" for k in ("prep_s", "bnb_s", "crop_s", "target_s", "align_s"))
                 + f" | {r['load'][0]:.1f}, {r['load'][1]:.1f} |")
    nh = walk.get("nohint")
    if nh:
        L.append(f"| no hint (place index, then regions), {_threads(args.threads[0])} | {len(nh['rows'])} | "
                 f"{100 * nh['share_ok']:.0f}% ({nh['ok']}) | {nh['wrong']} | {nh['unverified']} | "
                 f"{nh['total_s']['median']:.2f} / {nh['total_s']['p95']:.2f} | "
                 + " / ".join(f"{nh[k]['median']:.2f}" for k in ("prep_s", "bnb_s", "crop_s", "target_s", "align_s"))
                 + f" | {nh['load'][0]:.1f}, {nh['load'][1]:.1f} |")
    runs = _init_runs(args, walk)
    if runs:
        main = runs[0][1]
        good = [x["err_m"] for x in main["rows"] if x["outcome"] == "ok"]
        L += ["", f"Pyramid precompute (or load from the cache) {main['precompute_s']:.2f} s. Main run: median "
              f"error {np.median(good) if good else math.nan:.3f} m, median "
              f"{np.median([x['angles'] for x in main['rows']]):.0f} angles and "
              f"{np.median([x['nodes'] for x in main['rows']]):,.0f} search nodes; {main['ambiguous']} results "
              "flagged ambiguous."]
    if nh:
        good = [x["err_m"] for x in nh["rows"] if x["outcome"] == "ok"]
        stages = [x["place_stage"] for x in nh["rows"]]
        L += ["", f"No hint: every {args.nohint_every}th held-out scan ({len(nh['rows'])}), yaw unknown, the map's "
              f"place index (built for this map in {nh['index_s']:.2f} s, not timed), then the regions when no place "
              f"is verified (as `blockloc init` without `--pose-hint`). Median error {_f(np.median(good) if good else None)} m; "
              f"found at place stage 1: {sum(s == 1 for s in stages)}, later stages: {sum(s > 1 for s in stages)}, "
              f"the regions searched after the index: {sum(x['fallback'] for x in nh['rows'])} "
              f"(found there: {sum(x['fallback'] and x['outcome'] == 'ok' for x in nh['rows'])})."]
        runs = runs + [("no hint", nh)]
    for name, r in runs:
        bad = [x for x in r["rows"] if x["outcome"] != "ok"]
        if bad:
            L.append(f"Not within tolerance ({name}): " + ", ".join(
                f"scan {x['frame']} ({x['outcome']}, {_f(x['err_m'], '{:.2f}')} m / {_f(x['err_deg'], '{:.1f}')} deg, "
                f"fitness {x['fitness']:.2f}"
                + (f", coverage {x['coverage']:.2f}" if math.isfinite(x.get("coverage", math.nan)) else "")
                + (f", hint {x['hint_off_m']:.1f} m off" if math.isfinite(x['hint_off_m']) else "") + ")"
                for x in bad) + ".")
    th = walk.get("thresholds")
    if th:
        a, b = th["answers"]["default"], th["answers"]["configured"]
        L += ["", f"Where the `handheld` thresholds come from: all {th['searches']} held-out scans, hints drawn with "
              f"seed {THRESHOLD_SEED} (another draw than above), every candidate refined with verification off: "
              f"the correct pose was among the candidates in {th['with_correct']} searches; correct candidates "
              f"({th['good_n']}) had fitness >= {th['good_min'][0]:.2f} and above-ground inlier ratio >= "
              f"{th['good_min'][1]:.2f}, wrong ones ({th['bad_n']}) at most {th['bad_max'][0]:.2f} and "
              f"{th['bad_max'][1]:.2f}. The best passing candidate by NDT score would be right / wrong / none in "
              f"{a['ok']} / {a['wrong']} / {a['unverified']} searches with the defaults {a['thresholds'][0]:g} / "
              f"{a['thresholds'][1]:g} (static-band coverage >= {a['thresholds'][2]:g}, see-through <= {a['thresholds'][3]:g}), "
              f"{b['ok']} / {b['wrong']} / {b['unverified']} with {b['thresholds'][0]:g} / "
              f"{b['thresholds'][1]:g} (>= {b['thresholds'][2]:g}, <= {b['thresholds'][3]:g}). Static-band coverage, where "
              f"judged: correct candidates ({th['coverage']['good_n']}) >= {_f(th['coverage']['good_min'], '{:.2f}')}, "
              f"wrong ones ({th['coverage']['bad_n']}) <= {_f(th['coverage']['bad_max'], '{:.2f}')}; see-through: correct "
              f"<= {_f(th['coverage']['good_see_max'], '{:.2f}')}, wrong >= {_f(th['coverage']['bad_see_min'], '{:.2f}')}. The thresholds were chosen on this walk, so the rows above are not an "
              "independent test of them. Correct poses fit only part of a scan where the map (scans 0-88) covers "
              "only part of what the scan sees, as on the scans the defaults left unverified."]
    return L + [""]


def _ndt_section() -> list[str]:
    L = ["### NDT on the real HDL-32E pair (quoted, not rerun)", ""]
    if not NDT_FRAGMENT.exists():
        return L + ["`docs/bench/ndt.md` is missing: run `python -m bench ndt`.", ""]
    q = quote_ndt(NDT_FRAGMENT.read_text())
    L += [f"From `docs/bench/ndt.md`, its latest run ({q['run'].removeprefix('Command: ').rstrip('.')}; "
          f"{q['machine'].removeprefix('Machine: ').split(';')[0]}); this benchmark does not rerun `bench ndt`. "
          "A 10.8k-point scan of `hdl32e_pair/source.pcd` against `target.pcd` (in a 1M-point map), 30 starts per row, "
          "errors against `T_target_source.txt`.", "",
          "| method | starts | median time (ms) | within 5 cm / 0.5 deg | median error (cm) | median error (deg) |",
          "|---|---|---|---|---|---|"]
    L += [f"| {' | '.join(r)} |" for r in q["rows"]]
    return L + [""]


def _fixture_section(rows: list[dict]) -> list[str]:
    L = ["### Reading the opencalib fixture", "",
         "`opencalib_car5/` (real `binary_compressed` PCD, LZF; fields x y z intensity ring timestamp) read by "
         "`blockloc.datasets.pointclouds.read_point_cloud` (pypcd4 underneath); read time = median of 3 reads of "
         "the file (page cache warm after the first).", "",
         "| file | size (MB) | points | NaN dropped | rings (min-max, distinct) | time field | per-point time span (s) | "
         "read (ms) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rings = "-" if r["ring_min"] is None else f"{r['ring_min']}-{r['ring_max']} ({r['rings']})"
        L.append(f"| {r['file']} | {r['bytes'] / 1e6:.2f} | {r['points']:,} | {r['dropped']} | {rings} | "
                 f"{r['time_field'] or '-'} | {_f(r['span_s'], '{:.4f}')} | {r['read_ms']:.0f} |")
    return L + [""]


def _sim_section(sim: dict) -> list[str]:
    m = sim["metrics"]
    return ["### LiDAR-only on the simulated `small` world (IMU withheld)", "",
            "`sim:small/loc@1` through `tests/tracking/noimu.py`'s `WithoutImu` (the IMU stream empty, so the "
            f"tracker ran LiDAR-only: {'yes' if sim['lidar_only'] else 'no'}), in the small world's block map, the `sim` preset, from "
            "the first ground-truth pose.", "",
            "| frames | estimated | ATE trans. RMSE (m) | ATE rot. RMSE (deg) | RPE 10 m (m) | failures | recoveries | "
            "rejected | statuses | update median (ms) | load (start, end) |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            f"| {m.get('frames')} | {m.get('estimated')} | {_f(m.get('ate_trans_rmse_m'), '{:.4f}')} | "
            f"{_f(m.get('ate_rot_rmse_deg'))} | {_f(m.get('rpe_10m_trans_rmse_m'), '{:.4f}')} | {m.get('failures')} | "
            f"{m.get('recoveries')} | {m.get('rejected')} | "
            + ", ".join(f"{k} {v}" for k, v in sorted(sim["statuses"].items()))
            + f" | {_f(m.get('update_ms_median'), '{:.1f}')} | {sim['load'][0]:.1f}, {sim['load'][1]:.1f} |", ""]


def _limits(args, walk: dict) -> list[str]:
    """What limits the figures, from this run's own measurements."""
    L = ["### What limits the figures (measured in this run)", ""]
    g = [(n, walk[f"gt_{n}"]) for n in args.threads if f"gt_{n}" in walk]
    if g:
        L.append("- Per-scan update by `registration.num_threads`: " + "; ".join(
            f"{n}: update {r['update_ms']['median']:.1f} ms median (NDT {r['registration_ms']['median']:.1f}, smoother "
            f"{r['smoother_ms']['median']:.1f}), thread CPU {r['thread_cpu_ms']['median']:.1f} ms, process CPU "
            f"{r['process_cpu_ms']['median']:.1f} ms" for n, r in g) + ". The gap between wall and CPU time is "
            "time spent waiting for a core (see the load average).")
    w = walk.get("whole")
    if w and w.get("not_ok"):
        tc = walk["config"].tracking
        i, st, t, _, t0, cv = w["not_ok"][0]
        L.append(f"- Turn-and-stop (whole-walk run, outside the held-out half): scan {i} is {st} because the "
                 f"reference turned {t0:.0f} deg into scan {i - 1} and only {t:.0f} deg into scan {i}, so the "
                 f"constant-velocity prior predicts a rotation {cv:.0f} deg off; the rotated retries (yaw "
                 f"{', '.join(f'{v:+g}' for v in tc.rotation_retry_yaw_deg)} deg, tilt "
                 f"{', '.join(f'{v:+g}' for v in tc.rotation_retry_tilt_deg)} deg, one axis at a time) did not "
                 f"bring NDT into its basin; {len(w['not_ok'])} scans were not `ok`, "
                 f"{w['counters'].get('recoveries', 0)} recovery by global init ended it. ATE over the whole walk "
                 f"{w['metrics']['ate_trans_rmse_m']:.3f} m; its scans 89-176 alone {w['held_out_rmse_m']:.4f} m. Untried "
                 "here (tracker code, not changed): a prior that damps the angular rate after a large turn, or "
                 "retries about the last pose's orientation as well as about the prediction.")
    b, b1 = walk.get(f"init_{args.threads[0]}"), walk.get("init_blas1")
    if b and b1:
        L.append(f"- Global init's largest stage is the refinement's map crop (`StoreMap.points_in_box`): every search "
                 "loads and decodes each block the +-50 m refinement box touches (here all of them) and levels the "
                 "points with a numpy matrix product, which runs on OpenBLAS threads; on shared cores those wait for "
                 f"each other: crop median {b['crop_s']['median']:.2f} s with numpy's default BLAS threads, "
                 f"{b1['crop_s']['median']:.2f} s with `OPENBLAS_NUM_THREADS=1` (whole init {b['total_s']['median']:.2f} "
                 f"vs {b1['total_s']['median']:.2f} s).")
    for name, r in _init_runs(args, walk):
        L.append(f"- Global init, {name}: {r['total_s']['median']:.2f} s median = leveling {r['prep_s']['median']:.2f} "
                 f"+ branch and bound {r['bnb_s']['median']:.2f} + refinement {r['refine_s']['median']:.2f} (of which "
                 f"cropping the map around the candidates {r['crop_s']['median']:.2f}, building the NDT target "
                 f"{r['target_s']['median']:.2f}, NDT alignment {r['align_s']['median']:.2f}) s.")
    return L + [""]


# --------------------------------------------------------------------------- main


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma separated: {', '.join(PARTS)}")
    ap.add_argument("--threads", default="2,1", help="registration.num_threads values to run (first: the main runs)")
    ap.add_argument("--init-every", type=int, default=4)
    ap.add_argument("--nohint-every", type=int, default=1, help="no-hint global init on every Nth held-out scan")
    ap.add_argument("--hint-error", type=float, default=8.0, help="hint = reference + uniform +-E m on x and y")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--window", type=float, default=None, help="global init window, m (default: the config's)")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--json", type=Path, default=None, help=argparse.SUPPRESS)  # the BLAS child's results
    return ap


def main(argv: list[str] | None = None) -> int:
    import logging

    from blockloc.fileio import atomic_write_text

    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser().parse_args(argv)
    args.threads = [int(t) for t in args.threads.split(",") if t]
    parts = {p for p in args.parts.split(",") if p}
    unknown = parts - set(PARTS)
    if unknown:
        raise SystemExit(f"--parts: unknown {', '.join(sorted(unknown))} (expected {', '.join(PARTS)})")
    logging.basicConfig(level=logging.WARNING)
    started, load0 = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), _load()
    walk = run_walk(args, parts) if parts & {"walk", "init", "nohint", "thresholds"} else None
    if args.json is not None:
        import json

        args.json.write_text(json.dumps(walk))
        return 0
    png = None
    if walk is not None and "walk" in parts:
        png = plot_walk(walk, args.out.with_suffix(".png"))
    fixture = read_fixture() if "fixture" in parts else None
    sim = None
    if "sim" in parts:
        print("== small world, IMU withheld", flush=True)
        sim = run_small_without_imu()
    text = fragment(args, argv, walk, fixture, sim, png, started, load0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
