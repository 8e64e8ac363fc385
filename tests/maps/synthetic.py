"""A tiny synthetic world and an in-memory Sequence for map tests (no simulator needed)."""

from __future__ import annotations

import numpy as np

from blockloc.datasets.base import LidarFrame, SequenceInfo
from blockloc.geometry import Trajectory, inv_T, xyzrpy_to_T


def world_points(extent=(-20.0, 220.0), seed=0, density=0.5):
    """Ground plane plus random box-like pillars over a square (map frame, metres)."""
    rng = np.random.default_rng(seed)
    lo, hi = extent
    n_ground = int((hi - lo) ** 2 * density)
    ground = np.c_[rng.uniform(lo, hi, (n_ground, 2)), rng.normal(0, 0.02, n_ground)]
    pillars = []
    for c in rng.uniform(lo, hi, (150, 2)):
        m = 300
        pillars.append(np.c_[c + rng.uniform(-1, 1, (m, 2)), rng.uniform(0, 5, m)])
    return np.concatenate([ground] + pillars)


def route(waypoints, speed=5.0, rate=10.0, t0=100.0):
    """Poses (T_map_body) at ``rate`` Hz along straight segments through ``waypoints`` (x, y)."""
    wp = np.asarray(waypoints, float)
    pos, yaw = [], []
    for a, b in zip(wp[:-1], wp[1:]):
        L = np.linalg.norm(b - a)
        n = max(int(L / speed * rate), 1)
        s = np.arange(n) / n
        pos.append(a + s[:, None] * (b - a))
        yaw.append(np.full(n, np.arctan2(*(b - a)[::-1])))
    pos = np.concatenate(pos + [wp[-1:]])
    yaw = np.concatenate(yaw + [yaw[-1][-1:]])
    T = xyzrpy_to_T(pos[:, 0], pos[:, 1], np.zeros(len(pos)), 0 * yaw, 0 * yaw, yaw)
    return Trajectory(t0 + np.arange(len(pos)) / rate, T)


class MemorySequence:
    """Scans = world points within ``radius`` of the sensor, in the lidar frame."""

    def __init__(self, world, traj, radius=30.0, T_body_lidar=None, with_poses=True, name="synthetic"):
        self.world = world
        self.traj = traj
        self.radius = radius
        T_bl = np.eye(4) if T_body_lidar is None else T_body_lidar
        self.info = SequenceInfo(name, T_body_lidar=T_bl)
        self.with_poses = with_poses

    def __len__(self):
        return len(self.traj)

    def frame_stamps(self):
        return self.traj.stamps.copy()

    def frame(self, index):
        T_map_lidar = self.traj.poses[index] @ self.info.T_body_lidar
        near = np.linalg.norm(self.world[:, :2] - T_map_lidar[:2, 3], axis=1) < self.radius
        pts = self.world[near]
        local = (pts - T_map_lidar[:3, 3]) @ T_map_lidar[:3, :3]
        return LidarFrame(index, float(self.traj.stamps[index]), local.astype(np.float32),
                          np.full(len(local), 7.0, np.float32), None, None)

    def frames(self, start=0, stop=None):
        for i in range(start, len(self) if stop is None else stop):
            yield self.frame(i)

    def imu(self):
        raise NotImplementedError

    def ground_truth(self):
        return self.traj if self.with_poses else None

    def mapping_poses(self):
        return self.traj if self.with_poses else None
