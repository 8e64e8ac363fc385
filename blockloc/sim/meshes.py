"""Mesh primitives of the procedural world (world frame, z up, metres): (V, 3) float64 vertices
and (F, 3) int64 triangles, and the reflectance of each surface category."""

from __future__ import annotations

import functools

import numpy as np

#: Lambertian reflectance at 905 nm per surface category (0..1), used for intensity. Asphalt
#: is dark, vegetation bright in the near infrared; buildings get their own (``Facade``).
ALBEDO = {"terrain": 0.3, "road": 0.09, "building": 0.3, "wall": 0.25, "fence": 0.35,
          "pole": 0.3, "trunk": 0.12, "crown": 0.35, "car": 0.25, "bin": 0.2,
          "pedestrian": 0.15, "vehicle": 0.25, "sign": 0.5, "ceiling": 0.3, "self": 0.15,
          "foliage": 0.4, "sidewalk": 0.22, "grass": 0.35, "glass": 0.05}
#: Reflectance by ground material code (``World.ground_material``: road, sidewalk, grass, footpath).
GROUND_ALBEDO = np.array([ALBEDO["road"], ALBEDO["sidewalk"], ALBEDO["grass"], ALBEDO["sidewalk"]])


class MeshBuilder:
    """Accumulates triangles of one surface category."""

    def __init__(self) -> None:
        self.verts: list[np.ndarray] = []
        self.tris: list[np.ndarray] = []
        self.n = 0

    def add(self, V: np.ndarray, F: np.ndarray) -> None:
        self.verts.append(np.asarray(V, dtype=np.float64))
        self.tris.append(np.asarray(F, dtype=np.int64) + self.n)
        self.n += len(V)

    def build(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.verts:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        return np.concatenate(self.verts), np.concatenate(self.tris)


_BOX_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                   [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def box_mesh(cx, cy, z0, z1, lx, ly, yaw) -> tuple[np.ndarray, np.ndarray]:
    """An oriented box: centre (cx, cy), z from z0 to z1, length lx along yaw, width ly."""
    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.array([[-lx, -ly], [lx, -ly], [lx, ly], [-lx, ly]]) * 0.5
    xy = corners @ np.array([[c, s], [-s, c]]) + [cx, cy]
    V = np.empty((8, 3))
    V[:4, :2] = V[4:, :2] = xy
    V[:4, 2], V[4:, 2] = z0, z1
    return V, _BOX_F


@functools.lru_cache(maxsize=8)
def _cylinder_template(n: int) -> tuple[np.ndarray, np.ndarray]:
    a = np.arange(n) * 2 * np.pi / n
    i = np.arange(n)
    j = (i + 1) % n
    F = np.concatenate([np.c_[i, j, n + j], np.c_[i, n + j, n + i], np.c_[n + i, n + j, np.full(n, 2 * n)]])
    return np.c_[np.cos(a), np.sin(a)], F


def cylinder_mesh(cx, cy, z0, z1, r, n=8) -> tuple[np.ndarray, np.ndarray]:
    cs, F = _cylinder_template(n)
    V = np.empty((2 * n + 1, 3))
    V[:n, :2] = V[n:2 * n, :2] = cs * r + [cx, cy]
    V[:n, 2], V[n:, 2] = z0, z1
    V[2 * n, :2] = cx, cy
    return V, F


def _icosphere() -> tuple[np.ndarray, np.ndarray]:
    t = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
                  [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=float)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    # one subdivision: 80 faces
    verts = list(V / np.linalg.norm(V, axis=1)[:, None])
    cache: dict[tuple[int, int], int] = {}

    def mid(a, b):
        key = (min(a, b), max(a, b))
        if key not in cache:
            m = verts[a] + verts[b]
            verts.append(m / np.linalg.norm(m))
            cache[key] = len(verts) - 1
        return cache[key]

    out = []
    for a, b, c in F:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        out += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
    return np.array(verts), np.array(out)


_ICO_V, _ICO_F = _icosphere()


def ellipsoid_mesh(cx, cy, cz, rxy, rz) -> tuple[np.ndarray, np.ndarray]:
    return _ICO_V * [rxy, rxy, rz] + [cx, cy, cz], _ICO_F

