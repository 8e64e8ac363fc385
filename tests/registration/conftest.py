"""Fixtures for the NDT tests: the real HDL-32E pair and a synthetic scene."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.voxels import voxel_downsample


def read_pcd_xyz(path) -> np.ndarray:
    from pypcd4 import PointCloud

    pc = PointCloud.from_path(str(path))
    arr = pc.numpy(("x", "y", "z"))
    return np.asarray(arr, dtype=np.float64)


@pytest.fixture(scope="session")
def hdl_pair(shared_data):
    """(target (N,3), source downsampled at 0.5 m (M,3), T_target_source reference (4,4))."""
    d = shared_data / "hdl32e_pair"
    target = read_pcd_xyz(d / "target.pcd")
    source = read_pcd_xyz(d / "source.pcd")
    T_ref = np.loadtxt(d / "T_target_source.txt")
    return target, voxel_downsample(source, 0.5)[0], T_ref


def synthetic_scene(seed: int = 0, n_per_m2: float = 40.0) -> np.ndarray:
    """Points (N, 3) on a floor, walls of a 40 x 30 m yard and a few boxes, 1 cm noise."""
    rng = np.random.default_rng(seed)
    pts = []

    def plane(origin, e1, e2, l1, l2):
        n = int(l1 * l2 * n_per_m2)
        a = rng.uniform(0, l1, n)[:, None]
        b = rng.uniform(0, l2, n)[:, None]
        pts.append(np.asarray(origin) + a * np.asarray(e1) + b * np.asarray(e2))

    X, Y, Z = np.eye(3)
    plane([-20, -15, 0], X, Y, 40, 30)  # floor
    plane([-20, -15, 0], X, Z, 40, 4)  # walls
    plane([-20, 15, 0], X, Z, 40, 4)
    plane([-20, -15, 0], Y, Z, 30, 4)
    plane([20, -15, 0], Y, Z, 30, 4)
    for cx, cy, sx, sy, h in [(-8, -5, 3, 2, 2.5), (6, 4, 2, 4, 1.5), (10, -8, 1.5, 1.5, 3.0),
                              (-12, 9, 4, 1, 2.0), (2, -10, 1, 1, 1.0)]:
        x0, y0 = cx - sx / 2, cy - sy / 2
        plane([x0, y0, 0], X, Z, sx, h)
        plane([x0, y0 + sy, 0], X, Z, sx, h)
        plane([x0, y0, 0], Y, Z, sy, h)
        plane([x0 + sx, y0, 0], Y, Z, sy, h)
        plane([x0, y0, h], X, Y, sx, sy)
    cloud = np.concatenate(pts)
    return cloud + rng.normal(0, 0.01, cloud.shape)


@pytest.fixture(scope="session")
def scene():
    return synthetic_scene()


@pytest.fixture(scope="session")
def make_scene():
    """The scene generator, for independent samples of the same surfaces."""
    return synthetic_scene
