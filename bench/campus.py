"""Campus tracking run (issue 7's targets): block vs global backend on ``sim:campus/loc``, side by side.

    python -m bench.campus                       # as much of the session as fits in --minutes
    python -m bench.campus --minutes 50 --state DIR
    python -m bench.campus --report-only --state DIR   # fragment from the last checkpoint

Each scan is ray-cast once and fed to one tracker per backend in lockstep (same frames, same load,
the same first stretch of the session for every backend). Both trackers use the same block store
(built from ``sim:campus/map`` once and cached, or ``--map``); the backends differ only in the map
provider's policy: ``block`` serves the block(s) at the robot, ``global`` the union of all blocks.

The run checkpoints every ``--checkpoint-s`` seconds into ``--state`` (per backend: stamps, poses,
per-frame times and flags as .npz, plus progress.json), so a run that is stopped still reports what
it covered. Writes docs/bench/campus.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from bench._track import STATUS_CODES, BackendRun, engine_settings
from blockloc.fileio import atomic_path, atomic_write_text, save_figure

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "campus.md"


def default_map_dir(preset: str, seed: int, map_cfg, kind: str = "block", exact: tuple[str, ...] = ()) -> Path:
    """Cache path of the campus map of ``kind``, keyed by the simulator's and map builder's code
    (``exact``: the map session's error sources switched off, see EXACT_PARTS)."""
    from blockloc.cache import cache_root, fingerprint

    size = map_cfg.block_size_m if kind == "block" else map_cfg.tile_size_m
    key = fingerprint("blockloc.sim", "blockloc.maps", params=(preset, seed, size, map_cfg.keyframe_distance_m,
                                                               map_cfg.keyframe_angle_deg, map_cfg.voxel_size_m))
    tag = "".join(f"-exact{x}" for x in exact) + ("-mounted" if map_cfg.calibrate_mounting else "")
    return cache_root() / "bench" / f"campus_{preset}_{seed}_{kind}{tag}-{key}"


def ensure_map(preset: str, seed: int, out: Path, map_cfg, kind: str = "block", exact: tuple[str, ...] = ()) -> float:
    """Build the ``kind`` map of ``sim:<preset>/map@<seed>`` (with the error sources in ``exact``
    off) at ``out`` unless it loads; seconds spent."""
    from blockloc.app.catalog import open_sequence
    from blockloc.errors import MapError
    from blockloc.maps.store import open_map
    from blockloc.app.runs import build_map

    try:
        open_map(out)
        return 0.0
    except MapError:
        pass
    t0 = time.perf_counter()
    seq = exact_sequence(preset, "map", seed, list(exact)) if exact else open_sequence(f"sim:{preset}/map@{seed}")
    build_map(seq, kind, out, map_cfg, overwrite=True, progress=False)
    return time.perf_counter() - t0


#: Error sources ``--exact`` can switch off (sim.presets.ideal's parts that leave the world alone):
#: ``slam`` the mapping drive's offline-SLAM pose error; ``extrinsic`` the LiDAR mounting error and
#: ``lidar`` the sensor's errors (one robot drives both sessions, so both are off in the map too);
#: ``imu`` and ``platform`` the localization drive's IMU errors and Segway motion. A part in
#: MAP_PARTS builds its own map (its own cache directory).
EXACT_PARTS = ("slam", "extrinsic", "lidar", "imu", "platform")
MAP_PARTS = ("slam", "extrinsic", "lidar")


def exact_sequence(preset: str, session: str, seed: int, parts: list[str]):
    """``sim:<preset>/<session>@<seed>`` with the error sources in ``parts`` off (see EXACT_PARTS)."""
    from dataclasses import replace

    from blockloc.sim.presets import get_preset, ideal
    from blockloc.sim.stream import SimSequence

    p = get_preset(preset)
    off = ideal(p)
    changes = {part: getattr(off, part) for part in parts if part in ("lidar", "imu", "platform")}
    if "extrinsic" in parts:
        changes.update(extrinsic_error_m=0.0, extrinsic_error_deg=0.0)
    if "slam" in parts:
        changes.update(slam_error_m=0.0, slam_error_rad=0.0)
    return SimSequence(replace(p, **changes), session, seed)


def frames_for_km(seq, start: int, km: float) -> int:
    """How many frames from ``start`` the ground truth of ``seq`` takes to cover ``km`` of path
    (the frame that reaches it included; the rest of the session if it never does)."""
    gt = seq.ground_truth()
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt.positions, axis=0), axis=1))])
    at = np.interp(seq.frame_stamps()[start:], gt.stamps, d)  # path length at each frame, m
    return min(len(at), int(np.searchsorted(at - at[0], 1000.0 * km)) + 1)


