"""Synthetic runs for the viz tests: a robot on a circle through a 2 x 2 block map, random scans.

No tracking happens: the events are what the session engine would emit, with known poses, so the
tests can check every message against them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.geometry import Trajectory, make_T, rpy_to_R, so3_exp, xyzrpy_to_T
from blockloc.viz.events import FrameEvent, RunInfo

RADIUS_M = 20.0
SPEED_M_S = 6.0
RATE_HZ = 10.0
T0_S = 1000.0  # a sensor clock that does not start at zero


def T_body_lidar() -> np.ndarray:
    return make_T(rpy_to_R(0.01, -0.02, 0.03), np.array([0.3, -0.1, 1.2]))


def block_entries() -> list[dict]:
    """Four 40 m blocks around the origin; the first has a hexagonal footprint, the rest none."""
    out = []
    for k, (cx, cy) in enumerate([(-20, -20), (20, -20), (20, 20), (-20, 20)]):
        lo, hi = np.array([cx - 20.0, cy - 20.0, -2.0]), np.array([cx + 20.0, cy + 20.0, 12.0])
        fp = None
        if k == 0:
            ang = np.linspace(0, 2 * np.pi, 7)[:-1]
            fp = np.c_[cx + 19 * np.cos(ang), cy + 19 * np.sin(ang)]
        out.append({"id": f"block_{k:03d}", "bounds_min": lo, "bounds_max": hi,
                    "centroid": np.array([cx, cy, 3.0]), "footprint": fp})
    return out


def block_of(xy: np.ndarray) -> str:
    k = {(False, False): 0, (True, False): 1, (True, True): 2, (False, True): 3}[(bool(xy[0] >= 0), bool(xy[1] >= 0))]
    return f"block_{k:03d}"


def circle_pose(t: np.ndarray) -> np.ndarray:
    """(N,) seconds since T0 -> (N, 4, 4) T_map_body on the circle, heading along it, small pitch/roll."""
    w = SPEED_M_S / RADIUS_M
    a = w * np.asarray(t, float)
    return xyzrpy_to_T(RADIUS_M * np.cos(a), RADIUS_M * np.sin(a), 0.5 + 0.2 * np.sin(3 * a),
                       0.02 * np.sin(a), 0.01 * np.cos(2 * a), a + np.pi / 2)


def ground_truth(duration_s: float) -> Trajectory:
    t = np.arange(0.0, duration_s + 1e-9, 0.01)
    return Trajectory(T0_S + t, circle_pose(t))


@dataclass
class SyntheticRun:
    info: RunInfo
    events: list[FrameEvent]

    @property
    def localized(self) -> list[FrameEvent]:
        return [e for e in self.events if e.T_map_body is not None]


def random_cov(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(6, 6)) * np.r_[[0.002] * 3, [0.03] * 3]
    return A @ A.T + np.diag(np.r_[[1e-6] * 3, [1e-4] * 3])


def make_run(*, duration_s: float = 20.0, scan_points: int = 2000, lost_frames: tuple = (),
             map_every_s: float = 10.0, map_points: int = 5000, seed: int = 0,
             with_gt: bool = True, out_dir=None, map_on_block_change: bool = True) -> SyntheticRun:
    """Frames at 10 Hz along the circle. ``lost_frames``: indices reported lost (no pose). The
    local map changes every ``map_every_s`` and (``map_on_block_change``) whenever the block changes."""
    rng = np.random.default_rng(seed)
    n = int(round(duration_s * RATE_HZ))
    t = np.arange(n) / RATE_HZ
    poses = circle_pose(t)
    entries = block_entries()
    info = RunInfo(sequence="synthetic:circle", T_body_lidar=T_body_lidar(), map_kind="block",
                   map_entries=entries, tile_size_m=None,
                   ground_truth=ground_truth(duration_s) if with_gt else None,
                   config={"tracking": {"window_size": 20}, "map": {"block_blend_m": 15.0}}, out_dir=out_dir)
    events, last_block, last_map_t = [], None, -1e9
    for i in range(n):
        lost = i in lost_frames
        block = block_of(poses[i, :2, 3])
        switched = block != last_block and last_block is not None
        new_map = (map_on_block_change and block != last_block) or t[i] - last_map_t >= map_every_s
        local_map = None
        if new_map:
            last_map_t = t[i]
            c = np.array([e["centroid"] for e in entries if e["id"] == block][0])
            local_map = (c + rng.uniform(-20, 20, size=(map_points, 3)) * [1, 1, 0.3]).astype(np.float32)
        last_block = block
        scan = rng.uniform(-25, 25, size=(scan_points, 3)).astype(np.float32)
        scan[:, 2] *= 0.2
        diag = {"status": "lost" if lost else "ok", "fitness": float(0.3 + 0.1 * np.sin(i / 7.0)),
                "window_size": 5 if switched else 20, "switched": switched, "block_id": block,
                "num_points": scan_points, "update_ms": 20 + 5 * rng.random(), "registration_ms": 9.5,
                "smoother_ms": 4.25, "map_ms": 0.5, "deskew_ms": 1.0, "innovation_m": float("nan")}
        v_map = poses[i, :3, :3] @ np.array([SPEED_M_S, 0.0, 0.0])
        events.append(FrameEvent(index=i, stamp=T0_S + float(t[i]), T_map_body=None if lost else poses[i],
                                 covariance=None if lost else random_cov(rng), velocity_map=v_map,
                                 status="lost" if lost else "ok", diagnostics=diag,
                                 scan_lidar=None if lost else scan, local_map_points=local_map,
                                 local_map_id=f"region:{block}", active_entries=(block,)))
    return SyntheticRun(info, events)


def perturb(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """T * Exp(xi) to first order in the Pose3 tangent (rot, trans) used by FrameEvent.covariance."""
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ so3_exp(xi[:3])
    out[:3, 3] = T[:3, 3] + T[:3, :3] @ xi[3:]
    return out
