"""Procedural world: terrain, road grid, buildings, vegetation, street furniture, movable objects.

Frame: the world is modelled z UP (x east, y north, metres, centred on the origin); the NCLT
map frame (z down) is ``T_map_world = diag(1, -1, -1)`` (see ``blockloc.sim.trajectory``).

Everything is generated from ``(preset, seed)`` alone, as plain numpy arrays (no I/O); meshes are
(V, 3) float64 vertices and (F, 3) int64 triangles. ``session_movables`` gives each session's
"day": a deterministic share of the movable objects moved, removed or added.
"""

from __future__ import annotations

import functools
import logging
import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from blockloc.sim.presets import Preset

log = logging.getLogger(__name__)

#: Lambertian reflectance at 905 nm per surface category (0..1), used for intensity. Asphalt
#: is dark, vegetation bright in the near infrared; buildings get their own (``Facade``).
ALBEDO = {"terrain": 0.3, "road": 0.09, "building": 0.3, "wall": 0.25, "fence": 0.35,
          "pole": 0.3, "trunk": 0.12, "crown": 0.35, "car": 0.25, "bin": 0.2,
          "pedestrian": 0.15, "vehicle": 0.25, "sign": 0.5, "ceiling": 0.3, "self": 0.15,
          "foliage": 0.4, "sidewalk": 0.22, "grass": 0.35, "glass": 0.05}

MOVABLE_KINDS = ("car", "bin")
#: half length and half width (m) of each movable's footprint, as :func:`movable_meshes` draws it
MOVABLE_HALF_EXTENT_M = {"car": (2.2, 0.9), "bin": (0.3, 0.3)}
#: how close (m) a movable's footprint may come to a route: the robot's half width and a margin
ROUTE_CLEARANCE_M = 0.8
#: Ground-material raster tiles (128 m, 0.25 m cells, four 2-bit codes a byte: 64 KiB each) a
#: world keeps, the least recently used dropped first: 64 MiB at most. Grazing rays hit the
#: terrain far out (a 2000-frame city drive touches ~300 tiles, every one of them rebuilt when
#: only 64 were kept: +20% CPU a scan); unbounded (and a byte a code), a process rendering
#: drives across a world kept every tile it touched, 256 KiB each (a tile is a pure function
#: of the world: rebuilding one gives the same codes).
MATERIAL_TILES = 1024


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
    #: footpaths: (node a, node b) with a < b -> (K, 2) polyline from a to b (world, m)
    paths: dict = field(default_factory=dict)
    #: edges (a < b) that are hard places: footpaths, passages under buildings, the corridor
    special: set = field(default_factory=set)
    #: grid edges the moving vehicles must not use (the indoor corridor)
    no_traffic: set = field(default_factory=set)

    def node_xy(self, node: tuple[int, int]) -> np.ndarray:
        return np.array([self.xs[node[0]], self.ys[node[1]]])

    def neighbours(self, node: tuple[int, int]) -> list[tuple[int, int]]:
        i, j = node
        out = []
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            if 0 <= i + di < len(self.xs) and 0 <= j + dj < len(self.ys):
                out.append((i + di, j + dj))
        for di, dj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            nb = (i + di, j + dj)
            if (min(node, nb), max(node, nb)) in self.paths:
                out.append(nb)
        return out

    def edge_points(self, a: tuple[int, int], b: tuple[int, int]) -> np.ndarray:
        """(K, 2) points from node a to node b along the edge (2 for a straight road)."""
        key = (min(a, b), max(a, b))
        if key in self.paths:
            P = self.paths[key]
            return P if key[0] == a else P[::-1]
        return np.array([self.node_xy(a), self.node_xy(b)])

    def edge_length(self, a, b) -> float:
        return float(np.linalg.norm(np.diff(self.edge_points(a, b), axis=0), axis=1).sum())

    def path_distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Distance (m) from (x, y) to the nearest footpath (inf without footpaths)."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        d = np.full(np.broadcast(x, y).shape, np.inf)
        for P in self.paths.values():
            d = np.minimum(d, polyline_distance(P, x, y))
        return d

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
class Volumes:
    """Vegetation as scattering volumes (tree crowns, bushes, hedge pieces): axis-aligned
    ellipsoids. center: (V, 3) world m; radii: (V, 3) semi-axes m; mfp: (V,) mean free path m
    of a ray inside (dense hedge ~0.3 m, open crown ~1 m); kind: (V,) 0 crown, 1 bush, 2 hedge."""

    center: np.ndarray
    radii: np.ndarray
    mfp: np.ndarray
    kind: np.ndarray

    def __len__(self) -> int:
        return len(self.mfp)


