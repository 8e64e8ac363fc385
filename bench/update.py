"""The tracker's own per-scan update (``Estimator.insert_frame``) on the small world: its time, where
it goes, and the accuracy it keeps (issue 39: median <= 6 ms).

    python -m bench.update --work /work/acc --seeds 2,3                 # whole sessions, both seeds
    python -m bench.update --work /work/acc --seeds 2 --frames 300      # a quick re-run
    python -m bench.update ... --profile 300                            # + a cProfile split (300 scans)
    python -m bench.update ... --json after.json --before before.json   # a before/after table
    python -m bench.update ... --no-imu                                 # the LiDAR-only tracker
    python -m bench.update --seeds 2 --frames 300 --ab registration     # A/B: this round's change off in A

Each seed's world is the layout ``python -m bench.seeds`` writes: ``WORK/sS/loc`` (the localization
session) and ``WORK/sS_map`` (its block map). The session runs in this process as ``blockloc
track --init gt`` runs it (the preset that fits, the session's map), scan after scan; around every
``insert_frame`` it records the wall time (perf_counter), this thread's CPU time (thread_time:
the numba worker threads of a parallel NDT pass are not in it) and the process's CPU time
(process_time: all threads, the map provider's background loads included). The split by stage
comes from the tracker's own diagnostics (``prep_ms``, ``deskew_ms``, ``map_ms``,
``registration_ms``, ``smoother_ms``; the rest is the estimate at the stamp and bookkeeping).
ATE: position RMSE against ground truth over the frames run, no alignment, interpolated
(``blockloc eval --interpolate``'s numbers). The first ``--skip`` scans (kernel warm-up) are left
out of the times, not of the ATE.

``--before`` takes the JSON of an earlier run (e.g. the same command on another checkout: copy this
file there and run it with that checkout on PYTHONPATH) and writes both side by side.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "update.md"
STAGES = ("prep_ms", "deskew_ms", "map_ms", "registration_ms", "smoother_ms")
STAGE_NAMES = {"prep_ms": "scan prep", "deskew_ms": "prediction + deskew", "map_ms": "map provider",
               "registration_ms": "registration", "smoother_ms": "smoother", "rest_ms": "rest"}


def default_work() -> Path:
    from blockloc.cache import cache_root

    return cache_root() / "bench-seeds"


def _q(a, p) -> float:
    return float(np.percentile(a, p)) if len(a) else float("nan")


def run_seed(world: Path, map_path: Path, frames: int | None, skip: int, profile: bool,
             threads: int | None = None, no_imu: bool = False) -> dict:
    """One session through the tracker, timed per scan. Returns the figures (see module doc)."""
    import cProfile

    from blockloc.app.catalog import config_for_sequence
    from blockloc.app.runs import open_session

    seq = str(world / "loc")
    overrides: dict = {"evaluation": {"plots": False}}
    if threads:
        overrides["registration"] = {"num_threads": threads}
    if no_imu:  # the LiDAR-only tracker, as blockloc track --no-imu
        overrides["tracking"] = {"use_imu": False}
    cfg = config_for_sequence(seq, overrides=overrides)
    session = open_session(seq, cfg=cfg, map_path=str(map_path))
    tracker = session.tracker
    stop = len(session.seq) if frames is None else min(len(session.seq), frames)
    wall, thread_cpu, proc_cpu = [], [], []
    inner = tracker.insert_frame

    def timed(frame):
        c0, p0, w0 = time.thread_time(), time.process_time(), time.perf_counter()
        est = inner(frame)
        wall.append((time.perf_counter() - w0) * 1e3)
        thread_cpu.append((time.thread_time() - c0) * 1e3)
        proc_cpu.append((time.process_time() - p0) * 1e3)
        return est

    tracker.insert_frame = timed
    # the profiler's clock is the process's CPU time: on shared cores wall time mostly measures the wait
    prof = cProfile.Profile(time.process_time) if profile else None
    loads = [os.getloadavg()[0]]
    diags, stamps, poses = [], [], []
    try:
        session.initialize("gt", 0)
        for n, frame in enumerate(session.seq.frames(0, stop)):
            if prof is not None and n == skip:
                prof.enable()
            est = session.step(frame)
            diags.append(est.diagnostics)
            if est.T_map_body is not None:
                stamps.append(est.stamp)
                poses.append(np.asarray(est.T_map_body))
            if n % 100 == 0:
                loads.append(os.getloadavg()[0])
        if prof is not None:
            prof.disable()
    finally:
        session.close()
    loads.append(os.getloadavg()[0])
    from blockloc.evaluation.report import evaluate_trajectories
    from blockloc.geometry import Trajectory

    ev = evaluate_trajectories(session.seq.ground_truth(), Trajectory(np.asarray(stamps), np.asarray(poses)),
                               align=False, max_time_diff_s=0.02, interpolate=True)
    d = diags[skip:]
    stage = {k: np.array([getattr(x, k, np.nan) for x in d], dtype=np.float64) for k in STAGES + ("update_ms",)}
    known = np.nansum(np.stack([stage[k] for k in STAGES]), axis=0)
    stage["rest_ms"] = stage["update_ms"] - known
    w, c, pc = (np.asarray(a[skip:]) for a in (wall, thread_cpu, proc_cpu))
    out = {"world": str(world), "map": str(map_path), "frames": len(diags), "timed": len(w), "no_imu": no_imu,
           "num_threads": cfg.registration.num_threads,
           "failures": int(tracker.counters["failures"]), "rejected": int(tracker.counters["rejected"]),
           "ate_trans_rmse_m": ev["ate_trans_rmse_m"], "ate_rot_rmse_deg": ev["ate_rot_rmse_deg"],
           "matched": ev["matched"],
           "wall_ms": {p: _q(w, q) for p, q in (("median", 50), ("p90", 90), ("p99", 99))},
           "thread_cpu_ms": {p: _q(c, q) for p, q in (("median", 50), ("p90", 90), ("p99", 99))},
           "process_cpu_ms": {p: _q(pc, q) for p, q in (("median", 50), ("p90", 90), ("p99", 99))},
           "stage_median_ms": {k: float(np.nanmedian(v)) if np.isfinite(v).any() else None
                               for k, v in stage.items() if k != "update_ms"},
           "stage_mean_ms": {k: float(np.nanmean(v)) if np.isfinite(v).any() else None
                             for k, v in stage.items()},
           "points_median": float(np.median([x.num_points for x in d])) if d else None,
           "load_avg": {"start": loads[0], "end": loads[-1], "mean": float(np.mean(loads))}}
    if prof is not None:
        out["profile"] = profile_split(prof, len(d))
    return out


class _WithoutFastPath:
    """A registration engine without ``align_from_prediction``: the tracker then aligns with
    ``align`` (the stages as before the fast path)."""

    def __init__(self, engine) -> None:
        self._engine = engine

    def __getattr__(self, name):
        if name == "align_from_prediction":
            raise AttributeError(name)
        return getattr(self._engine, name)


def _without(change: str):
    """A session edit that turns ``change`` off (A of an A/B run)."""
    def edit(session) -> None:
        if change == "smoother":  # LM's own stopping test only
            session.tracker.window.one_step_m = session.tracker.window.one_step_rad = 0.0
        elif change == "registration":
            session.tracker.registration = _WithoutFastPath(session.tracker.registration)
        else:
            raise ValueError(f"--ab {change!r}: expected smoother or registration")
    return edit


def run_ab(world: Path, map_path: Path, frames: int | None, skip: int, change: str, no_imu: bool = False) -> dict:
    """Two sessions of one world stepped alternately, scan by scan (the order swapped every scan),
    A with ``change`` off, B as the code is: both see the same load. Per scan the thread CPU and
    wall of each ``Session.step`` (``insert_frame`` and the scan's IMU samples fed to it); returns
    medians, the paired median of B - A, each one's ATE over the scans run."""
    from blockloc.app.catalog import config_for_sequence
    from blockloc.app.runs import open_session
    from blockloc.evaluation.report import evaluate_trajectories
    from blockloc.geometry import Trajectory

    seq = str(world / "loc")
    overrides: dict = {"evaluation": {"plots": False}}
    if no_imu:
        overrides["tracking"] = {"use_imu": False}
    runs = {}
    for name in ("A", "B"):
        session = open_session(seq, cfg=config_for_sequence(seq, overrides=overrides), map_path=str(map_path))
        if name == "A":
            _without(change)(session)
        session.initialize("gt", 0)
        runs[name] = {"session": session, "wall": [], "cpu": [], "stamps": [], "poses": [], "diags": []}
    stop = len(runs["A"]["session"].seq) if frames is None else min(len(runs["A"]["session"].seq), frames)
    streams = {n: r["session"].seq.frames(0, stop) for n, r in runs.items()}
    loads = [os.getloadavg()[0]]
    try:
        for n in range(stop):
            frames_now = {name: next(streams[name]) for name in runs}
            for name in (("A", "B") if n % 2 == 0 else ("B", "A")):
                r = runs[name]
                c0, w0 = time.thread_time(), time.perf_counter()
                est = r["session"].step(frames_now[name])
                r["wall"].append((time.perf_counter() - w0) * 1e3)
                r["cpu"].append((time.thread_time() - c0) * 1e3)
                r["diags"].append(est.diagnostics)
                if est.T_map_body is not None:
                    r["stamps"].append(est.stamp)
                    r["poses"].append(np.asarray(est.T_map_body))
            if n % 100 == 0:
                loads.append(os.getloadavg()[0])
    finally:
        for r in runs.values():
            r["session"].close()
    loads.append(os.getloadavg()[0])
    out = {"world": str(world), "change": change, "no_imu": no_imu, "frames": stop,
           "load_avg": {"min": min(loads), "max": max(loads)}}
    for name, r in runs.items():
        ev = evaluate_trajectories(r["session"].seq.ground_truth(),
                                   Trajectory(np.asarray(r["stamps"]), np.asarray(r["poses"])),
                                   align=False, max_time_diff_s=0.02, interpolate=True)
        out[name] = {"wall_median_ms": float(np.median(r["wall"][skip:])),
                     "thread_cpu_median_ms": float(np.median(r["cpu"][skip:])),
                     "ate_trans_rmse_m": ev["ate_trans_rmse_m"],
                     "failures": int(r["session"].tracker.counters["failures"]),
                     "stage_median_ms": {k: float(np.nanmedian([getattr(x, k, np.nan) for x in r["diags"][skip:]]))
                                         for k in STAGES}}
    out["paired_thread_cpu_median_ms"] = float(np.median(np.subtract(runs["B"]["cpu"][skip:], runs["A"]["cpu"][skip:])))
    out["paired_wall_median_ms"] = float(np.median(np.subtract(runs["B"]["wall"][skip:], runs["A"]["wall"][skip:])))
    return out


#: cProfile functions whose cumulative time is a stage (matched on "file:function"), outermost first.
PROFILE_GROUPS = (
    ("scan prep", ("estimator.py:_preprocess",)),
    ("prediction (IMU)", ("imu.py:predict_states",)),
    ("deskew", ("deskew.py:deskew_points", "deskew.py:lidar_motion_table")),
    ("map provider", ("provider.py:update",)),
    ("registration: NDT kernel", ("_ndt_kernels.py:ndt_level",)),
    ("registration: rest", ("estimator.py:_register",)),
    ("smoother: LM", ("window.py:optimize",)),
    ("smoother: marginalize", ("window.py:enforce_size",)),
    ("smoother: new keyframe (IMU factor)", ("estimator.py:_add_keyframe",)),
    ("covariance", ("estimator.py:_covariance",)),
    ("insert_frame total", ("estimator.py:insert_frame",)),
)


def profile_split(prof, scans: int) -> dict:
    """ms per scan of each PROFILE_GROUPS entry (cumulative times; "registration: rest" is the
    registration call minus its kernel)."""
    import pstats

    st = pstats.Stats(prof).stats  # (file, line, func) -> (cc, nc, tt, ct, callers)
    cum = {}
    for (file, _, func), (_, _, _, ct, _) in st.items():
        cum[f"{Path(file).name}:{func}"] = cum.get(f"{Path(file).name}:{func}", 0.0) + ct
    out = {}
    for name, keys in PROFILE_GROUPS:
        out[name] = sum(cum.get(k, 0.0) for k in keys) * 1e3 / max(scans, 1)
    out["registration: rest"] -= out["registration: NDT kernel"]
    return out


def _seed_name(s: dict) -> str:
    return Path(s["world"]).name + (" LiDAR-only" if s.get("no_imu") else "")


def _f(x, fmt="{:.2f}") -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else fmt.format(x)


def render(after: dict, before: dict | None, command: str) -> str:
    """docs/bench/update.md's section."""
    lines = ["## The tracker's own per-scan update (issue 39: median <= 6 ms)", "",
             f"`{command}`, {after['date']}, on {after['machine']}, commit {after['commit']}."
             + (f" Before: `{before['command']}`, {before['date']}, commit {before['commit']}." if before else ""),
             "",
             "Per scan, around `Estimator.insert_frame` (what the node's latency is mostly made of): wall "
             "(perf_counter), the tracking thread's CPU (thread_time) and the process's CPU (process_time, "
             "all threads), median / p90 / p99 over the scans after the first "
             f"{after['skip']}; 1-min load average at the start / end of each run (2 cores shared with "
             "other engineers' processes: wall times are upper bounds, CPU times the steadier figure). "
             "ATE: position RMSE against ground truth over every scan of the session, no alignment, "
             "interpolated; the worlds are seeds 2 and 3 of `python -m bench.seeds` (small world, "
             "`loc` session, block map with the mounting estimated).", "",
             "| seed | code | NDT threads | scans | wall median / p90 / p99 [ms] | thread CPU median / p90 / p99 [ms] | "
             "process CPU median [ms] | load start / end | ATE [m] | rot. ATE [deg] | failures |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, res in (("before", before), ("after", after)):
        if not res:
            continue
        for s in res["seeds"]:
            w, c, p = s["wall_ms"], s["thread_cpu_ms"], s["process_cpu_ms"]
            lines.append(f"| {_seed_name(s)} | {label} | {s.get('num_threads')} | {s['timed']} | {_f(w['median'])} / {_f(w['p90'])} / "
                         f"{_f(w['p99'])} | {_f(c['median'])} / {_f(c['p90'])} / {_f(c['p99'])} | {_f(p['median'])} | "
                         f"{_f(s['load_avg']['start'], '{:.1f}')} / {_f(s['load_avg']['end'], '{:.1f}')} | "
                         f"{_f(s['ate_trans_rmse_m'], '{:.4f}')} | {_f(s['ate_rot_rmse_deg'], '{:.3f}')} | "
                         f"{s['failures']} |")
    lines += ["", "Split by stage (the tracker's diagnostics, wall ms, median per scan; rest = update minus "
              "the stages: the pose and covariance at the stamp, health bookkeeping):", "",
              "| seed | code | " + " | ".join(STAGE_NAMES[k] for k in STAGES + ("rest_ms",)) + " |",
              "|---|---|" + "---|" * (len(STAGES) + 1)]
    for label, res in (("before", before), ("after", after)):
        if not res:
            continue
        for s in res["seeds"]:
            m = s["stage_median_ms"]
            lines.append(f"| {_seed_name(s)} | {label} | "
                         + " | ".join(_f(m.get(k)) for k in STAGES + ("rest_ms",)) + " |")
    prof = [(label, s) for label, res in (("before", before), ("after", after)) if res
            for s in res["seeds"] if "profile" in s]
    if prof:
        names = [n for n, _ in PROFILE_GROUPS]
        lines += ["", f"cProfile of a second run of each world's first {prof[0][1].get('profile_scans')} scans "
                  "(`--profile N`, clocked with the process's CPU time: ms per "
                  "scan, mean, profiler overhead included; the numba worker threads of a parallel NDT pass "
                  "count in the registration, a background map load in whatever ran beside it): where the "
                  "time goes, finer than the diagnostics.", "",
                  "| seed | code | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
        for label, s in prof:
            lines.append(f"| {_seed_name(s)} | {label} | "
                         + " | ".join(_f(s["profile"].get(n)) for n in names) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    import shlex

    ap = argparse.ArgumentParser(prog="python -m bench.update", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=None,
                    help="folder of bench.seeds' worlds (default: <blockloc cache>/bench-seeds)")
    ap.add_argument("--seeds", default="2,3")
    ap.add_argument("--frames", type=int, default=None, help="scans per seed (default: the whole session)")
    ap.add_argument("--skip", type=int, default=5, help="first scans left out of the times (warm-up)")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="also a cProfile split by stage: a second run of N scans per seed (0: none)")
    ap.add_argument("--threads", type=int, default=None,
                    help="registration.num_threads (numba threads of the NDT passes; default: the preset's)")
    ap.add_argument("--no-imu", action="store_true", help="the LiDAR-only tracker (as blockloc track --no-imu)")
    ap.add_argument("--ab", choices=("smoother", "registration"), default=None,
                    help="instead: an A/B run, two sessions stepped alternately, A with this round's "
                         "smoother or registration change off (printed, and in --json)")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here too")
    ap.add_argument("--before", type=Path, default=None, help="an earlier run's --json, shown beside")
    ap.add_argument("--out", type=Path, default=OUT, help="the markdown section ('-': none)")
    a = ap.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.WARNING)
    from bench.__main__ import _commit, machine
    from blockloc.fileio import atomic_write_text

    work = a.work or default_work()
    command = "python -m bench.update " + shlex.join(argv if argv is not None else sys.argv[1:])
    res = {"command": command, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "machine": machine(),
           "commit": _commit(), "skip": a.skip, "seeds": []}
    for seed in [int(s) for s in a.seeds.split(",") if s]:
        world, map_path = work / f"s{seed}", work / f"s{seed}_map"
        if not (world / "loc").is_dir() or not map_path.is_dir():
            print(f"error: {world}/loc or {map_path} missing: make them with python -m bench.seeds --seeds {seed} "
                  f"--runs default --work {work}", file=sys.stderr)
            return 2
        if a.ab:
            s = run_ab(world, map_path, a.frames, a.skip, a.ab, a.no_imu)
            res["seeds"].append(s)
            print(f"seed {seed} --ab {a.ab}: thread CPU median A {s['A']['thread_cpu_median_ms']:.2f} -> B "
                  f"{s['B']['thread_cpu_median_ms']:.2f} ms (paired B-A {s['paired_thread_cpu_median_ms']:+.2f}), "
                  f"wall A {s['A']['wall_median_ms']:.2f} -> B {s['B']['wall_median_ms']:.2f} ms (paired "
                  f"{s['paired_wall_median_ms']:+.2f}), ATE A {s['A']['ate_trans_rmse_m']:.4f} -> B "
                  f"{s['B']['ate_trans_rmse_m']:.4f} m, load {s['load_avg']['min']:.1f}-{s['load_avg']['max']:.1f}",
                  flush=True)
            continue
        s = run_seed(world, map_path, a.frames, a.skip, False, a.threads, a.no_imu)
        if a.profile:  # apart: the profiler's overhead stays out of the timed run
            s["profile"] = run_seed(world, map_path, a.profile, a.skip, True, a.threads, a.no_imu)["profile"]
            s["profile_scans"] = a.profile
        res["seeds"].append(s)
        print(f"seed {seed}: update wall median {s['wall_ms']['median']:.2f} ms, thread CPU median "
              f"{s['thread_cpu_ms']['median']:.2f} ms, ATE {s['ate_trans_rmse_m']:.4f} m, load "
              f"{s['load_avg']['mean']:.1f}", flush=True)
    if a.json:
        atomic_write_text(a.json, json.dumps(res, indent=1))
    if a.ab:
        return 0
    before = json.loads(a.before.read_text()) if a.before else None
    if str(a.out) != "-":
        atomic_write_text(a.out, render(res, before, command))
        print(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
