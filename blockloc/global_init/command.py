"""``blockloc init``: global initialization of one frame of a sequence against a map store.

The CLI only parses; this module opens the sequence and the map, levels the scan with the
accelerometer around the frame, runs :class:`GlobalLocalizer` and formats the result.
"""

from __future__ import annotations

import json
import logging
import math

import numpy as np

from blockloc.errors import GlobalInitError
from blockloc.geometry import T_to_xyzrpy, transform_points
from blockloc.global_init.projection import gravity_body_from_imu
from blockloc.global_init.relocalize import GlobalLocalizer, InitParams, InitResult

log = logging.getLogger(__name__)

IMU_HALF_WINDOW_S = 0.25


def parse_hint(text: str | None) -> tuple[tuple[float, float] | None, float | None]:
    """'x,y' or 'x,y,yaw' (metres, radians; map frame) -> ((x, y), yaw | None); None -> (None, None)."""
    if text is None:
        return None, None
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (2, 3) or not all(math.isfinite(v) for v in vals):
        raise GlobalInitError(f"--pose-hint {text!r}: expected x,y or x,y,yaw (metres, radians)")
    return (vals[0], vals[1]), (vals[2] if len(vals) == 3 else None)


def gravity_at(seq, stamp: float) -> np.ndarray:
    """Gravity (3,) in the body frame from the accelerometer within +-0.25 s of ``stamp``."""
    imu = seq.imu()
    if imu is None or len(imu) == 0:
        raise GlobalInitError(f"{seq.info.name}: no IMU data to level the scan")
    near = imu.between(stamp - IMU_HALF_WINDOW_S, stamp + IMU_HALF_WINDOW_S)
    if len(near) == 0:  # e.g. the first frame before the IMU starts: the nearest samples
        i = int(np.clip(np.searchsorted(imu.t, stamp), 0, len(imu) - 1))
        near = imu.between(imu.t[max(i - 25, 0)], imu.t[min(i + 25, len(imu) - 1)] + 1e-9)
    return gravity_body_from_imu(near.acc, seq.info.T_body_imu)


def run_init(seq_name: str, frame_index: int, map_path: str, hint: str | None, window_m: float | None,
             yaw_window_deg: float | None, config: str | None, data_root: str | None):
    """Returns (InitResult, summary dict). Raises BlocklocError on bad input."""
    from blockloc.config import load_config
    from blockloc.datasets import open_sequence
    from blockloc.maps.store import open_map

    cfg = load_config(config)
    window_m = cfg.global_init.window_m if window_m is None else window_m
    yaw_window_deg = cfg.global_init.yaw_window_deg if yaw_window_deg is None else yaw_window_deg
    hint_xy, hint_yaw = parse_hint(hint)
    if not window_m > 0:
        raise GlobalInitError(f"--window {window_m}: expected a positive size in metres")
    seq = open_sequence(seq_name, data_root=data_root, dataset_cfg=cfg.dataset)
    if not 0 <= frame_index < len(seq):
        raise GlobalInitError(f"--frame {frame_index}: expected 0..{len(seq) - 1} ({seq.info.name} has "
                              f"{len(seq)} frames)")
    store = open_map(map_path)
    frame = seq.frame(frame_index)
    params = InitParams.from_config(cfg.global_init, cfg.registration)
    loc = GlobalLocalizer.for_store(store, seq.info.gravity_map, params)
    pts_body = transform_points(seq.info.T_body_lidar, frame.points)
    res = loc.localize(pts_body, gravity_at(seq, frame.stamp), hint_xy, hint_yaw, window_m, yaw_window_deg)
    return res, summary(res, frame.stamp)


def summary(res: InitResult, stamp: float | None = None) -> dict:
    """JSON-ready dict: x, y, z (m), roll, pitch, yaw (rad) of T_map_body, score, fitness, ..."""
    out: dict = {"verified": bool(res.verified), "ambiguous": bool(res.ambiguous),
                 "score": round(float(res.score), 4), "fitness": round(float(res.fitness), 4),
                 "time_s": round(float(res.time_s), 3), "num_candidates": len(res.candidates)}
    if stamp is not None:
        out["stamp"] = float(stamp)
    if res.T_map_body is not None:
        x, y, z, roll, pitch, yaw = (float(v) for v in T_to_xyzrpy(res.T_map_body))
        out.update(x=x, y=y, z=z, roll=roll, pitch=pitch, yaw=yaw)
    out["candidates"] = [
        dict(zip(("x", "y", "z", "roll", "pitch", "yaw"), (round(float(v), 4) for v in T_to_xyzrpy(c.T_map_body))),
             score=round(c.score, 4), fitness=round(c.fitness, 4), verified=c.verified)
        for c in res.candidates]
    out["stats"] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in res.stats.items()}
    return out


def print_result(summ: dict, console) -> None:
    """Human-readable result (rich console)."""
    from rich.table import Table

    if "x" in summ:
        console.print(f"T_map_body  x {summ['x']:.3f}  y {summ['y']:.3f}  z {summ['z']:.3f} m   "
                      f"roll {math.degrees(summ['roll']):.2f}  pitch {math.degrees(summ['pitch']):.2f}  "
                      f"yaw {math.degrees(summ['yaw']):.2f} deg")
    console.print(f"score {summ['score']:.3f}  fitness {summ['fitness']:.3f}  verified {summ['verified']}  "
                  f"ambiguous {summ['ambiguous']}  time {summ['time_s']:.2f} s")
    table = Table("#", "x", "y", "z", "yaw deg", "score", "fitness", "verified")
    for i, c in enumerate(summ["candidates"]):
        table.add_row(str(i), f"{c['x']:.2f}", f"{c['y']:.2f}", f"{c['z']:.2f}", f"{math.degrees(c['yaw']):.1f}",
                      f"{c['score']:.3f}", f"{c['fitness']:.3f}", str(c["verified"]))
    console.print(table)


def to_json(summ: dict) -> str:
    return json.dumps(summ)
