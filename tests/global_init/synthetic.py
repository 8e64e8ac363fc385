"""Small synthetic worlds for global-init tests: ground on a gentle slope plus box outlines."""

from __future__ import annotations

import numpy as np

from blockloc.geometry import inv_T, transform_points

# z-down map frame (NCLT, simulator) from a z-up world: (x, y, z) -> (x, -y, -z).
Z_DOWN = np.diag([1.0, -1.0, -1.0])
GRAVITY_Z_DOWN = np.array([0.0, 0.0, 9.81])


def box_outline(rng, cx, cy, w, d, h, angle, slope, per_m=60):
    n = int(per_m * 2 * (w + d))
    t = rng.uniform(0, 2 * (w + d), n)
    z = rng.uniform(0, h, n)
    x = np.where(t < w, t, np.where(t < w + d, w, np.where(t < 2 * w + d, 2 * w + d - t, 0.0))) - w / 2
    y = np.where(t < w, 0.0, np.where(t < w + d, t - w, np.where(t < 2 * w + d, d, 2 * (w + d) - t))) - d / 2
    c, s = np.cos(angle), np.sin(angle)
    X, Y = cx + c * x - s * y, cy + s * x + c * y
    return np.c_[X, Y, z + slope * X]


def world_up(seed=0, size=120.0, n_boxes=45, slope=0.02, ground_per_m2=15.0):
    """(N, 3) z-up points over [-size/2, size/2]^2: sloped ground plus random boxes."""
    rng = np.random.default_rng(seed)
    n_g = int(ground_per_m2 * size * size)
    g = rng.uniform(-size / 2, size / 2, (n_g, 2))
    parts = [np.c_[g, slope * g[:, 0] + rng.normal(0, 0.02, n_g)]]
    for _ in range(n_boxes):
        cx, cy = rng.uniform(-size / 2, size / 2, 2)
        w, d = rng.uniform(1, 8, 2)
        parts.append(box_outline(rng, cx, cy, w, d, rng.uniform(1, 5), rng.uniform(0, np.pi), slope))
    return np.concatenate(parts)


def periodic_world_up(period=12.0, length=240.0, seed=0):
    """A corridor of identical boxes every ``period`` metres along x: ambiguous along x."""
    rng = np.random.default_rng(seed)
    n_g = int(10.0 * length * 40)
    g = np.c_[rng.uniform(-length / 2, length / 2, n_g), rng.uniform(-20, 20, n_g)]
    parts = [np.c_[g, rng.normal(0, 0.02, n_g)]]
    for x in np.arange(-length / 2, length / 2, period):
        parts.append(box_outline(rng, x, 8.0, 3.0, 2.0, 3.0, 0.3, 0.0))
        parts.append(box_outline(rng, x + 4.0, -9.0, 2.0, 4.0, 3.0, -0.2, 0.0))
    return np.concatenate(parts)


def scan_from(world_map, T_map_body, radius=40.0, noise=0.02, seed=1):
    """Scan (N, 3) in the body frame: map points within ``radius`` (horizontal) plus noise."""
    rng = np.random.default_rng(seed)
    near = world_map[np.linalg.norm(world_map[:, :2] - T_map_body[:2, 3], axis=1) < radius]
    return transform_points(inv_T(T_map_body), near) + rng.normal(0, noise, near.shape)


def gravity_body(T_map_body, gravity_map=GRAVITY_Z_DOWN):
    return T_map_body[:3, :3].T @ gravity_map


def grid_store(path, pts, tile=30.0):
    """``pts`` (N, 3) written as a grid store of ``tile`` m tiles at ``path``; the opened store."""
    from blockloc.maps.store import MapWriter, open_map

    keys = np.floor(pts[:, :2] / tile).astype(int)
    with MapWriter(path, "grid", params={"tile_size_m": tile}) as w:
        for k in np.unique(keys, axis=0):
            w.add(f"{k[0]}_{k[1]}", pts[np.all(keys == k, axis=1)].astype(np.float32))
        w.commit()
    return open_map(path)

