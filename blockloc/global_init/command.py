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


def scan_body_deskewed(frame, seq, imu=None) -> tuple[np.ndarray, float]:
    """Frame points (N, 3) in the BODY frame at the middle of the sweep, and that time (s).

    The reference time is the middle of the sweep (``frame.stamp`` plus the mid time offset): the
    pose a rigid registration finds for a scan taken while moving is the pose at mid-sweep, so
    the result is stamped there (NCLT and simulated stamps are the sweep start: ~0.065 m apart at
    1.3 m/s). Points are rotation-deskewed to that time with the gyro.

    At initialization the velocity is unknown, so only the rotation during the sweep (integrated
    from the gyro, bias neglected: ~0.002 rad/s x 0.1 s) is removed; at a turn in place it moves far
    points by metres, while the unknown translation is at most speed x sweep time (~0.15 m).
    Frames without per-point times are returned as they are.
    """
    from blockloc.geometry import so3_exp
    from blockloc.tracking.deskew import deskew_points_numpy

    info = seq.info
    pts = np.asarray(frame.points, dtype=np.float64)
    if frame.time_offsets is None or len(pts) == 0:
        return transform_points(info.T_body_lidar, pts), float(frame.stamp)
    offs = np.asarray(frame.time_offsets, dtype=np.float64)
    t_ref = float(frame.stamp + 0.5 * (offs.min() + offs.max()))
    imu = seq.imu() if imu is None else imu
    t0, t1 = frame.stamp + offs.min(), frame.stamp + offs.max()
    near = imu.between(t0 - 0.02, t1 + 0.02)
    if len(near) < 2 or t1 <= t0:
        return transform_points(info.T_body_lidar, pts), t_ref
    omega_body = near.gyro @ np.asarray(info.T_body_imu, float)[:3, :3].T
    times = np.concatenate([[t0], near.t[(near.t > t0) & (near.t < t1)], [t1]])
    idx = np.clip(np.searchsorted(near.t, times, side="right") - 1, 0, len(near) - 1)
    R = [np.eye(3)]
    for k in range(1, len(times)):  # zero-order hold of the rate over each interval
        R.append(R[-1] @ so3_exp(omega_body[idx[k - 1]] * (times[k] - times[k - 1])))
    R = np.array(R)
    # Rotation of the body at each table time relative to the body at t_ref.
    times = np.append(times, t_ref)
    R_ref = _interp_rotation(times[:-1], R, t_ref)
    times = times[:-1]
    T_body_table = np.zeros((len(times), 4, 4))
    T_body_table[:, :3, :3] = R_ref.T[None] @ R
    T_body_table[:, 3, 3] = 1.0
    T_bl = np.asarray(info.T_body_lidar, float)
    from blockloc.geometry import inv_T

    T_lidar_table = inv_T(T_bl)[None] @ T_body_table @ T_bl[None]
    lidar = deskew_points_numpy(pts, frame.stamp + offs, times, T_lidar_table)
    return transform_points(T_bl, lidar), t_ref


def _interp_rotation(times: np.ndarray, R: np.ndarray, t: float) -> np.ndarray:
    """Rotation at time t from a table (K,) times and (K, 3, 3) rotations (slerp in one interval)."""
    from blockloc.geometry import so3_exp, so3_log

    j = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2))
    span = times[j + 1] - times[j]
    a = (t - times[j]) / span if span > 0 else 0.0
    return R[j] @ so3_exp(a * so3_log(R[j].T @ R[j + 1]))


def run_init(seq_name: str, frame_index: int, map_path: str, hint: str | None, window_m: float | None,
             yaw_window_deg: float | None, config: str | None, data_root: str | None):
    """Returns (InitResult, summary dict). Raises BlocklocError on bad input."""
    from blockloc.config import load_config_for_sequence
    from blockloc.datasets import open_sequence
    from blockloc.maps.store import open_map

    cfg = load_config_for_sequence(seq_name, config)
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
    pts_body, t_ref = scan_body_deskewed(frame, seq)
    res = loc.localize(pts_body, gravity_at(seq, t_ref), hint_xy, hint_yaw, window_m, yaw_window_deg)
    return res, summary(res, t_ref)


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
    if summ["ambiguous"]:
        console.print("[yellow]warning: ambiguous: another verified candidate far from this one fits almost "
                      "as well (repeated structure); check the candidates or give a tighter hint[/yellow]")
    table = Table("#", "x", "y", "z", "yaw deg", "score", "fitness", "verified")
    for i, c in enumerate(summ["candidates"]):
        table.add_row(str(i), f"{c['x']:.2f}", f"{c['y']:.2f}", f"{c['z']:.2f}", f"{math.degrees(c['yaw']):.1f}",
                      f"{c['score']:.3f}", f"{c['fitness']:.3f}", str(c["verified"]))
    console.print(table)


def to_json(summ: dict) -> str:
    return json.dumps(summ)