#: sections of the fragment that other tools write (``bench.campus_seeds``): a rewrite keeps them
KEPT_SECTION_PREFIX = "## Campus over "


def _kept_sections(text: str) -> str:
    """The ``KEPT_SECTION_PREFIX`` sections of ``text`` (each up to the next ``## `` heading)."""
    out, keep = [], False
    for line in text.splitlines():
        if line.startswith("## "):
            keep = line.startswith(KEPT_SECTION_PREFIX)
        if keep:
            out.append(line)
    return "\n".join(out).rstrip("\n") + "\n" if out else ""


def _write_json(path: Path, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=1))


def summarize(state: Path, backend: str, gt) -> dict:
    """Metrics of one backend from its checkpoint: accuracy against ground truth, times, health."""
    from blockloc.evaluation.report import evaluate_trajectories
    from blockloc.geometry import Trajectory

    z = np.load(state / f"{backend}.npz")
    counters = json.loads(str(z["counters"]))
    core, upd, sw = z["core_ms"], z["update_ms"], z["switched"].astype(bool)
    tracked = z["status"] != STATUS_CODES["uninitialized"]
    est = Trajectory(z["stamps"], z["poses"])
    m = {"backend": backend, "frames": int(len(core)), "failures": counters["failures"],
         "recoveries": counters["recoveries"], "switches": counters["switches"],
         "rejected": counters["rejected"], "imu_only": counters["imu_only"],
         "core_ms_median": float(np.median(core[tracked])), "core_ms_mean": float(np.mean(core[tracked])),
         "core_ms_p99": float(np.percentile(core[tracked], 99)),
         "update_ms_median": float(np.median(upd[tracked])), "update_ms_mean": float(np.mean(upd[tracked])),
         "update_ms_p99": float(np.percentile(upd[tracked], 99)),
         "registration_ms_median": float(np.median(z["registration_ms"][tracked])),
         "map_ms_median": float(np.median(z["map_ms"][tracked])),
         "switch_frames": int(sw.sum()),
         "switch_core_ms_p99": float(np.percentile(core[sw], 99)) if sw.any() else None,
         "switch_update_ms_p99": float(np.percentile(upd[sw], 99)) if sw.any() else None,
         "window_min": int(z["window"][tracked].min()), "window_max": int(z["window"][tracked].max()),
         "map_stats": json.loads(str(z["map_stats"])),
         "reject_reasons": {k[len("rejected_"):]: v for k, v in counters.items() if k.startswith("rejected_") and v}}
    for k in ("step_wall_ms", "step_cpu_ms"):  # runs before these columns existed have none
        if k in z.files:
            m[f"{k}_median"] = float(np.median(z[k][tracked]))
            m[f"{k}_mean"] = float(np.mean(z[k][tracked]))
    if len(est) > 1:
        ev = evaluate_trajectories(gt, est, align=False, max_time_diff_s=0.02, rpe_deltas_m=(10.0, 100.0),
                                   interpolate=True)
        m.update({k: ev.get(k) for k in ("ate_trans_rmse_m", "ate_trans_max_m", "ate_full_rmse",
                                         "ate_rot_rmse_deg", "path_length_m", "matched", "duration_s",
                                         "err_along_mean_m", "err_along_rms_m", "err_cross_mean_m",
                                         "err_cross_rms_m", "err_vertical_mean_m", "err_vertical_rms_m",
                                         "err_time_shift_s")})
    m["_stamps"], m["_positions"] = est.stamps, est.positions
    return m


def _traj_rmse(a: dict, b: dict):
    from bench._track import trajectory_rmse

    return trajectory_rmse(a, b)


