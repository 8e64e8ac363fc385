"""Synthetic data for the tracking core: a point-cloud scene, an analytic trajectory, its exact IMU
readings and motion-distorted scans, plus small stand-ins for the map provider and registration.

Nothing here is a stub of behaviour under test: the IMU is derived from the trajectory by finite
differences of an analytic curve, and scans are scene points moved into the lidar frame at each
point's own time (real motion distortion).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.datasets.base import ImuData, LidarFrame
from blockloc.geometry import inv_T, rpy_to_R, so3_log, xyzrpy_to_T


# ----------------------------------------------------------------------------- scene
def make_scene(seed: int = 0, half_size: float = 60.0, spacing: float = 0.25) -> np.ndarray:
    """(N, 3) map points: a gently sloped ground, walls and boxes of random orientation."""
    rng = np.random.default_rng(seed)
    g = np.arange(-half_size, half_size, spacing * 2)
    gx, gy = np.meshgrid(g, g)
    ground = np.c_[gx.ravel(), gy.ravel(), 0.02 * gx.ravel() + 0.3 * np.sin(gy.ravel() / 15.0)]
    parts = [ground]
    for _ in range(60):
        cx, cy = rng.uniform(-half_size, half_size, 2)
        if abs(np.hypot(cx, cy) - 20.0) < 4.0:  # keep the driving circle clear
            continue
        length, height = rng.uniform(2, 10), rng.uniform(1.5, 6)
        yaw = rng.uniform(0, np.pi)
        s = np.arange(0, length, spacing)
        h = np.arange(0, height, spacing)
        ss, hh = np.meshgrid(s, h)
        wall = np.c_[ss.ravel() * np.cos(yaw) + cx, ss.ravel() * np.sin(yaw) + cy, hh.ravel()]
        wall[:, 2] += 0.02 * wall[:, 0] + 0.3 * np.sin(wall[:, 1] / 15.0)
        parts.append(wall)
        # a perpendicular wall so corners constrain every direction
        wall2 = np.c_[-ss.ravel() * np.sin(yaw) * 0.5 + cx, ss.ravel() * np.cos(yaw) * 0.5 + cy, hh.ravel()]
        wall2[:, 2] += 0.02 * wall2[:, 0] + 0.3 * np.sin(wall2[:, 1] / 15.0)
        parts.append(wall2)
    return np.concatenate(parts)


# ----------------------------------------------------------------------------- trajectory
@dataclass
class CircleTrajectory:
    """Analytic T_map_body(t): a circle of radius r at speed v, with small roll/pitch/z wiggles.

    z_up: when False the map is z down (NCLT convention) and gravity_map = (0, 0, +9.81).
    """

    radius: float = 20.0
    speed: float = 2.0
    z_up: bool = True

    @property
    def gravity_map(self) -> np.ndarray:
        return np.array([0.0, 0.0, -9.81 if self.z_up else 9.81])

    def pose(self, t) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        w = self.speed / self.radius
        a = w * t
        x, y = self.radius * np.cos(a), self.radius * np.sin(a)
        z = 1.0 + 0.02 * x + 0.3 * np.sin(y / 15.0) + 0.05 * np.sin(0.7 * t)
        yaw = a + np.pi / 2
        roll = 0.03 * np.sin(1.3 * t)
        pitch = 0.02 * np.sin(0.9 * t + 0.3)
        T = xyzrpy_to_T(x, y, z, roll, pitch, yaw)
        if not self.z_up:  # same motion seen from a z-down map: rotate the world by pi about x
            F = np.diag([1.0, -1.0, -1.0, 1.0])
            T = F[None] @ T @ F[None]
        return T

    def velocity(self, t, h: float = 1e-4) -> np.ndarray:
        return (self.pose(np.asarray(t) + h)[:, :3, 3] - self.pose(np.asarray(t) - h)[:, :3, 3]) / (2 * h)


def imu_from_trajectory(traj: CircleTrajectory, t0: float, t1: float, rate_hz: float = 100.0,
                        T_body_imu: np.ndarray = np.eye(4), acc_bias=(0.0, 0.0, 0.0), gyro_bias=(0.0, 0.0, 0.0),
                        noise: float = 0.0, seed: int = 0) -> ImuData:
    """Exact specific force and angular rate of the imu frame along ``traj`` (plus bias, noise)."""
    rng = np.random.default_rng(seed)
    t = np.arange(t0, t1, 1.0 / rate_hz)
    h = 1e-3
    Tm = traj.pose(t - h) @ T_body_imu
    T0 = traj.pose(t) @ T_body_imu
    Tp = traj.pose(t + h) @ T_body_imu
    acc_map = (Tp[:, :3, 3] - 2 * T0[:, :3, 3] + Tm[:, :3, 3]) / h**2
    R = T0[:, :3, :3]
    f = np.einsum("nji,nj->ni", R, acc_map - traj.gravity_map[None])
    gyro = so3_log(np.swapaxes(Tm[:, :3, :3], 1, 2) @ Tp[:, :3, :3]) / (2 * h)
    acc = f + np.asarray(acc_bias) + noise * rng.standard_normal(f.shape)
    gyro = gyro + np.asarray(gyro_bias) + 0.1 * noise * rng.standard_normal(gyro.shape)
    return ImuData(t, acc, gyro)


def make_scan(scene: np.ndarray, traj: CircleTrajectory, stamp: float, T_body_lidar: np.ndarray,
              index: int = 0, sweep_s: float = 0.1, max_range: float = 40.0, max_points: int = 30000,
              noise_m: float = 0.01, seed: int = 0) -> LidarFrame:
    """A motion-distorted sweep ending at ``stamp`` (offsets in [-sweep_s, 0])."""
    rng = np.random.default_rng(seed + index)
    T_map_lidar = traj.pose(stamp)[0] @ T_body_lidar
    local = (scene - T_map_lidar[:3, 3]) @ T_map_lidar[:3, :3]
    r = np.linalg.norm(local, axis=1)
    pick = np.flatnonzero((r > 1.5) & (r < max_range))
    if len(pick) > max_points:
        pick = rng.choice(pick, max_points, replace=False)
    az = np.arctan2(local[pick, 1], local[pick, 0])
    offsets = (az + np.pi) / (2 * np.pi) * sweep_s - sweep_s
    T_at = traj.pose(stamp + offsets) @ T_body_lidar
    T_inv = inv_T(T_at)
    pts = np.einsum("nij,nj->ni", T_inv[:, :3, :3], scene[pick]) + T_inv[:, :3, 3]
    pts += noise_m * rng.standard_normal(pts.shape)
    return LidarFrame(index, stamp, pts.astype(np.float32), None, offsets.astype(np.float32), None)


T_BODY_LIDAR = xyzrpy_to_T(0.1, -0.05, -0.8, 0.01, -0.02, 0.03)  # not identity, as on NCLT


# ----------------------------------------------------------------------------- stand-ins
class GicpRegistration:
    """small_gicp GICP behind the NDT engine's interface (same H, b convention)."""

    def __init__(self, max_correspondence_m: float = 1.0, num_threads: int = 1) -> None:
        self.max_corr = max_correspondence_m
        self.num_threads = num_threads

    def build_target(self, points: np.ndarray):
        import small_gicp

        return small_gicp.preprocess_points(np.asarray(points, np.float64), 0.3, num_threads=self.num_threads)

    def align(self, target, source_points, T_init):
        import small_gicp

        cloud, tree = target
        src, _ = small_gicp.preprocess_points(np.asarray(source_points, np.float64), 0.1,
                                              num_threads=self.num_threads)
        res = small_gicp.align(cloud, src, tree, np.asarray(T_init), registration_type="GICP",
                               max_correspondence_distance=self.max_corr, num_threads=self.num_threads)
        return _Result(res.T_target_source, res.converged, res.num_inliers / max(src.size(), 1), res.H, res.b)


@dataclass
class _Result:
    T_target_source: np.ndarray
    converged: bool
    fitness: float
    H: np.ndarray
    b: np.ndarray


@dataclass
class LocalMap:
    target: object
    switched: bool = False
    block_id: int = 0


class ScriptedProvider:
    """One target for the whole scene; reports a switch on the frames (by call count) listed.

    A call for a stamp not after the last one (the tracker registering the first scans again once
    it knows the velocity) is not counted: it reports no switch."""

    def __init__(self, target, switch_calls=()) -> None:
        self.target = target
        self.switch_calls = set(switch_calls)
        self.calls = 0
        self.block = 0
        self._last_stamp = -np.inf

    def update(self, position_map, velocity_map, stamp):
        if stamp <= self._last_stamp:
            return LocalMap(self.target, False, self.block)
        self._last_stamp = stamp
        switched = self.calls in self.switch_calls
        self.calls += 1
        if switched:
            self.block += 1
        return LocalMap(self.target, switched, self.block)
