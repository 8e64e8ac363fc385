"""Random but smooth SE(3) trajectories for the evaluation tests (imported by them)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from blockloc.geometry import Trajectory


def random_trajectory(rng: np.random.Generator, n: int = 400, dt: float = 0.1, t0: float = 1000.0,
                      speed: float = 1.2) -> Trajectory:
    """A wandering 3D path (n poses, dt s apart) with yaw following the heading and small roll/pitch."""
    yaw = np.cumsum(rng.normal(0.0, 0.08, n))
    step = speed * dt * np.stack([np.cos(yaw), np.sin(yaw), rng.normal(0.0, 0.05, n)], axis=1)
    pos = np.cumsum(step, axis=0) + rng.normal(0.0, 5.0, 3)
    rpy = np.stack([rng.normal(0, 0.05, n), rng.normal(0, 0.05, n), yaw], axis=1)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    poses[:, :3, 3] = pos
    return Trajectory(t0 + dt * np.arange(n), poses)


def perturb(rng: np.random.Generator, traj: Trajectory, sigma_t: float = 0.1, sigma_r_rad: float = 0.02,
            T_offset: np.ndarray | None = None) -> Trajectory:
    """traj with per-pose noise (metres, radians) and optionally a global transform applied on the left."""
    poses = traj.poses.copy()
    noise = Rotation.from_rotvec(rng.normal(0.0, sigma_r_rad, (len(traj), 3))).as_matrix()
    poses[:, :3, :3] = poses[:, :3, :3] @ noise
    poses[:, :3, 3] += rng.normal(0.0, sigma_t, (len(traj), 3))
    if T_offset is not None:
        poses = T_offset @ poses
    return Trajectory(traj.stamps.copy(), poses)


