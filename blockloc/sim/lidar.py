"""Velodyne HDL-32E model: 32 beams, 10 Hz spin, per-column firing times, motion distortion.

Frames: the lidar frame is NCLT's velodyne frame (z DOWN, as the devkit's points are; the
sensor spins clockwise seen from above, i.e. the azimuth atan2(y, x) grows with time).
Each azimuth column is cast from the lidar pose at its own firing time, and its points are
reported in the lidar frame of that instant: a sweep read without deskewing shows the motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.sim.presets import LidarModel

#: Elevation (deg, up positive) of HDL-32E lasers 0..31 in firing order (Velodyne manual).
HDL32E_ELEVATION_DEG = np.array([
    -30.67, -9.33, -29.33, -8.00, -28.00, -6.67, -26.67, -5.33, -25.33, -4.00, -24.00, -2.67,
    -22.67, -1.33, -21.33, 0.00, -20.00, 1.33, -18.67, 2.67, -17.33, 4.00, -16.00, 5.33,
    -14.67, 6.67, -13.33, 8.00, -12.00, 9.33, -10.67, 10.67])


@dataclass
class ScanResult:
    """One simulated sweep (before writing).

    points: (N, 3) float64, lidar frame at each point's own time, metres.
    intensity: (N,) float32 0..255. ring: (N,) uint16 laser id. time_offsets: (N,) float32 s
    from the sweep start. category: (N,) int, index into the scene's ``categories`` (for tests).
    """

    points: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    time_offsets: np.ndarray
    category: np.ndarray


def beam_directions(azimuth_steps: int, az0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (A, 32, 3) in the lidar frame (z down) and column azimuths (A,) rad."""
    az = az0 + 2.0 * np.pi * np.arange(azimuth_steps) / azimuth_steps
    el = np.deg2rad(HDL32E_ELEVATION_DEG)
    ce, se = np.cos(el), np.sin(el)
    d = np.empty((azimuth_steps, 32, 3))
    d[..., 0] = np.cos(az)[:, None] * ce
    d[..., 1] = np.sin(az)[:, None] * ce
    d[..., 2] = -se  # z down: an upward beam has negative z
    return d, az


def simulate_scan(scene, T_world_lidar_cols: np.ndarray, col_offsets: np.ndarray,
                  model: LidarModel, rng: np.random.Generator, t_mid: float | None,
                  az0: float = 0.0) -> ScanResult:
    """Cast one sweep.

    scene: ``SessionScene``. T_world_lidar_cols: (A, 4, 4) lidar pose at each column's firing
    time (world, z up). col_offsets: (A,) s from sweep start. t_mid: session time at which
    moving actors are placed (None: no actors). rng: the frame's generator (noise, dropouts).
    """
    A = len(col_offsets)
    d_lidar, _ = beam_directions(A, az0)
    R = T_world_lidar_cols[:, :3, :3]
    dirs = np.matmul(d_lidar, R.transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat(T_world_lidar_cols[:, :3, 3], 32, axis=0)
    rng_true, normals, albedo, cat = scene.cast(origins, dirs, t_mid, model.max_range_m)
    n = len(rng_true)
    cosi = np.abs((normals * dirs).sum(axis=1))
    noise = rng.normal(0.0, model.range_noise_m, n)
    u_drop = rng.random(n)
    u_graze = rng.random(n)
    i_noise = rng.normal(0.0, 2.0, n)
    r = rng_true + noise
    ok = np.isfinite(rng_true) & (rng_true <= model.max_range_m) & (r >= model.min_range_m)
    ok &= u_drop >= model.dropout_prob
    ok &= ~((cosi < model.grazing_dropout_cos) & (u_graze < 0.5))
    idx = np.flatnonzero(ok)
    pts = d_lidar.reshape(-1, 3)[idx] * r[idx, None]
    inten = 255.0 * albedo[idx] * (0.25 + 0.75 * cosi[idx]) * np.exp(-r[idx] / 150.0) + i_noise[idx]
    ring = np.tile(np.arange(32, dtype=np.uint16), A)[idx]
    toff = np.repeat(col_offsets.astype(np.float32), 32)[idx]
    return ScanResult(pts, np.clip(inten, 1.0, 255.0).astype(np.float32), ring, toff, cat[idx])
