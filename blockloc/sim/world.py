"""Procedural world: terrain, road grid, buildings, vegetation, street furniture, movable objects.

Frame: the world is modelled z UP (x east, y north, metres, centred on the origin); the NCLT
map frame (z down) is ``T_map_world = diag(1, -1, -1)`` (see ``blockloc.sim.trajectory``).

Everything is generated from ``(preset, seed)`` alone, as plain numpy arrays (no I/O); meshes are
(V, 3) float64 vertices and (F, 3) int64 triangles. ``session_movables`` gives each session's
"day": a deterministic share of the movable objects moved, removed or added.
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass, field

import numpy as np

from blockloc.sim.presets import Preset

log = logging.getLogger(__name__)

#: Lambertian albedo per surface category, used for intensity (0..1).
ALBEDO = {"terrain": 0.45, "road": 0.22, "building": 0.6, "wall": 0.5, "fence": 0.8,
          "pole": 0.85, "trunk": 0.3, "crown": 0.35, "car": 0.7, "bin": 0.5,
          "pedestrian": 0.4, "vehicle": 0.75}

MOVABLE_KINDS = ("car", "bin")


def stable_hash(text: str) -> int:
    """A process-independent 32-bit hash of ``text`` (Python's hash() is salted)."""
    return zlib.crc32(text.encode("utf-8"))


def smootherstep(u: np.ndarray) -> np.ndarray:
    """Quintic 0..1 step, C2 (zero first and second derivative at both ends)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (u * (u * 6.0 - 15.0) + 10.0)


def smootherstep_d(u: np.ndarray) -> np.ndarray:
    """d/du of ``smootherstep``: 30 u^2 (1-u)^2 on [0, 1], 0 outside; integrates to 1."""
    inside = (u > 0.0) & (u < 1.0)
    return np.where(inside, 30.0 * u * u * (1.0 - u) ** 2, 0.0)


# --- terrain ----------------------------------------------------------------------------------

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
        h = np.zeros(np.broadcast(x, y).shape)
        hx = np.zeros_like(h)
        hy = np.zeros_like(h)
        for a, kx, ky, ph in self.waves:
            arg = kx * x + ky * y + ph
            h += a * np.sin(arg)
            c = a * np.cos(arg)
            hx += c * kx
            hy += c * ky
        for ux, uy, off, width, rise in self.ramps:
            u = (ux * x + uy * y - off) / width
            h += rise * smootherstep(u)
            d = rise * smootherstep_d(u) / width
            hx += d * ux
            hy += d * uy
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


# --- mesh primitives ---------------------------------------------------------------------------

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
    V = np.concatenate([np.c_[xy, np.full(4, z0)], np.c_[xy, np.full(4, z1)]])
    return V, _BOX_F


def cylinder_mesh(cx, cy, z0, z1, r, n=8) -> tuple[np.ndarray, np.ndarray]:
    a = np.arange(n) * 2 * np.pi / n
    ring = np.c_[cx + r * np.cos(a), cy + r * np.sin(a)]
    V = np.concatenate([np.c_[ring, np.full(n, z0)], np.c_[ring, np.full(n, z1)], [[cx, cy, z1]]])
    i = np.arange(n)
    j = (i + 1) % n
    F = np.concatenate([np.c_[i, j, n + j], np.c_[i, n + j, n + i], np.c_[n + i, n + j, np.full(n, 2 * n)]])
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


# --- layout -----------------------------------------------------------------------------------

@dataclass
class Roads:
    """A grid of straight roads: north-south lines at x = xs, east-west lines at y = ys.

    Graph nodes are the intersections (i, j) at (xs[i], ys[j]); edges join grid neighbours.
    """

    xs: np.ndarray
    ys: np.ndarray
    width_m: float

    def node_xy(self, node: tuple[int, int]) -> np.ndarray:
        return np.array([self.xs[node[0]], self.ys[node[1]]])

    def neighbours(self, node: tuple[int, int]) -> list[tuple[int, int]]:
        i, j = node
        out = []
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            if 0 <= i + di < len(self.xs) and 0 <= j + dj < len(self.ys):
                out.append((i + di, j + dj))
        return out

    def distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Distance (m) from (x, y) to the nearest road centre line."""
        return np.minimum(_nearest_gap(np.asarray(x, float), self.xs),
                          _nearest_gap(np.asarray(y, float), self.ys))


def _nearest_gap(v: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """|v - nearest of the sorted ``lines``|, elementwise."""
    k = np.clip(np.searchsorted(lines, v), 1, len(lines) - 1) if len(lines) > 1 else np.zeros(v.shape, int)
    lo = np.abs(v - lines[k - 1]) if len(lines) > 1 else np.abs(v - lines[0])
    return np.minimum(lo, np.abs(v - lines[k]))


def _road_lines(rng, extent, spacing) -> np.ndarray:
    n = max(2, int(round(extent / spacing)) - 1)
    base = np.linspace(-extent / 2, extent / 2, n + 2)[1:-1]
    gap = extent / (n + 1)
    return np.sort(base + rng.uniform(-0.12, 0.12, n) * gap)


@dataclass
class Movables:
    """Objects that change between sessions. kind: (M,) str ('car' | 'bin'); xy: (M, 2);
    yaw: (M,); uid: (M,) int, stable across sessions (added objects get new uids)."""

    kind: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    uid: np.ndarray

    def __len__(self) -> int:
        return len(self.uid)


@dataclass
class World:
    """A generated world (z up). ``meshes``: category -> (V, F) of the static scene."""

    preset: Preset
    seed: int
    terrain: Terrain
    roads: Roads
    meshes: dict[str, tuple[np.ndarray, np.ndarray]]
    movables: Movables
    cells: list[dict] = field(default_factory=list)
    corridors: list[dict] = field(default_factory=list)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        sx, sy = self.preset.size_m
        return (-sx / 2, sx / 2, -sy / 2, sy / 2)

    def ground_albedo(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        on_road = self.roads.distance(x, y) < self.roads.width_m / 2
        return np.where(on_road, ALBEDO["road"], ALBEDO["terrain"])

    def num_triangles(self) -> int:
        return int(sum(len(F) for _, F in self.meshes.values()))


def build_world(preset: Preset, seed: int) -> World:
    """Generate the static world and the base set of movable objects from ``(preset, seed)``."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), stable_hash(preset.name), 1]))
    sx, sy = preset.size_m
    terrain = make_terrain(rng, preset)
    roads = Roads(_road_lines(rng, sx, preset.road_spacing_m[0]),
                  _road_lines(rng, sy, preset.road_spacing_m[1]), preset.road_width_m)
    hw = roads.width_m / 2
    b = {k: MeshBuilder() for k in ("building", "wall", "fence", "pole", "trunk", "crown")}
    mov_kind, mov_xy, mov_yaw = [], [], []
    H = terrain.height

    # corridors: long parallel walls on both sides of some east-west road edges
    corridors = []
    n_corr = 1 if len(roads.xs) < 4 else 3
    cand = [(i, j) for i in range(len(roads.xs) - 1) for j in range(len(roads.ys))]
    for ci in rng.choice(len(cand), size=min(n_corr, len(cand)), replace=False):
        i, j = cand[ci]
        x0, x1 = roads.xs[i] + hw + 4.0, roads.xs[i + 1] - hw - 4.0
        y = roads.ys[j]
        if x1 - x0 < 20:
            continue
        corridors.append({"x0": x0, "x1": x1, "y": y})
        for side in (-1, 1):
            yw = y + side * (hw + 0.6)
            n_seg = int(np.ceil((x1 - x0) / 10.0))
            for k in range(n_seg):  # segments follow the terrain
                a0 = x0 + (x1 - x0) * k / n_seg
                a1 = x0 + (x1 - x0) * (k + 1) / n_seg
                hs = H(np.array([a0, a1]), np.array([yw, yw]))
                b["wall"].add(*box_mesh((a0 + a1) / 2, yw, hs.min() - 0.5, hs.max() + 3.5,
                                        a1 - a0 + 0.02, 0.3, 0.0))

    def in_corridor_strip(x, y):
        return any(c["x0"] - 2 <= x <= c["x1"] + 2 and abs(y - c["y"]) < hw + 9.0 for c in corridors)

    # cells between road lines (and the world border)
    xl = np.concatenate([[-sx / 2 - hw], roads.xs, [sx / 2 + hw]])
    yl = np.concatenate([[-sy / 2 - hw], roads.ys, [sy / 2 + hw]])
    cells = []
    kinds = ["buildings", "park", "parking", "field"]
    probs = [0.5, 0.2, 0.15, 0.15]
    ncell = (len(xl) - 1) * (len(yl) - 1)
    types = list(rng.choice(kinds, size=ncell, p=probs))
    # every world has at least one open field, one parking and two building cells
    perm = rng.permutation(ncell)
    for k, forced in zip(perm[:4], ["field", "parking", "buildings", "buildings"]):
        types[k] = forced
    setback = 6.0
    for ix in range(len(xl) - 1):
        for iy in range(len(yl) - 1):
            ctype = str(types[ix * (len(yl) - 1) + iy])
            cx0, cx1 = xl[ix] + hw, xl[ix + 1] - hw
            cy0, cy1 = yl[iy] + hw, yl[iy + 1] - hw
            ix0, ix1, iy0, iy1 = cx0 + setback, cx1 - setback, cy0 + setback, cy1 - setback
            cells.append({"type": ctype, "rect": (cx0, cx1, cy0, cy1)})
            if ix1 - ix0 < 6 or iy1 - iy0 < 6:
                continue
            # street furniture in the setback strip: poles, street trees
            if ctype != "field":
                for (ax, ay, bx, by) in ((cx0, cy0 + 1.5, cx1, cy0 + 1.5), (cx0, cy1 - 1.5, cx1, cy1 - 1.5),
                                         (cx0 + 1.5, cy0, cx0 + 1.5, cy1), (cx1 - 1.5, cy0, cx1 - 1.5, cy1)):
                    L = np.hypot(bx - ax, by - ay)
                    step = rng.uniform(22, 35)
                    for s in np.arange(rng.uniform(3, step), L - 3, step):
                        px, py = ax + (bx - ax) * s / L, ay + (by - ay) * s / L
                        if in_corridor_strip(px, py):
                            continue
                        z = H(px, py)
                        if rng.random() < 0.5:
                            b["pole"].add(*cylinder_mesh(px, py, z - 0.3, z + rng.uniform(5, 8), 0.12))
                        elif ctype in ("park", "buildings"):
                            _tree(b, rng, px + rng.uniform(-1, 1), py + rng.uniform(-1, 1), H)
            if ctype == "buildings":
                _buildings(b, rng, (ix0, ix1, iy0, iy1), H, preset)
            elif ctype == "park":
                area = (ix1 - ix0) * (iy1 - iy0)
                for _ in range(int(area / rng.uniform(120, 250))):
                    _tree(b, rng, rng.uniform(ix0, ix1), rng.uniform(iy0, iy1), H)
                for _ in range(int(area / 400) + 1):
                    mov_kind.append("bin")
                    mov_xy.append((rng.uniform(ix0, ix1), rng.uniform(iy0, iy1)))
                    mov_yaw.append(rng.uniform(0, np.pi))
            elif ctype == "parking":
                # rows of parking places along x; ~70% occupied
                yaw = 0.0 if rng.random() < 0.5 else np.pi / 2
                for py in np.arange(iy0 + 3, iy1 - 3, 12.0):
                    for px in np.arange(ix0 + 2, ix1 - 2, 2.8):
                        for dy in (-2.6, 2.6):
                            if rng.random() < 0.7:
                                mov_kind.append("car")
                                mov_xy.append((px, py + dy))
                                mov_yaw.append(np.pi / 2 + rng.normal(0, 0.05))
                del yaw
                if rng.random() < 0.7:
                    _fence(b, rng, (ix0 - 2, ix1 + 2, iy0 - 2, iy1 + 2), H, in_corridor_strip)
            # cars parked along the kerb (movable) beside non-field cells
            if ctype != "field":
                for y_k, sgn in ((cy0, 1), (cy1, -1)):
                    for px in np.arange(cx0 + 8, cx1 - 8, 6.0):
                        if rng.random() < 0.25 and not in_corridor_strip(px, y_k):
                            mov_kind.append("car")
                            mov_xy.append((px, y_k + sgn * 1.2))
                            mov_yaw.append(rng.normal(0, 0.03))

    ext = preset.terrain_margin_m
    meshes = {"terrain": terrain_mesh(terrain, -sx / 2 - ext, sx / 2 + ext, -sy / 2 - ext,
                                      sy / 2 + ext, preset.terrain_res_m)}
    for k, mb in b.items():
        V, F = mb.build()
        if len(F):
            meshes[k] = (V, F)
    movables = Movables(np.array(mov_kind, dtype="<U8"), np.array(mov_xy, dtype=float).reshape(-1, 2),
                        np.array(mov_yaw, dtype=float), np.arange(len(mov_kind)))
    world = World(preset, int(seed), terrain, roads, meshes, movables, cells, corridors)
    log.debug("world %s/%d: %d triangles, %d movables", preset.name, seed, world.num_triangles(),
              len(movables))
    return world


def _tree(b, rng, x, y, H) -> None:
    z = H(x, y)
    h_trunk = rng.uniform(1.8, 3.2)
    r = rng.uniform(1.3, 3.0)
    b["trunk"].add(*cylinder_mesh(x, y, z - 0.3, z + h_trunk + 0.5 * r, rng.uniform(0.12, 0.3), n=6))
    b["crown"].add(*ellipsoid_mesh(x, y, z + h_trunk + r, r, r * rng.uniform(0.9, 1.5)))


def _fence(b, rng, rect, H, skip) -> None:
    x0, x1, y0, y1 = rect
    for (ax, ay, bx, by) in ((x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)):
        L = np.hypot(bx - ax, by - ay)
        n = max(1, int(L / 5.0))
        gap = rng.integers(0, n)  # an entrance
        for k in range(n):
            if k == gap:
                continue
            s0, s1 = k / n, (k + 1) / n
            px, py = ax + (bx - ax) * (s0 + s1) / 2, ay + (by - ay) * (s0 + s1) / 2
            if skip(px, py):
                continue
            z = H(px, py)
            b["fence"].add(*box_mesh(px, py, z - 0.3, z + 1.3, L / n, 0.06, np.arctan2(by - ay, bx - ax)))


def _buildings(b, rng, rect, H, preset) -> None:
    """Fill a rectangle with 1-4 buildings of varied footprint (rectangles and L shapes)."""
    x0, x1, y0, y1 = rect
    parts = [(x0, x1, y0, y1)]
    for _ in range(rng.integers(0, 3)):
        k = int(np.argmax([(p[1] - p[0]) * (p[3] - p[2]) for p in parts]))
        p = parts.pop(k)
        if (p[1] - p[0]) > (p[3] - p[2]):
            m = rng.uniform(0.35, 0.65) * (p[1] - p[0]) + p[0]
            parts += [(p[0], m - 3, p[2], p[3]), (m + 3, p[1], p[2], p[3])]
        else:
            m = rng.uniform(0.35, 0.65) * (p[3] - p[2]) + p[2]
            parts += [(p[0], p[1], p[2], m - 3), (p[0], p[1], m + 3, p[3])]
    hmax = 25.0 if preset.name == "campus" else 18.0
    for (a0, a1, c0, c1) in parts:
        if a1 - a0 < 5 or c1 - c0 < 5:
            continue
        # shrink randomly: varied footprints
        w, d = a1 - a0, c1 - c0
        fa0 = a0 + rng.uniform(0, 0.2) * w
        fa1 = a1 - rng.uniform(0, 0.2) * w
        fc0 = c0 + rng.uniform(0, 0.2) * d
        fc1 = c1 - rng.uniform(0, 0.2) * d
        height = rng.uniform(4.0, hmax)
        zs = H(np.array([fa0, fa1, fa0, fa1]), np.array([fc0, fc0, fc1, fc1]))
        z0, z1 = zs.min() - 0.5, zs.max() + height
        if rng.random() < 0.35 and (fa1 - fa0) > 12 and (fc1 - fc0) > 12:
            # L shape: a full-width wing plus a half-depth wing
            mid_c = (fc0 + fc1) / 2
            b["building"].add(*box_mesh((fa0 + fa1) / 2, (fc0 + mid_c) / 2, z0, z1, fa1 - fa0, mid_c - fc0, 0.0))
            ma = fa0 + (fa1 - fa0) * rng.uniform(0.3, 0.6)
            b["building"].add(*box_mesh((fa0 + ma) / 2, (mid_c + fc1) / 2, z0, z0 + 0.5 + height * rng.uniform(0.5, 1.0),
                                        ma - fa0, fc1 - mid_c, 0.0))
        else:
            b["building"].add(*box_mesh((fa0 + fa1) / 2, (fc0 + fc1) / 2, z0, z1, fa1 - fa0, fc1 - fc0, 0.0))


def movable_mesh(kind: str, x: float, y: float, yaw: float, terrain: Terrain) -> list[tuple[np.ndarray, np.ndarray]]:
    """Mesh parts of one movable or dynamic object standing on the terrain at (x, y)."""
    z = float(terrain.height(x, y))
    if kind in ("car", "vehicle"):
        return [box_mesh(x, y, z + 0.25, z + 1.0, 4.4, 1.8, yaw),
                box_mesh(x - 0.2 * np.cos(yaw), y - 0.2 * np.sin(yaw), z + 1.0, z + 1.5, 2.4, 1.6, yaw)]
    if kind == "bin":
        return [box_mesh(x, y, z - 0.1, z + 1.0, 0.6, 0.6, yaw)]
    if kind == "pedestrian":
        return [box_mesh(x, y, z - 0.05, z + 1.75, 0.35, 0.5, yaw)]
    raise ValueError(kind)


def session_movables(world: World, session: str, base: bool) -> Movables:
    """The movable objects present on a session's day.

    ``base``: the mapping day, the world's base set. Otherwise a deterministic ``movable_change``
    share (at least 10%) of the base objects is changed: a third removed, a third moved (cars
    shifted 3-8 m or re-parked, bins moved a few metres) and as many new ones added.
    """
    mv = world.movables
    if base or len(mv) == 0:
        return mv
    rng = np.random.default_rng(np.random.SeedSequence([world.seed, stable_hash(session), 2]))
    n = len(mv)
    n_change = max(1, int(np.ceil(world.preset.movable_change * n)))
    n_remove = n_change // 3
    n_move = n_change // 3
    n_add = n_change - n_remove - n_move
    order = rng.permutation(n)
    removed, moved = order[:n_remove], order[n_remove:n_remove + n_move]
    keep = np.ones(n, dtype=bool)
    keep[removed] = False
    xy = mv.xy.copy()
    yaw = mv.yaw.copy()
    for k in moved:
        step = rng.uniform(3.0, 8.0) if mv.kind[k] == "car" else rng.uniform(1.0, 4.0)
        xy[k] += step * np.array([np.cos(yaw[k]), np.sin(yaw[k])]) * rng.choice([-1, 1])
        yaw[k] += rng.normal(0, 0.1)
    src = rng.choice(n, size=n_add)  # new objects: near existing ones, in free space
    add_xy = mv.xy[src] + rng.uniform(-1, 1, (n_add, 2)) * [[6.0, 2.0]]
    add_yaw = mv.yaw[src] + rng.normal(0, 0.1, n_add)
    return Movables(np.concatenate([mv.kind[keep], mv.kind[src]]),
                    np.concatenate([xy[keep], add_xy]), np.concatenate([yaw[keep], add_yaw]),
                    np.concatenate([mv.uid[keep], n + np.arange(n_add) + 1_000_000 * (1 + stable_hash(session) % 97)]))