def plot(rows: dict, gt, state: Path, path: Path) -> None:
    """Three panels for a person to look at: the routes seen from above with the block backend's
    error as colour, each backend's position error along the route, and its per-scan core time
    along the route (rolling median over 200 scans)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 5))
    first = "block" if "block" in rows else next(iter(rows))
    for b in rows:
        z = np.load(state / f"{b}.npz")
        keep = (z["status"] != STATUS_CODES["uninitialized"]) & (z["stamps"] >= gt.stamps[0]) & \
            (z["stamps"] <= gt.stamps[-1])
        if keep.sum() < 2:
            continue
        pos, core = z["poses"][keep][:, :3, 3], z["core_ms"][keep]
        ref = gt.interpolate(z["stamps"][keep])[:, :3, 3]
        err = np.linalg.norm(pos - ref, axis=1)
        km = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ref, axis=0), axis=1))]) / 1000.0
        if b == first:
            sc = axes[0].scatter(pos[:, 0], pos[:, 1], c=np.minimum(err, 0.3), s=1, cmap="viridis")
            fig.colorbar(sc, ax=axes[0], label=f"{b}: position error [m] (clipped at 0.3)")
        axes[1].plot(km, np.maximum(err, 1e-3), lw=0.6, label=b)
        w = int(np.clip(len(core) // 10, 1, 200))
        at = np.arange(w - 1, len(core), max(1, w // 4))
        axes[2].plot(km[at], [np.median(core[i + 1 - w:i + 1]) for i in at], lw=1.0, label=b)
    axes[0].set_aspect("equal")
    axes[0].set_xlabel("x [m]")
    axes[0].set_ylabel("y [m]")
    axes[0].set_title("route (map frame)")
    axes[1].set_xlabel("distance along the route [km]")
    axes[1].set_ylabel("position error [m]")
    axes[1].set_yscale("log")
    axes[1].set_title("position error against ground truth")
    axes[2].set_xlabel("distance along the route [km]")
    axes[2].set_ylabel("core time per scan [ms]")
    axes[2].set_ylim(bottom=0)
    axes[2].set_title("per-scan core time (rolling median)")
    for ax in axes[1:]:
        ax.grid(True, alpha=0.3)
        ax.legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def merge_states(parts: list[Path], state: Path) -> None:
    """Join the checkpoints of consecutive segments of one session (each run with its own
    ``--start`` and ``--state``, e.g. one per core) into ``state``, as if one run had covered them:
    per-frame arrays concatenated, counters summed, the last segment's map statistics. Each segment's
    trackers start at the ground-truth pose of its first frame, which the fragment says. Segments
    may have run more backends than others (e.g. a first kilometre with a second engine): the
    backends every segment ran are merged."""
    progs = sorted((json.loads((p / "progress.json").read_text()) | {"_dir": str(p)} for p in parts),
                   key=lambda g: g["start"])
    backends = [b for b in progs[0]["backends"] if all(b in g["backends"] for g in progs)]
    for a, b in zip(progs, progs[1:]):
        if a["start"] + a["frames_done"] != b["start"] or not backends \
                or a["sequence"] != b["sequence"] \
                or a.get("exact", []) != b.get("exact", []):
            raise SystemExit(f"--merge: {b['_dir']} does not continue {a['_dir']} (same sequence, a backend "
                             f"in common, start {a['start'] + a['frames_done']} expected, got {b['start']})")
    state.mkdir(parents=True, exist_ok=True)
    for backend in backends:
        zs = [np.load(Path(g["_dir"]) / f"{backend}.npz") for g in progs]
        merged = {k: np.concatenate([z[k] for z in zs]) for k in zs[0].files if k not in ("counters", "map_stats")}
        counters = [json.loads(str(z["counters"])) for z in zs]
        merged["counters"] = np.array(json.dumps({k: sum(c[k] for c in counters) for k in counters[0]}))
        merged["map_stats"] = zs[-1]["map_stats"]
        with atomic_path(state / f"{backend}.npz", suffix=".npz") as tmp:
            np.savez(tmp, **merged)
    prog = {k: v for k, v in progs[0].items() if k != "_dir"}
    prog.update(backends=backends, frames_done=sum(g["frames_done"] for g in progs), wall_s=max(g["wall_s"] for g in progs),
                updated=max(g["updated"] for g in progs), load_now=progs[-1]["load_now"],
                load_mean=float(np.mean([g["load_mean"] for g in progs])),
                # each segment continues the one before (checked above), so the joined run covers
                # every frame up to the last one's stop when that one finished (an earlier segment may
                # have been stopped where the next one took over)
                finished=bool(progs[-1]["finished"]), stop=progs[-1].get("stop", progs[0].get("stop")),
                cpu_s=sum(g["cpu_s"] for g in progs) if all("cpu_s" in g for g in progs) else None,
                scan_wall_ms=max(1e3 * g["wall_s"] / max(g["frames_done"], 1) for g in progs),
                segments=[{"start": g["start"], "frames": g["frames_done"], "command": g["command"]} for g in progs])
    _write_json(state / "progress.json", prog)


def before_table(rows: dict, before: dict, what: str) -> list[str]:
    """Lines comparing this run's rows with an earlier run's campus JSON (``before``), backend by backend."""
    f = lambda v, s="{:.3f}": "-" if v is None else s.format(v)  # noqa: E731
    lines = ["", f"Before and after, per backend ({what}):", "",
             "| backend | km before / now | ATE trans RMSE [m] before / now | failures before / now | "
             "rejected before / now | core median [ms] before / now |", "|---|---|---|---|---|---|"]
    for b, m in rows.items():
        o = before.get("backends", {}).get(b)
        if o is None:
            continue
        lines.append(f"| {b} | {before.get('covered_km', 0):.2f} / {(m.get('path_length_m') or 0) / 1000:.2f} | "
                     f"{f(o.get('ate_trans_rmse_m'))} / {f(m.get('ate_trans_rmse_m'))} | {o['failures']} / "
                     f"{m['failures']} | {o['rejected']} / {m['rejected']} | {o['core_ms_median']:.1f} / "
                     f"{m['core_ms_median']:.1f} |")
    return lines if len(lines) > 5 else []


def _sim_name(name: str) -> tuple[str, str, int]:
    """(preset, session, seed) of ``sim:<preset>/<session>@<seed>``."""
    from blockloc.app.catalog import SequenceRef

    return SequenceRef.parse(name).sim


def _bound(prog: dict, frames: int) -> str:
    """What stopped a run short of the session's end: its --max-frames or its --minutes."""
    if prog.get("max_frames") is not None and frames >= prog["max_frames"]:
        return f"the run was bounded to --max-frames {prog['max_frames']:,}"
    return f"the loop is bounded to --minutes {prog['minutes']:g}"


