"""The terrain: a smooth (C2) height field and its triangle mesh (world frame, z up, metres)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.sim.presets import Preset


def smootherstep(u: np.ndarray) -> np.ndarray:
    """Quintic 0..1 step, C2 (zero first and second derivative at both ends)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (u * (u * 6.0 - 15.0) + 10.0)


def smootherstep_d(u: np.ndarray) -> np.ndarray:
    """d/du of ``smootherstep``: 30 u^2 (1-u)^2 on [0, 1], 0 outside; integrates to 1."""
    inside = (u > 0.0) & (u < 1.0)
    return np.where(inside, 30.0 * u * u * (1.0 - u) ** 2, 0.0)


@dataclass
class Terrain:
    """Smooth (C2) height field h(x, y) = sum of long sine waves + a few quintic ramps.

    waves: (K, 4) amplitude m, kx, ky rad/m, phase rad. ramps: (R, 5) ux, uy (unit normal of
    the ramp line), offset m (line position along u), width m, rise m.
    """

    waves: np.ndarray
    ramps: np.ndarray

    def height_grad(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height h and gradient (dh/dx, dh/dy) at (x, y), any broadcastable shapes, metres."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        shape = np.broadcast(x, y).shape
        x = np.broadcast_to(x, shape)[..., None]
        y = np.broadcast_to(y, shape)[..., None]
        a, kx, ky, ph = self.waves.T
        arg = kx * x + ky * y + ph
        h = (a * np.sin(arg)).sum(axis=-1)
        c = a * np.cos(arg)
        hx = (c * kx).sum(axis=-1)
        hy = (c * ky).sum(axis=-1)
        if len(self.ramps):
            ux, uy, off, width, rise = self.ramps.T
            u = (ux * x + uy * y - off) / width
            h = h + (rise * smootherstep(u)).sum(axis=-1)
            d = rise * smootherstep_d(u) / width
            hx = hx + (d * ux).sum(axis=-1)
            hy = hy + (d * uy).sum(axis=-1)
        return h, hx, hy

    def height(self, x, y) -> np.ndarray:
        return self.height_grad(x, y)[0]


def make_terrain(rng: np.random.Generator, preset: Preset) -> Terrain:
    sx, sy = preset.size_m
    waves = []
    for k in range(4):
        wl = rng.uniform(0.5, 1.5) * max(sx, sy) / (1.0 + k)  # long wavelengths: gentle slopes
        ang = rng.uniform(0, np.pi)
        kk = 2 * np.pi / wl
        amp = preset.terrain_amplitude_m * rng.uniform(0.3, 1.0) / (1.0 + 0.5 * k)
        waves.append((amp, kk * np.cos(ang), kk * np.sin(ang), rng.uniform(0, 2 * np.pi)))
    ramps = []
    for _ in range(preset.n_ramps):
        ang = rng.uniform(0, 2 * np.pi)
        off = rng.uniform(-0.35, 0.35) * min(sx, sy)
        ramps.append((np.cos(ang), np.sin(ang), off, rng.uniform(10.0, 18.0),
                      rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.6)))  # slopes up to ~8 deg
    return Terrain(np.array(waves), np.array(ramps).reshape(-1, 5))



def terrain_mesh(terrain: Terrain, xmin, xmax, ymin, ymax, res) -> tuple[np.ndarray, np.ndarray]:
    nx = int(np.ceil((xmax - xmin) / res)) + 1
    ny = int(np.ceil((ymax - ymin) / res)) + 1
    xs = np.linspace(xmin, xmax, nx)
    ys = np.linspace(ymin, ymax, ny)
    X, Y = np.meshgrid(xs, ys, indexing="xy")
    Z = terrain.height(X, Y)
    V = np.c_[X.ravel(), Y.ravel(), Z.ravel()]
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.c_[a, b, d], np.c_[a, d, c]])
    return V, F

