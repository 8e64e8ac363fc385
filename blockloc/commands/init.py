"""``blockloc init``: global initialization of one frame of a sequence against a map store.

Opens the sequence and the map, prepares the scan as tracking does
(:func:`blockloc.tracking.scan_prep.prepare_for_init`: gyro deskew to mid-sweep, gravity from the
accelerometer), runs the global localizer with the configured registration engine and reports
the result; with ground truth, also its error.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np

from blockloc.errors import GlobalInitError
from blockloc.geometry import T_to_xyzrpy


def run_init(seq_name: str, frame_index: int, map_path: str, hint: str | None, window_m: float | None,
             yaw_window_deg: float | None, config: str | None, data_root: str | None, poses=None,
             sets: list[str] | None = None) -> tuple:
    """Returns (InitResult, summary dict for printing/JSON). Raises BlocklocError on bad input."""
    import dataclasses

    from blockloc.commands.common import config_for, parse_pose_hint
    from blockloc.datasets import open_sequence
    from blockloc.global_init.relocalize import GlobalLocalizer, InitParams, pose_error
    from blockloc.jit import CompileClock
    from blockloc.maps.mounting import with_map_mounting
    from blockloc.maps.store import open_map_from_config
    from blockloc.registration.engines import engine_from_settings
    from blockloc.tracking.scan_prep import prepare_for_init

    cfg = config_for(seq_name, config, sets)
    gi, rc = cfg.global_init, cfg.registration
    window_m = gi.window_m if window_m is None else window_m
    yaw_window_deg = gi.yaw_window_deg if yaw_window_deg is None else yaw_window_deg
    x, y, hint_yaw = parse_pose_hint(hint) if hint is not None else (None, None, None)
    if not (window_m > 0 and math.isfinite(window_m)):
        raise GlobalInitError(f"--window {window_m}: expected a positive size in metres")
    if not (0 < yaw_window_deg <= 360):
        raise GlobalInitError(f"--yaw-window {yaw_window_deg}: expected an angle in (0, 360] degrees")
    seq = open_sequence(seq_name, data_root=data_root, dataset_cfg=cfg.dataset, poses=poses)
    if not 0 <= frame_index < len(seq):
        raise GlobalInitError(f"--frame {frame_index}: expected 0..{len(seq) - 1} ({seq.info.name} has "
                              f"{len(seq)} frames)")
    store = open_map_from_config(map_path, cfg.map)
    seq = with_map_mounting(seq, store, cfg.map.use_map_mounting)  # as track does (issue 41)
    engine = engine_from_settings(dataclasses.asdict(rc), resolution_m=gi.ndt_resolution_m)
    loc = GlobalLocalizer.for_store(store, seq.info.gravity_map, InitParams.from_config(gi, rc), engine=engine)
    scan = prepare_for_init(seq.frame(frame_index), seq.imu(), seq.info)
    t0 = time.perf_counter()
    with CompileClock() as jit:
        res = loc.localize(scan.points_body, scan.gravity_body, None if x is None else (x, y), hint_yaw,
                           window_m, yaw_window_deg if hint_yaw is not None else 360.0)
    summ = summary(res, scan.stamp)
    # search and refinement: not process start, map opening, loading the place index, nor compiling
    # the kernels on the first run after an install (compile_s)
    summ["time_s"] = round(min(float(res.time_s), time.perf_counter() - t0) - jit.seconds, 3)
    summ["compile_s"] = round(jit.seconds, 3)
    gt = seq.ground_truth()
    if gt is not None and gt.stamps[0] <= scan.stamp <= gt.stamps[-1]:
        Tg = gt.interpolate(np.array([scan.stamp]))[0]
        gx, gy, _, _, _, gyaw = (float(v) for v in T_to_xyzrpy(Tg))
        summ["gt"] = {"x": gx, "y": gy, "yaw": gyaw}
        if res.T_map_body is not None:
            err_m, err_deg = pose_error(np.asarray(res.T_map_body), Tg)
            summ["error_m"], summ["error_deg"] = round(err_m, 4), round(err_deg, 4)
    return res, summ


def summary(res, stamp: float | None = None) -> dict:
    """JSON-ready dict: x, y, z (m), roll, pitch, yaw (rad) of T_map_body, score, fitness, ..."""
    out: dict = {"verified": bool(res.verified), "ambiguous": bool(res.ambiguous),
                 "score": round(float(res.score), 4), "fitness": round(float(res.fitness), 4),
                 "time_s": round(float(res.time_s), 3), "num_candidates": len(res.candidates)}
    if stamp is not None:
        out["stamp"] = float(stamp)
    out["pose"] = None  # x, y, z (m), roll, pitch, yaw (rad); also flat, below
    if res.T_map_body is not None:
        x, y, z, roll, pitch, yaw = (float(v) for v in T_to_xyzrpy(res.T_map_body))
        out.update(x=x, y=y, z=z, roll=roll, pitch=pitch, yaw=yaw)
        out["pose"] = {"x": x, "y": y, "z": z, "roll": roll, "pitch": pitch, "yaw": yaw}
    out["candidates"] = [
        dict(zip(("x", "y", "z", "roll", "pitch", "yaw"), (round(float(v), 4) for v in T_to_xyzrpy(c.T_map_body))),
             score=round(c.score, 4), fitness=round(c.fitness, 4), verified=c.verified)
        for c in res.candidates]
    out["stats"] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in res.stats.items()}
    return out


def compile_note(info: dict) -> str:
    """" (+N s compiling kernels, ...)" when the kernels were compiled in the timed part, else ""."""
    c = info.get("compile_s") or 0.0
    return f" (+{c:.0f} s compiling kernels, first run after install only)" if c >= 0.5 else ""


def print_result(summ: dict, console) -> None:
    """Human-readable result (rich console)."""
    from rich.table import Table

    if "x" in summ:
        console.print(f"T_map_body  x {summ['x']:.3f}  y {summ['y']:.3f}  z {summ['z']:.3f} m   "
                      f"roll {math.degrees(summ['roll']):.2f}  pitch {math.degrees(summ['pitch']):.2f}  "
                      f"yaw {math.degrees(summ['yaw']):.2f} deg")
    console.print(f"score {summ['score']:.3f}  fitness {summ['fitness']:.3f}  verified {summ['verified']}  "
                  f"ambiguous {summ['ambiguous']}  time {summ['time_s']:.2f} s{compile_note(summ)}")
    if "error_m" in summ:
        console.print(f"against ground truth: {summ['error_m']:.3f} m, {summ['error_deg']:.2f} deg")
    if summ.get("stats", {}).get("timed_out") and not summ["verified"]:
        console.print("[yellow]not found: the search stopped at its budget (global_init.max_search_s; "
                      "--set global_init.max_search_s=0 searches the whole map however long it takes)[/yellow]")
    if summ["ambiguous"]:
        console.print("[yellow]warning: ambiguous: another verified candidate far from this one fits almost "
                      "as well (repeated structure); check the candidates or give a tighter hint[/yellow]")
    table = Table("#", "x", "y", "z", "yaw deg", "score", "fitness", "verified")
    for i, c in enumerate(summ["candidates"]):
        table.add_row(str(i), f"{c['x']:.2f}", f"{c['y']:.2f}", f"{c['z']:.2f}", f"{math.degrees(c['yaw']):.1f}",
                      f"{c['score']:.3f}", f"{c['fitness']:.3f}", str(c["verified"]))
    console.print(table)


def init_command(seq, frame, map_path, pose_hint, window, yaw_window, json_out, data_root, config,
                 poses=None, sets=None) -> None:
    """The command: run, print (JSON or tables), fail (exit 2) when nothing was verified."""
    from blockloc.commands.common import console

    res, summ = run_init(seq, frame, map_path, pose_hint, window, yaw_window, config, data_root, poses, sets)
    if json_out:
        print(json.dumps(summ))
    else:
        print_result(summ, console())
    if not res.verified:
        raise GlobalInitError(f"no verified match (best score {res.score:.3f}, fitness {res.fitness:.3f})")