def write_fragment(state: Path, out: Path, before: Path | None = None) -> str:
    from bench.__main__ import machine
    from blockloc.app.catalog import open_sequence

    prog = json.loads((state / "progress.json").read_text())
    loc_exact = [x for x in prog.get("exact", []) if x != "slam"]
    seq = open_sequence(prog["sequence"]) if not loc_exact else exact_sequence(*_sim_name(prog["sequence"]), loc_exact)
    gt = seq.ground_truth()
    rows = {b: summarize(state, b, gt) for b in prog["backends"] if (state / f"{b}.npz").exists()}
    total_km = gt.path_length() / 1000.0
    f = lambda v, s="{:.1f}": "-" if v is None else s.format(v)  # noqa: E731
    covered = rows[next(iter(rows))].get("path_length_m") or 0.0
    frames = prog["frames_done"]
    segs = prog.get("segments", [])
    lines = [
        "## Campus tracking run (issue 7's targets)" if set(prog["backends"]) == {"block", "global"} else
        f"## Campus tracking, backends {', '.join(prog['backends'])} side by side",
        "",
        (f"Command: `{prog['command']}`, started {prog['started']}, last checkpoint {prog['updated']} "
         if not segs else
         f"Run in {len(segs)} consecutive segments side by side (one process each, started together), joined by "
         f"`python -m bench.campus --merge ...`: " + "; ".join(f"`{g['command']}`" for g in segs)
         + f"; started {prog['started']}, last checkpoint {prog['updated']} ")
        + f"({prog['wall_s'] / 60:.1f} min of wall time"
        f"{'' if prog['finished'] else (', stopped at the time bound' if prog['wall_s'] >= 60 * prog['minutes'] - 1 else ', still running or stopped')}).",
        f"Machine: {machine()}. Load average (1 min) {prog['load_start']:.1f} at the start, "
        f"{prog['load_now']:.1f} at the last checkpoint, mean of samples {prog['load_mean']:.1f} "
        "(other engineers' processes share the 2 cores: times are upper bounds).",
        "",
        f"Sequence `{prog['sequence']}`"
        + (f" with these error sources off (`--exact`): {', '.join(prog['exact'])}" if prog.get("exact") else "")
        + f": {len(seq):,} scans, {total_km:.2f} km in total. **Covered: frames "
        f"{prog['start']}..{prog['start'] + frames - 1} ({frames:,} scans, {covered / 1000:.2f} km of ground truth, "
        f"{100 * frames / len(seq):.1f}% of the session)**"
        + (" — the whole session." if prog['start'] + frames >= len(seq) else
           f" — the last {len(seq) - prog['start'] - frames:,} scans were not run: {_bound(prog, frames)} "
           "(each scan is ray-cast at full density before the trackers see it; "
           f"{prog.get('scan_wall_ms', 1e3 * prog['wall_s'] / max(frames, 1)):.0f} ms of wall time a scan for ray "
           "casting and the trackers)."),
        f"Map: block store `{prog['map']}` ({prog['map_desc']}); `block` and `global` use the block store, "
        "`global` serves the union of all blocks. Init at the first ground-truth pose"
        + ("" if not segs else " of each segment (frames " + ", ".join(str(g["start"]) for g in segs)
           + "): every tracker runs each segment through on its own, nothing is carried between segments")
        + "; `blockloc/presets/sim.yaml` with "
        f"block size {prog['block_size_m']:g} m. Each scan ray-cast once and fed to every tracker in lockstep.",
        "",
        "Core = deskew + registration + smoother (the issue's per-scan update); update = the whole "
        "`insert_frame` (adds the map-provider call and the pose covariance).",
        "",
        "| backend | scans | km | ATE trans RMSE [m] | ATE trans max [m] | ATE full RMSE | failures | recoveries | "
        "rejected | switches | core median [ms] | core mean [ms] | core p99 [ms] | update median [ms] | "
        "update p99 [ms] | switch-frame core p99 [ms] | registration median [ms] | resident map MB (provider, at the end) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for b, m in rows.items():
        ms = m["map_stats"]
        res = ms.get("resident_mb")
        lines.append(
            f"| {b} | {m['frames']:,} | {f((m.get('path_length_m') or 0) / 1000, '{:.2f}')} | "
            f"{f(m.get('ate_trans_rmse_m'), '{:.3f}')} | {f(m.get('ate_trans_max_m'), '{:.2f}')} | "
            f"{f(m.get('ate_full_rmse'), '{:.3f}')} | {m['failures']} | {m['recoveries']} | {m['rejected']} | "
            f"{m['switches']} | {f(m['core_ms_median'])} | {f(m['core_ms_mean'])} | {f(m['core_ms_p99'])} | "
            f"{f(m['update_ms_median'])} | {f(m['update_ms_p99'])} | {f(m['switch_core_ms_p99'])} | "
            f"{f(m['registration_ms_median'])} | {f(res, '{:.0f}')} |")
    lines += ["", "Targets (issue 7), block backend, on the stretch covered:", ""]
    if "block" in rows:
        bm = rows["block"]
        ok = lambda c: "met" if c else "**missed**"  # noqa: E731
        ate = bm.get("ate_trans_rmse_m")
        lines.append(f"- ATE translation RMSE <= 0.10 m: {f(ate, '{:.3f}')} m — {ok(ate is not None and ate <= 0.10)}.")
        lines.append(f"- no failure: {bm['failures']} failures, {bm['recoveries']} recoveries — {ok(bm['failures'] == 0)}.")
        lines.append(f"- median per-scan update (core) <= 15 ms: {bm['core_ms_median']:.1f} ms — "
                     f"{ok(bm['core_ms_median'] <= 15.0)}.")
        if "global" in rows:
            gm = rows["global"]
            lines.append(f"- at most half the global backend's: block {bm['core_ms_median']:.1f} ms vs global "
                         f"{gm['core_ms_median']:.1f} ms (ratio {bm['core_ms_median'] / gm['core_ms_median']:.2f}) — "
                         f"{ok(bm['core_ms_median'] <= 0.5 * gm['core_ms_median'])}.")
            ga, ba = gm.get("ate_trans_rmse_m"), bm.get("ate_trans_rmse_m")
            if ga is not None and ba is not None:
                side = "global is the more accurate" if ga < ba else "block is the more accurate"
                lines.append(f"- global ATE within 10% of block's: {ga:.3f} vs {ba:.3f} m ({100 * (ga / ba - 1):+.0f}%, "
                             f"{side}) — {ok(abs(ga - ba) <= 0.1 * ba)}.")
        if bm["switch_core_ms_p99"] is not None:
            r = bm["switch_core_ms_p99"] / bm["core_ms_median"]
            lines.append(f"- no stall at switches, p99 over the {bm['switch_frames']} switch frames <= 2x median: "
                         f"{bm['switch_core_ms_p99']:.1f} ms core ({r:.1f}x), "
                         f"{f(bm['switch_update_ms_p99'])} ms whole update "
                         f"({bm['switch_update_ms_p99'] / bm['update_ms_median']:.1f}x its median) — {ok(r <= 2.0)}.")
        if "global" in rows:
            a, b = rows["block"], rows["global"]
            n = min(len(a["_stamps"]), len(b["_stamps"]))
            if n and np.allclose(a["_stamps"][:n], b["_stamps"][:n]):
                d = np.linalg.norm(a["_positions"][:n] - b["_positions"][:n], axis=1)
                lines.append(f"- trajectory RMSE global vs block (same stamps): {np.sqrt(np.mean(d ** 2)):.3f} m.")
        from bench._track import trajectory_rmse

        for other, ref, tgt in (("grid", "block", " (target <= 0.05 m)"), ("grid", "global", ""),
                                ("srt", "global", "")):
            if other in rows and ref in rows:
                r = trajectory_rmse(rows[other], rows[ref])
                lines.append(f"- trajectory RMSE {other} vs {ref} (same stamps): {f(r, '{:.3f}')} m{tgt}.")
    km = (covered or 0.0) / 1000.0
    others = [b for b in ("grid", "srt", "global") if b in rows]
    if "block" in rows and km >= 1.0:
        bm = rows["block"]
        ok = lambda c: "met" if c else "**missed**"  # noqa: E731
        ate = bm.get("ate_trans_rmse_m")
        lines += ["", f"Targets (issue 15: the realistic world, 6 km+, block backend, nominal calibration), on "
                  f"the {km:.2f} km covered:", "",
                  f"- 6 km+ covered: {km:.2f} km — {ok(km >= 6.0)}.",
                  f"- block ATE translation RMSE <= 0.06 m: {f(ate, '{:.3f}')} m — {ok(ate is not None and ate <= 0.06)}; "
                  f"no failure: {bm['failures']} — {ok(bm['failures'] == 0)}."]
        if others:
            lines.append("- " + ", ".join(others) + " without failure: " + ", ".join(
                f"{b} {rows[b]['failures']}" for b in others) + " — "
                + ok(all(rows[b]["failures"] == 0 for b in others)) + ".")
        lines.append("")
    why = [f"`{b}` {m['rejected']} ({', '.join(f'{k} {v}' for k, v in m['reject_reasons'].items())})"
           for b, m in rows.items() if m["reject_reasons"]]
    if why:
        lines.append("- rejected scans by the first acceptance test they failed: " + "; ".join(why) + ".")
    for b in rows:
        z = np.load(state / f"{b}.npz")
        lost = np.nonzero(np.isin(z["status"], [STATUS_CODES["lost"], STATUS_CODES["recovered"]]))[0]
        if len(lost):
            sw = np.nonzero(z["switched"])[0]
            desc = []
            for i in lost:
                near = sw[np.argmin(np.abs(sw - i))] if len(sw) else None
                desc.append(f"{int(z['index'][i])}" + (f" ({int(z['index'][near]) - int(z['index'][i]):+d} scans to the "
                                                       "nearest switch)" if near is not None else ""))
            more = f", and {len(desc) - 8} more up to scan {int(z['index'][lost[-1]])}" if len(desc) > 8 else ""
            lines.append(f"- `{b}`: {len(desc)} scans lost or relocalized: " + ", ".join(desc[:8]) + more + ".")
    if before is not None and before.is_file():
        lines += before_table(rows, json.loads(before.read_text()),
                              f"before: `{before.name}`, the earlier simulator's world and the tracker of its day; "
                              "its command and this one give the threads each used")
    png = out.with_suffix(".png")
    plot(rows, gt, state, png)
    lines += ["", f"![route, position error and per-scan time along the route]({png.name})", ""]
    from bench._track import write_json

    write_json(out.with_suffix(".json"), {
        "command": prog["command"], "covered_km": covered / 1000.0, "total_km": total_km, "frames": frames,
        "finished": prog["finished"], "load_mean": prog["load_mean"],
        "trajectory_rmse_m": {f"{a}_vs_{b}": _traj_rmse(rows[a], rows[b]) for a, b in
                              (("global", "block"), ("grid", "block"), ("grid", "global"), ("srt", "global"))
                              if a in rows and b in rows},
        "backends": {b: {**{k: v for k, v in m.items() if not k.startswith("_") and k != "map_stats"},
                         "resident_mb": m["map_stats"].get("resident_mb")} for b, m in rows.items()}})
    text = "\n".join(lines) + "\n"
    kept = _kept_sections(out.read_text()) if out.is_file() else ""
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, text + ("\n" + kept if kept else ""))
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.campus", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="campus")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--session", default="loc")
    ap.add_argument("--backends", default="block,global")
    ap.add_argument("--minutes", type=float, default=50.0, help="wall-time budget of the tracking loop")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--km", type=float, default=None,
                    help="stop after this many km of ground-truth path from --start (with --max-frames: "
                         "whichever comes first)")
    ap.add_argument("--map", default=None, help="block store (default: built once into the cache)")
    ap.add_argument("--grid-map", default=None, help="grid store for grid/srt (default: built once into the cache)")
    ap.add_argument("--block-size", type=float, default=100.0)
    ap.add_argument("--state", default=None, help="checkpoint directory (default: cache)")
    ap.add_argument("--checkpoint-s", type=float, default=60.0)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="config override on top of blockloc/presets/sim.yaml, e.g. map.grid_n=2 (repeatable)")
    ap.add_argument("--exact", default="", metavar="PARTS",
                    help="switch these error sources of the localization session off (comma list of "
                         f"{', '.join(EXACT_PARTS)}); the world and the map stay as they are: splits the error budget")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--before", default=None, metavar="JSON",
                    help="an earlier run's campus JSON (e.g. docs/bench/campus_earlier.json) to set beside this one")
    ap.add_argument("--merge", default=None, metavar="DIR,DIR,...",
                    help="join the --state dirs of consecutive segments into --state, then write the fragment")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    cmd = "python -m bench.campus " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))

    import logging

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(message)s")
    from blockloc.cache import cache_root
    from blockloc.config import load_config
    from blockloc.app.catalog import open_sequence
    from blockloc.maps.store import open_map

    state = Path(args.state) if args.state else cache_root() / "bench" / f"campus_run_{args.preset}_{args.seed}"
    if args.merge:
        if not args.state:
            ap.error("--merge needs --state (where the joined checkpoint goes)")
        merge_states([Path(p) for p in args.merge.split(",") if p], state)
    if args.report_only or args.merge:
        print(write_fragment(state, Path(args.out), Path(args.before) if args.before else None))
        return 0
    state.mkdir(parents=True, exist_ok=True)
    overrides = {"map": {"block_size_m": args.block_size}, "evaluation": {"plots": False}}
    for item in args.set:
        key, sep, value = item.partition("=")
        section, dot, name = key.partition(".")
        if not (sep and dot and section and name):
            ap.error(f"--set {item!r}: expected SECTION.KEY=VALUE, e.g. map.grid_n=2")
        overrides.setdefault(section, {})[name] = yaml.safe_load(value)
    cfg = load_config("sim", overrides=overrides)
    exact = [x for x in args.exact.split(",") if x]
    if any(x not in EXACT_PARTS for x in exact):
        ap.error(f"--exact {args.exact!r}: expected a comma list of {', '.join(EXACT_PARTS)}")
    map_exact = tuple(x for x in EXACT_PARTS if x in exact and x in MAP_PARTS)
    if map_exact and (args.map or args.grid_map):
        ap.error(f"--exact {','.join(map_exact)} builds its own map: leave out --map and --grid-map")
    map_path = Path(args.map) if args.map else default_map_dir(args.preset, args.seed, cfg.map, exact=map_exact)
    t_build = ensure_map(args.preset, args.seed, map_path, cfg.map, exact=map_exact)
    store = open_map(map_path)
    map_desc = (f"{len(store.entries)} blocks, {store.total_points:,} points, S = "
                f"{store.params.get('block_size_m', args.block_size):g} m"
                + (f", built in {t_build:.0f} s" if t_build else ", cached"))
    for drive, m in store.params.get("mounting", {}).items():
        map_desc += (f"; LiDAR mounting estimated from {m['used']} keyframe pairs of {drive}: "
                     f"rotation {m['rotation_deg']} deg, translation {m['translation_m']} m (body frame)")

    seq_name = f"sim:{args.preset}/{args.session}@{args.seed}"
    loc_exact = [x for x in exact if x != "slam"]
    seq = open_sequence(seq_name) if not loc_exact else exact_sequence(args.preset, args.session, args.seed, loc_exact)
    stop = len(seq) if args.max_frames is None else min(len(seq), args.start + args.max_frames)
    if args.km is not None:
        stop = min(stop, args.start + frames_for_km(seq, args.start, args.km))
    backends = [b for b in args.backends.split(",") if b]
    grid_path = None
    if any(b.partition("@")[0] in ("grid", "srt") for b in backends):
        grid_path = Path(args.grid_map) if args.grid_map else default_map_dir(args.preset, args.seed, cfg.map, "grid",
                                                                                    exact=map_exact)
        t_grid = ensure_map(args.preset, args.seed, grid_path, cfg.map, "grid", exact=map_exact)
        gstore = open_map(grid_path)
        map_desc += (f"; grid store `{grid_path}` for grid/srt ({len(gstore.entries)} tiles of "
                     f"{cfg.map.tile_size_m:g} m, {gstore.total_points:,} points"
                     + (f", built in {t_grid:.0f} s)" if t_grid else ", cached)"))
    def run_for(b: str) -> BackendRun:
        # backend@engine (e.g. block@vgicp): that map policy with registration.method = engine
        policy, _, engine = b.partition("@")
        cfg_b = cfg if not engine else load_config("sim", overrides={
            **overrides, "registration": {**overrides.get("registration", {}), **engine_settings(engine)}})
        r = BackendRun(seq, cfg_b, grid_path if policy in ("grid", "srt") else map_path, policy, args.start, stop)
        r.backend = b  # names its checkpoint and its row
        return r

    runs = [run_for(b) for b in backends]
    prog = {"command": cmd, "sequence": seq_name, "exact": exact, "backends": backends, "map": str(map_path),
            "map_desc": map_desc, "block_size_m": args.block_size, "start": args.start, "minutes": args.minutes,
            "max_frames": args.max_frames, "started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load_start": os.getloadavg()[0],
            "km": args.km, "stop": stop, "frames_done": 0, "finished": False}
    loads = [os.getloadavg()[0]]
    for r in runs:  # the whole step of each tracker, wall and this thread's CPU (core is wall only)
        r.rows["step_wall_ms"], r.rows["step_cpu_ms"] = [], []
    t0 = last_ck = time.perf_counter()
    cpu0 = time.process_time()

    def checkpoint(finished: bool) -> None:
        for r in runs:
            r.save(state / f"{r.backend}.npz")
        prog.update(updated=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), wall_s=time.perf_counter() - t0,
                    cpu_s=time.process_time() - cpu0,
                    load_now=os.getloadavg()[0], load_mean=float(np.mean(loads)), finished=finished)
        _write_json(state / "progress.json", prog)

    n = 0
    try:
        for frame in seq.frames(args.start, stop):
            for r in runs:
                w0, c0 = time.perf_counter(), time.thread_time()
                r.step(frame)
                r.rows["step_cpu_ms"].append(1e3 * (time.thread_time() - c0))
                r.rows["step_wall_ms"].append(1e3 * (time.perf_counter() - w0))
            n += 1
            prog["frames_done"] = n
            now = time.perf_counter()
            if now - last_ck >= args.checkpoint_s:
                loads.append(os.getloadavg()[0])
                checkpoint(False)
                last_ck = now
                print(f"[{(now - t0) / 60:.1f} min] {n} scans, " + ", ".join(
                    f"{r.backend}: core median {np.median(r.rows['core_ms']):.1f} ms, failures "
                    f"{r.session.tracker.counters['failures']}" for r in runs), flush=True)
            if now - t0 >= args.minutes * 60:
                break
    finally:
        for r in runs:
            r.session.provider.close()
        checkpoint(args.start + n >= stop)
    print(write_fragment(state, Path(args.out), Path(args.before) if args.before else None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
