"""Synthetic sweeps for the loader/writer tests (deterministic, small)."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.datasets.base import ImuData, LidarFrame
from blockloc.geometry import Trajectory, xyzrpy_to_T


def make_frame(index: int, stamp: float, n: int = 4000, seed: int = 0) -> LidarFrame:
    """A sweep-like frame: points ordered by azimuth, times spanning 0.1 s before ``stamp``."""
    rng = np.random.default_rng(seed + index)
    az = np.sort(rng.uniform(0.0, 2 * np.pi, n))
    rng_m = rng.uniform(2.0, 80.0, n)
    el = rng.uniform(-0.53, 0.18, n)
    pts = np.stack([rng_m * np.cos(el) * np.cos(az), rng_m * np.cos(el) * np.sin(az),
                    rng_m * np.sin(el)], axis=1)
    offsets = (az / (2 * np.pi) * 0.1 - 0.1).astype(np.float32)
    return LidarFrame(index, stamp, pts, rng.uniform(0, 255, n).astype(np.float32), offsets,
                      rng.integers(0, 32, n).astype(np.uint16))


def make_imu(t0: float, t1: float, rate: float = 100.0, seed: int = 1) -> ImuData:
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(int(round((t1 - t0) * rate))) / rate
    return ImuData(t, rng.normal(0, 1, (len(t), 3)) + [0, 0, -9.81], rng.normal(0, 0.1, (len(t), 3)))


def make_traj(t0: float, t1: float, rate: float = 100.0, seed: int = 2) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(int(round((t1 - t0) * rate))) / rate
    x = np.cumsum(rng.normal(0, 0.01, (6, len(t))), axis=1)
    return Trajectory(t, xyzrpy_to_T(x[0] * 50, x[1] * 50, x[2], x[3], x[4], x[5] * 10))


@pytest.fixture
def session_data():
    t0 = 1326030000.0  # an NCLT-like epoch (2012)
    frames = [make_frame(i, t0 + 0.1 * (i + 1)) for i in range(4)]
    return dict(frames=frames, imu=make_imu(t0, t0 + 0.6), gt=make_traj(t0, t0 + 0.6),
                slam=make_traj(t0, t0 + 0.6, seed=3))