@dataclass
class World:
    """A generated world (z up). ``meshes``: category -> (V, F) of the static scene;
    ``owners``: category -> (F,) index of the object each triangle belongs to (buildings: the
    row of ``facades``). ``facades``: (B, 10) building boxes x0 x1 y0 y1 z0 z1, reflectance,
    floor height, window period, phase (m)."""

    preset: Preset
    seed: int
    terrain: Terrain
    roads: Roads
    meshes: dict[str, tuple[np.ndarray, np.ndarray]]
    movables: Movables
    cells: list[dict] = field(default_factory=list)
    corridors: list[dict] = field(default_factory=list)
    volumes: Volumes | None = None
    facades: np.ndarray = field(default_factory=lambda: np.zeros((0, 10)))
    owners: dict = field(default_factory=dict)
    passages: list[dict] = field(default_factory=list)
    _material: dict = field(default_factory=dict, repr=False)  # (ti, tj) -> tile, LRU order
    #: where built raster tiles are shared between processes (get / put by tile id; None: not
    #: shared): set by whoever opens the world (``blockloc.sim.stream.cached_world``)
    material_tiles: Any = field(default=None, repr=False, compare=False)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        sx, sy = self.preset.size_m
        return (-sx / 2, sx / 2, -sy / 2, sy / 2)

    def ground_material(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(N,) ground surface code at (x, y): 0 road (asphalt), 1 sidewalk (paved, a kerb
        above the road), 2 grass, 3 footpath (paved, flush with the grass). Looked up in 0.25 m
        raster tiles of 128 m, each built on first use (a city is never rastered whole) or read
        from ``material_tiles``; the ``MATERIAL_TILES`` used last are kept."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        res, tile = 0.25, 128.0
        n = int(tile / res)
        ti = np.floor(x / tile).astype(np.int64)
        tj = np.floor(y / tile).astype(np.int64)
        key = ti * 1_000_003 + tj
        out = np.empty(x.shape, dtype=np.uint8)
        uniq, inv = np.unique(key, return_inverse=True)
        inv = inv.reshape(x.shape)
        for k, kk in enumerate(uniq):
            a, b = int(kk // 1_000_003), int(kk % 1_000_003)
            if b > 500_000:  # negative tj wrapped by the modulo
                a, b = a + 1, b - 1_000_003
            R = self._material.pop((a, b), None)
            if R is None and self.material_tiles is not None:
                R = self.material_tiles.get(f"{a}_{b}")
                if R is not None and (R.shape != (n, n // 4) or R.dtype != np.uint8):
                    R = None
            if R is None:
                gx = a * tile + (np.arange(n) + 0.5) * res
                gy = b * tile + (np.arange(n) + 0.5) * res
                X, Y = np.meshgrid(gx, gy)
                R = self._ground_material_exact(X.ravel(), Y.ravel(),
                                                (a * tile, (a + 1) * tile, b * tile, (b + 1) * tile))
                R = R.reshape(n, n).astype(np.uint8)  # codes 0..3: four a byte, column j in bits 2 (j % 4)
                R = R[:, 0::4] | (R[:, 1::4] << 2) | (R[:, 2::4] << 4) | (R[:, 3::4] << 6)
                if self.material_tiles is not None:
                    self.material_tiles.put(f"{a}_{b}", R)
            self._material[(a, b)] = R  # re-inserted: the newest last
            while len(self._material) > MATERIAL_TILES:
                del self._material[next(iter(self._material))]
            m = inv == k
            i = np.clip(((y[m] - b * tile) / res).astype(np.int64), 0, n - 1)
            j = np.clip(((x[m] - a * tile) / res).astype(np.int64), 0, n - 1)
            out[m] = (R[i, j >> 2] >> ((j & 3) << 1).astype(np.uint8)) & 3
        return out

    def _ground_material_exact(self, x: np.ndarray, y: np.ndarray, box=None) -> np.ndarray:
        d = self.roads.distance(x, y)
        hw = self.roads.width_m / 2
        code = np.where(d < hw, 0, np.where(d < hw + 2.5, 1, 2))
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        code = np.array(np.broadcast_to(code, x.shape))
        flat, xf, yf = code.reshape(-1), x.reshape(-1), y.reshape(-1)
        for P in self.roads.paths.values():
            lo, hi = P.min(axis=0) - 2.0, P.max(axis=0) + 2.0
            if box is not None and (hi[0] < box[0] or lo[0] > box[1] or hi[1] < box[2] or lo[1] > box[3]):
                continue
            # only grass within 2 m of the path's box can lie within 1.25 m of the path (the same
            # distances, computed for those points alone: a 128 m tile has 262k raster points)
            near = np.flatnonzero((flat == 2) & (xf >= lo[0]) & (xf <= hi[0]) & (yf >= lo[1]) & (yf <= hi[1]))
            if len(near):
                flat[near[polyline_distance(P, xf[near], yf[near]) < 1.25]] = 3
        return code

    def ground_albedo(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        if not self.preset.detail.ground_relief:
            on_road = self.roads.distance(x, y) < self.roads.width_m / 2
            return np.where(on_road, ALBEDO["road"], ALBEDO["terrain"])
        lut = np.array([ALBEDO["road"], ALBEDO["sidewalk"], ALBEDO["grass"], ALBEDO["sidewalk"]])
        return lut[self.ground_material(x, y)]

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
    b = {k: MeshBuilder() for k in ("building", "wall", "fence", "pole", "trunk", "crown", "sign",
                                    "ceiling")}
    detail = preset.detail
    veg = _Vegetation(detail.volumetric_vegetation, b, preset.vegetation,
                      np.random.SeedSequence([int(seed), stable_hash(preset.name), 3]))
    facades = _Facades()
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
        indoor = detail.layout and not corridors
        corridors.append({"x0": x0, "x1": x1, "y": y, "edge": ((i, j), (i + 1, j)), "indoor": indoor})
        if indoor:  # an indoor corridor: a ceiling 3.4 m up, lights (retroreflective) every 8 m
            roads.special.add(((i, j), (i + 1, j)))
            roads.no_traffic.add(((i, j), (i + 1, j)))
            n_seg = int(np.ceil((x1 - x0) / 10.0))
            for k in range(n_seg):
                a0 = x0 + (x1 - x0) * k / n_seg
                a1 = x0 + (x1 - x0) * (k + 1) / n_seg
                hs = H(np.array([a0, a1]), np.array([y, y]))
                _add_building(b, facades, rng, *box_mesh((a0 + a1) / 2, y, hs.max() + 3.4, hs.max() + 3.7,
                                                         a1 - a0 + 0.02, 2 * hw + 1.6, 0.0), "ceiling")
        for side in (-1, 1):
            yw = y + side * (hw + 0.6)
            n_seg = int(np.ceil((x1 - x0) / 10.0))
            for k in range(n_seg):  # segments follow the terrain
                a0 = x0 + (x1 - x0) * k / n_seg
                a1 = x0 + (x1 - x0) * (k + 1) / n_seg
                hs = H(np.array([a0, a1]), np.array([yw, yw]))
                _add_building(b, facades, rng, *box_mesh((a0 + a1) / 2, yw, hs.min() - 0.5, hs.max() + 3.5,
                                                         a1 - a0 + 0.02, 0.3, 0.0), "wall")

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
    perm = list(rng.permutation(ncell))
    ny_c = len(yl) - 1
    interior = [k for k in perm if 1 <= k // ny_c < len(xl) - 2 and 1 <= k % ny_c < len(yl) - 2]
    if preset.detail.layout and interior:  # an open quad with a footpath, where a route can cross it
        perm.remove(interior[0])
        perm.insert(0, interior[0])
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
                    step = rng.uniform(12, 20)
                    for s in np.arange(rng.uniform(3, step), L - 3, step):
                        px, py = ax + (bx - ax) * s / L, ay + (by - ay) * s / L
                        if in_corridor_strip(px, py):
                            continue
                        z = H(px, py)
                        if rng.random() < 0.5:
                            b["pole"].add(*cylinder_mesh(px, py, z - 0.3, z + rng.uniform(5, 8), 0.12))
                            if rng.random() < 0.35:  # a traffic sign (retroreflective sheeting)
                                b["sign"].add(*box_mesh(px, py, z + 2.0, z + 2.6, 0.6, 0.03,
                                                        rng.uniform(0, np.pi)))
                        else:
                            _tree(b, veg, rng, px + rng.uniform(-1, 1), py + rng.uniform(-1, 1), H)
                        if rng.random() < 0.6:
                            _bush(veg, rng, px + rng.uniform(-2, 2), py + rng.uniform(-2, 2), H)
            path = None
            if (detail.layout and ctype in ("field", "park", "parking") and 1 <= ix < len(roads.xs)
                    and 1 <= iy < len(roads.ys) and rng.random() < 0.75):
                path = _footpath(roads, rng, ix, iy)
            clear = (lambda x, y: True) if path is None else (
                lambda x, y, P=path: float(polyline_distance(P, x, y)) > 2.5)
            if ctype == "field":
                # an open quad: a line of trees along its edges, a few solitary ones on the lawn
                for (ax, ay, bx, by) in ((ix0, iy0, ix1, iy0), (ix1, iy0, ix1, iy1),
                                         (ix1, iy1, ix0, iy1), (ix0, iy1, ix0, iy0)):
                    if rng.random() < 0.5:
                        continue
                    L = np.hypot(bx - ax, by - ay)
                    for s_ in np.arange(rng.uniform(2, 10), L - 2, rng.uniform(9, 16)):
                        x, y = ax + (bx - ax) * s_ / L, ay + (by - ay) * s_ / L
                        if clear(x, y):
                            _tree(b, veg, rng, x, y, H)
                for _ in range(int((ix1 - ix0) * (iy1 - iy0) / 1500)):
                    x, y = rng.uniform(ix0, ix1), rng.uniform(iy0, iy1)
                    if clear(x, y):
                        _tree(b, veg, rng, x, y, H)
            if ctype == "buildings":
                _buildings(b, rng, (ix0, ix1, iy0, iy1), H, preset, facades)
                # hedges along the plot, shrubs at the walls
                _hedge(veg, rng, (ix0 - 3, ix1 + 3, iy0 - 3, iy1 + 3), H)
                _hedge(veg, rng, (ix0 - 0.5, ix1 + 0.5, iy0 - 0.5, iy1 + 0.5), H)
            elif ctype == "park":
                area = (ix1 - ix0) * (iy1 - iy0)
                for _ in range(int(area / rng.uniform(70, 140))):
                    x, y = rng.uniform(ix0, ix1), rng.uniform(iy0, iy1)
                    if clear(x, y):
                        _tree(b, veg, rng, x, y, H)
                for _ in range(int(area / 150)):
                    x, y = rng.uniform(ix0, ix1), rng.uniform(iy0, iy1)
                    if clear(x, y):
                        _bush(veg, rng, x, y, H)
                for _ in range(int(area / 400) + 1):
                    x, y = rng.uniform(ix0, ix1), rng.uniform(iy0, iy1)
                    if clear(x, y):
                        mov_kind.append("bin")
                        mov_xy.append((x, y))
                        mov_yaw.append(rng.uniform(0, np.pi))
            elif ctype == "parking":
                # rows of parking places along x; ~70% occupied
                yaw = 0.0 if rng.random() < 0.5 else np.pi / 2
                for py in np.arange(iy0 + 3, iy1 - 3, 12.0):
                    for px in np.arange(ix0 + 2, ix1 - 2, 2.8):
                        for dy in (-2.6, 2.6):
                            if rng.random() < 0.7 and clear(px, py + dy):
                                mov_kind.append("car")
                                mov_xy.append((px, py + dy))
                                mov_yaw.append(np.pi / 2 + rng.normal(0, 0.05))
                del yaw
                if rng.random() < 0.7:
                    _fence(b, rng, (ix0 - 2, ix1 + 2, iy0 - 2, iy1 + 2), H,
                           lambda x, y: in_corridor_strip(x, y) or not clear(x, y))
                else:
                    _hedge(veg, rng, (ix0 - 2, ix1 + 2, iy0 - 2, iy1 + 2), H,
                           skip=lambda x, y: not clear(x, y))
            # cars parked along the kerb (movable) beside non-field cells
            if ctype != "field":
                for y_k, sgn in ((cy0, 1), (cy1, -1)):
                    for px in np.arange(cx0 + 8, cx1 - 8, 6.0):
                        if rng.random() < 0.25 and not in_corridor_strip(px, y_k):
                            mov_kind.append("car")
                            mov_xy.append((px, y_k + sgn * 1.2))
                            mov_yaw.append(rng.normal(0, 0.03))

    passages = _passages(b, rng, roads, cells, corridors, H, preset, facades) if detail.layout else []
    ext = preset.terrain_margin_m
    meshes = {"terrain": terrain_mesh(terrain, -sx / 2 - ext, sx / 2 + ext, -sy / 2 - ext,
                                      sy / 2 + ext, preset.terrain_res_m)}
    for k, mb in b.items():
        V, F = mb.build()
        if len(F):
            meshes[k] = (V, F)
    owners = {k: np.asarray(v, dtype=np.int64) for k, v in facades.owner.items() if k in meshes}
    movables = Movables(np.array(mov_kind, dtype="<U8"), np.array(mov_xy, dtype=float).reshape(-1, 2),
                        np.array(mov_yaw, dtype=float), np.arange(len(mov_kind)))
    world = World(preset, int(seed), terrain, roads, meshes, movables, cells, corridors,
                  veg.build(), np.array(facades, dtype=float).reshape(-1, 10), owners, passages)
    log.debug("world %s/%d: %d triangles, %d movables", preset.name, seed, world.num_triangles(),
              len(movables))
    return world


class _Vegetation:
    """Collects vegetation: scattering volumes (volumetric) or solid ellipsoid meshes."""

    def __init__(self, volumetric: bool, b: dict, share: float = 1.0, seed=None):
        self.volumetric = volumetric
        self.b = b
        self.rows: list[tuple] = []
        self.share = float(share)
        # which plants grow: a stream of its own, so that thinning them moves nothing else
        self._thin = np.random.default_rng(seed)

    def grows(self) -> bool:
        """Whether the next tree, clump of shrubs or hedge grows (a ``share`` of them do)."""
        return bool(self._thin.random() < self.share)

    def add(self, b, cx, cy, cz, rxy, rz, mfp, kind) -> None:
        """One crown / bush / hedge piece (the same draws either way: switching the volumes
        off changes how rays meet vegetation, not where it grows)."""
        if self.volumetric:
            self.rows.append((cx, cy, cz, rxy, rxy, rz, mfp, kind))
        else:
            self.b["crown"].add(*ellipsoid_mesh(cx, cy, cz, rxy, rz))

    def build(self) -> Volumes | None:
        if not self.rows:
            return None
        a = np.array(self.rows, dtype=float)
        return Volumes(a[:, :3], a[:, 3:6], a[:, 6], a[:, 7].astype(np.int8))


def _tree(b, veg, rng, x, y, H) -> None:
    """A trunk and its crown (two volumes), if it grows (the same draws either way)."""
    grow = veg.grows()
    z = H(x, y)
    h_trunk = rng.uniform(1.8, 3.2)
    r = rng.uniform(1.3, 3.0)
    trunk = cylinder_mesh(x, y, z - 0.3, z + h_trunk + 0.5 * r, rng.uniform(0.12, 0.3), n=6)
    rz = r * rng.uniform(0.9, 1.5)
    mfp = rng.uniform(0.5, 1.4)
    mfp_inner = rng.uniform(0.4, 0.9)
    if not grow:
        return
    b["trunk"].add(*trunk)
    veg.add(b, x, y, z + h_trunk + r, r, rz, mfp, 0)
    if veg.volumetric:  # a lower, denser shell of leaves and branches (inside the solid crown)
        veg.add(b, x, y, z + h_trunk + 0.6 * r, 0.7 * r, 0.5 * rz, mfp_inner, 0)


def _bush(veg, rng, x, y, H) -> None:
    """A clump of 1-3 overlapping shrubs, if it grows (the same draws either way)."""
    grow = veg.grows()
    for _ in range(rng.integers(1, 4)):
        px, py = x + rng.uniform(-1, 1), y + rng.uniform(-1, 1)
        r = rng.uniform(0.4, 1.1)
        rz, mfp = r * rng.uniform(0.6, 1.0), rng.uniform(0.15, 0.4)
        if grow:
            veg.add(None, px, py, H(px, py) + r * 0.7, r, rz, mfp, 1)


def _hedge(veg, rng, rect, H, skip=None) -> None:
    """Hedges along one or two sides of a rectangle: chains of dense overlapping shrubs."""
    x0, x1, y0, y1 = rect
    sides = [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]
    for k in rng.choice(4, size=rng.integers(1, 3), replace=False):
        ax, ay, bx, by = sides[k]
        L = np.hypot(bx - ax, by - ay)
        s0 = rng.uniform(0, 0.3) * L
        s1 = s0 + rng.uniform(0.3, 0.7) * L
        r, h = rng.uniform(0.45, 0.7), rng.uniform(0.8, 1.6)
        ss = np.arange(s0, min(s1, L), 0.8)
        px, py = ax + (bx - ax) * ss / L, ay + (by - ay) * ss / L
        pz = H(px, py)
        mfp = rng.uniform(0.15, 0.35, len(ss))
        if not veg.grows():
            continue
        for k in range(len(ss)):
            if skip is None or not skip(px[k], py[k]):
                veg.add(None, px[k], py[k], pz[k] + h / 2, r, h / 2 + 0.1, mfp[k], 2)


def polyline_distance(P: np.ndarray, x, y) -> np.ndarray:
    """Distance (m) from points (x, y) (broadcastable) to the polyline P (K, 2)."""
    x, y = np.asarray(x, float)[..., None], np.asarray(y, float)[..., None]
    a, u = P[:-1], np.diff(P, axis=0)
    L2 = (u * u).sum(axis=1)
    s = np.clip(((x - a[:, 0]) * u[:, 0] + (y - a[:, 1]) * u[:, 1]) / L2, 0.0, 1.0)
    return np.hypot(x - a[:, 0] - s * u[:, 0], y - a[:, 1] - s * u[:, 1]).min(axis=-1)


def _footpath(roads: Roads, rng, ix: int, iy: int) -> np.ndarray:
    """A curving footpath across the cell ix, iy (between grid lines ix-1..ix, iy-1..iy), from
    one corner intersection to the opposite one; registered in ``roads.paths``."""
    if rng.random() < 0.5:
        a, b_ = (ix - 1, iy - 1), (ix, iy)
    else:
        a, b_ = (ix - 1, iy), (ix, iy - 1)
    A, B = roads.node_xy(a), roads.node_xy(b_)
    d = B - A
    n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
    bend = rng.choice([-1, 1]) * rng.uniform(0.12, 0.25) * np.linalg.norm(d)
    C = (A + B) / 2 + n * bend
    u = np.linspace(0.0, 1.0, 7)[:, None]
    P = (1 - u) ** 2 * A + 2 * u * (1 - u) * C + u * u * B  # quadratic Bezier
    key = (min(a, b_), max(a, b_))
    roads.paths[key] = P if key[0] == a else P[::-1]
    roads.special.add(key)
    return P


def _passages(b, rng, roads: Roads, cells, corridors, H, preset, facades) -> list[dict]:
    """Buildings bridging a road (the robot drives under them): over one grid edge beside a
    building cell per ~6 such edges (at least one)."""
    hw = roads.width_m / 2
    cand = []
    nx, ny = len(roads.xs), len(roads.ys)
    corr = {c["edge"] for c in corridors}
    for i in range(nx):
        for j in range(ny):
            for e in (((i, j), (i + 1, j)), ((i, j), (i, j + 1))):
                if e[1][0] < nx and e[1][1] < ny and e not in corr:
                    cand.append(e)
    rng.shuffle(cand)
    out = []
    n_want = max(1, len(cand) // 12)
    for a, b_ in cand:
        if len(out) >= n_want:
            break
        A, B = roads.node_xy(a), roads.node_xy(b_)
        L = np.linalg.norm(B - A)
        if L < 40:
            continue
        u = (B - A) / L
        mid = A + u * L * rng.uniform(0.35, 0.65)
        length = rng.uniform(14.0, 26.0)
        yaw = float(np.arctan2(u[1], u[0]))
        across = 2 * hw + 8.0
        z = H(np.array([mid[0]]), np.array([mid[1]]))[0]
        z0 = z + rng.uniform(4.2, 5.5)
        z1 = z0 + rng.uniform(5.0, 14.0)
        V, F = box_mesh(mid[0], mid[1], z0, z1, length, across, yaw)
        _add_building(b, facades, rng, V, F)
        nvec = np.array([-u[1], u[0]])
        for s_al in (-0.45, 0.45):
            for s_ac in (-1, 1):
                p = mid + u * s_al * length + nvec * s_ac * (hw + 2.2)
                _add_building(b, facades, rng, *box_mesh(p[0], p[1], z - 0.5, z0, 0.7, 0.7, yaw))
        key = (min(a, b_), max(a, b_))
        roads.special.add(key)
        out.append({"edge": key, "center": mid.tolist(), "length": length})
    return out


def _add_building(b, facades, rng, V, F, cat: str = "building") -> None:
    """One building (or wall, ceiling) box (12 triangles) and its facade row (see ``World``);
    ``facades.owner[cat]`` collects the row of each of the category's triangles."""
    b[cat].add(V, F)
    lo, hi = V.min(axis=0), V.max(axis=0)
    facades.owner.setdefault(cat, []).extend([len(facades)] * len(F))
    facades.append((lo[0], hi[0], lo[1], hi[1], lo[2], hi[2],
                    rng.uniform(0.12, 0.5) if cat == "building" else ALBEDO[cat],
                    rng.uniform(3.2, 4.2), rng.uniform(2.4, 4.0), rng.uniform(0, 4.0)))


class _Facades(list):
    """Facade rows (see ``World``) and, per category, the row of each triangle."""

    def __init__(self):
        super().__init__()
        self.owner: dict[str, list[int]] = {}


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


def _buildings(b, rng, rect, H, preset, facades) -> None:
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
    hmax = preset.max_building_height_m
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
            _add_building(b, facades, rng, *box_mesh((fa0 + fa1) / 2, (fc0 + mid_c) / 2, z0, z1,
                                                     fa1 - fa0, mid_c - fc0, 0.0))
            ma = fa0 + (fa1 - fa0) * rng.uniform(0.3, 0.6)
            _add_building(b, facades, rng, *box_mesh((fa0 + ma) / 2, (mid_c + fc1) / 2, z0,
                                                     z0 + 0.5 + height * rng.uniform(0.5, 1.0),
                                                     ma - fa0, fc1 - mid_c, 0.0))
        else:
            _add_building(b, facades, rng, *box_mesh((fa0 + fa1) / 2, (fc0 + fc1) / 2, z0, z1,
                                                     fa1 - fa0, fc1 - fc0, 0.0))


def _limb(base: np.ndarray, yaw: float, swing: float, length: float, thick: float):
    """A limb hanging from ``base`` (3,) swung by ``swing`` rad forward (about the body's
    lateral axis): a box from the joint down to the hand or foot."""
    c, s = np.cos(yaw), np.sin(yaw)
    tip = base + length * np.array([np.sin(swing) * c, np.sin(swing) * s, -np.cos(swing)])
    mid = (base + tip) / 2
    L = abs(np.sin(swing)) * length + thick
    return box_mesh(mid[0], mid[1], min(base[2], tip[2]), max(base[2], tip[2]), max(L, thick), thick, yaw)


def pedestrian_mesh(x: float, y: float, z: float, yaw: float, gait: float | None,
                    height: float = 1.75) -> list[tuple[np.ndarray, np.ndarray]]:
    """An articulated walker: torso, head, two legs and two arms swinging with ``gait`` (rad,
    the stride phase); ``gait`` None: the old rigid box."""
    if gait is None:
        return [box_mesh(x, y, z - 0.05, z + height, 0.35, 0.5, yaw)]
    k = height / 1.75
    hip = z + 0.9 * k
    lat = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    parts = [box_mesh(x, y, hip, z + 1.5 * k, 0.24, 0.42, yaw),  # torso
             box_mesh(x, y, z + 1.52 * k, z + height, 0.2, 0.18, yaw)]  # head
    swing = 0.45 * np.sin(gait)
    for side, sgn in ((-1, 1), (1, -1)):
        hp = np.array([x, y, hip]) + lat * side * 0.1
        parts.append(_limb(hp, yaw, sgn * swing, 0.9 * k, 0.14))
        sh = np.array([x, y, z + 1.45 * k]) + lat * side * 0.25
        parts.append(_limb(sh, yaw, -sgn * 0.8 * swing, 0.65 * k, 0.09))
    return parts


def movable_mesh(kind: str, x: float, y: float, yaw: float, terrain: Terrain,
                 gait: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Mesh parts of one movable or dynamic object standing on the terrain at (x, y);
    ``gait``: stride phase of an articulated pedestrian (None: a rigid box)."""
    z = float(terrain.height(x, y))
    if kind in ("car", "vehicle"):
        return [box_mesh(x, y, z + 0.25, z + 1.0, 4.4, 1.8, yaw),
                box_mesh(x - 0.2 * np.cos(yaw), y - 0.2 * np.sin(yaw), z + 1.0, z + 1.5, 2.4, 1.6, yaw)]
    if kind == "bin":
        return [box_mesh(x, y, z - 0.1, z + 1.0, 0.6, 0.6, yaw)]
    if kind == "pedestrian":
        return pedestrian_mesh(x, y, z, yaw, gait)
    raise ValueError(kind)


def _boxes(cx, cy, z0, z1, lx: float, ly: float, yaw) -> np.ndarray:
    """:func:`box_mesh` of M boxes at once (the same arithmetic, so the same bits): vertices
    (M, 8, 3); cx, cy, z0, z1, yaw (M,)."""
    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.array([[-lx, -ly], [lx, -ly], [lx, ly], [-lx, ly]]) * 0.5
    R = np.empty((len(yaw), 2, 2))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = c, s, -s, c
    xy = corners @ R + np.stack([cx, cy], axis=-1)[:, None, :]
    V = np.empty((len(yaw), 8, 3))
    V[:, :4, :2] = V[:, 4:, :2] = xy
    V[:, :4, 2], V[:, 4:, 2] = z0[:, None], z1[:, None]
    return V


def movable_meshes(movables: Movables, terrain: Terrain) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """kind -> (V, F) of every movable of that kind ('car', 'bin'), in the movables' order: what
    :func:`movable_mesh` per object gathered in a :class:`MeshBuilder` gives, bit for bit, in
    one pass (a city has ~55k movables: 11 s one by one, 0.2 s here). Kinds without an object
    are left out."""
    kind = np.asarray(movables.kind).astype(str)
    unknown = sorted(set(kind.tolist()) - set(MOVABLE_KINDS))
    if unknown:
        raise ValueError(f"movable kinds {unknown}: expected {MOVABLE_KINDS}")
    out = {}
    for k in MOVABLE_KINDS:
        m = kind == k
        if not m.any():
            continue
        x, y = (np.asarray(movables.xy, np.float64)[m, i] for i in (0, 1))
        yaw = np.asarray(movables.yaw, np.float64)[m]
        z = terrain.height(x, y)
        if k == "car":
            parts = [_boxes(x, y, z + 0.25, z + 1.0, 4.4, 1.8, yaw),
                     _boxes(x - 0.2 * np.cos(yaw), y - 0.2 * np.sin(yaw), z + 1.0, z + 1.5, 2.4, 1.6, yaw)]
        else:
            parts = [_boxes(x, y, z - 0.1, z + 1.0, 0.6, 0.6, yaw)]
        n = len(x) * len(parts)
        out[k] = (np.stack(parts, axis=1).reshape(-1, 3),
                  (_BOX_F[None] + 8 * np.arange(n)[:, None, None]).reshape(-1, 3).astype(np.int64))
    return out


def off_routes(movables: Movables, route_xy: np.ndarray, clearance_m: float = ROUTE_CLEARANCE_M) -> Movables:
    """``movables`` without the objects whose footprint (a yawed rectangle,
    :data:`MOVABLE_HALF_EXTENT_M`) comes within ``clearance_m`` of a point of ``route_xy``
    ((N, 2) world m, sampled densely along every session's route: spacing well below
    ``clearance_m``). Parked cars are placed clear of the footpaths' polylines, but the driven
    route rounds their bends: campus (seed 1) routes passed within 1.5 m of 51 car centres, the
    LiDAR inside the car's mesh."""
    from scipy.spatial import cKDTree

    route_xy = np.asarray(route_xy, dtype=np.float64).reshape(-1, 2)
    keep = np.ones(len(movables.kind), dtype=bool)
    if not len(route_xy) or not len(keep):
        return movables
    tree = cKDTree(route_xy)
    kind = np.asarray(movables.kind).astype(str)
    for k, (hl, hw) in MOVABLE_HALF_EXTENT_M.items():
        idx = np.nonzero(kind == k)[0]
        if not len(idx):
            continue
        near = tree.query_ball_point(np.asarray(movables.xy, np.float64)[idx], r=np.hypot(hl, hw) + clearance_m)
        for j, pts in zip(idx, near):
            if not pts:
                continue
            d = route_xy[pts] - movables.xy[j]
            c, s_ = np.cos(movables.yaw[j]), np.sin(movables.yaw[j])
            u = np.maximum(np.abs(d[:, 0] * c + d[:, 1] * s_) - hl, 0.0)  # along the object
            v = np.maximum(np.abs(-d[:, 0] * s_ + d[:, 1] * c) - hw, 0.0)  # across it
            if (np.hypot(u, v) < clearance_m).any():
                keep[j] = False
    if keep.all():
        return movables
    return Movables(movables.kind[keep], movables.xy[keep], movables.yaw[keep], movables.uid[keep])


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
