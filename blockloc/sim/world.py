"""Procedural world: terrain, road grid, buildings, vegetation, street furniture, movable objects.

Frame: the world is modelled z UP (x east, y north, metres, centred on the origin); the NCLT
map frame (z down) is ``T_map_world = diag(1, -1, -1)`` (see ``blockloc.sim.trajectory``).

Everything is generated from ``(preset, seed)`` alone, as plain numpy arrays (no I/O); meshes are
(V, 3) float64 vertices and (F, 3) int64 triangles. ``session_movables`` gives each session's
"day": a deterministic share of the movable objects moved, removed or added.

The world is built by modules of their own (each a pure function of its arguments): ``terrain``
(height field, mesh), ``meshes`` (primitives, reflectance), ``layout`` (roads, buildings,
vegetation), ``movables`` (the objects a session's day changes, actor meshes). A session is
this world plus its day's changes: ``movables.session_movables`` (parked objects),
``scene.make_actors`` (people, vehicles) and the foliage change in ``scene.SessionScene``.
Those names are re-exported here.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from blockloc.sim.layout import (Roads, Volumes, _add_building, _bush, _buildings, _Facades, _fence,
                                 _footpath, _hedge, _passages, _road_lines, _tree, _Vegetation,
                                 polyline_distance)
from blockloc.sim.meshes import (_BOX_F, _ICO_F, _ICO_V, ALBEDO, GROUND_ALBEDO, MeshBuilder, box_mesh,
                                 cylinder_mesh, ellipsoid_mesh)
from blockloc.sim.movables import (MOVABLE_HALF_EXTENT_M, MOVABLE_KINDS, ROUTE_CLEARANCE_M, Movables,
                                   movable_mesh, movable_meshes, off_routes, pedestrian_mesh,
                                   session_movables)
from blockloc.sim.presets import Preset
from blockloc.sim.seeds import stable_hash
from blockloc.sim.terrain import Terrain, make_terrain, smootherstep, smootherstep_d, terrain_mesh

log = logging.getLogger(__name__)

__all__ = ["ALBEDO", "GROUND_ALBEDO", "MATERIAL_TILES", "MOVABLE_HALF_EXTENT_M", "MOVABLE_KINDS",
           "ROUTE_CLEARANCE_M", "MeshBuilder", "Movables", "Roads", "Terrain", "Volumes", "World",
           "_BOX_F", "_ICO_F", "_ICO_V", "box_mesh", "build_world", "cylinder_mesh", "ellipsoid_mesh",
           "make_terrain", "movable_mesh", "movable_meshes", "off_routes", "pedestrian_mesh",
           "polyline_distance", "session_movables", "smootherstep", "smootherstep_d", "stable_hash",
           "terrain_mesh"]

#: Ground-material raster tiles (128 m, 0.25 m cells, four 2-bit codes a byte: 64 KiB each) a
#: world keeps, the least recently used dropped first: 64 MiB at most. Grazing rays hit the
#: terrain far out (a 2000-frame city drive touches ~300 tiles, every one of them rebuilt when
#: only 64 were kept: +20% CPU a scan); unbounded (and a byte a code), a process rendering
#: drives across a world kept every tile it touched, 256 KiB each (a tile is a pure function
#: of the world: rebuilding one gives the same codes).
MATERIAL_TILES = 1024
#: Stacks of tiles :meth:`World.ground_material` keeps (a scan's few sets of tiles).
MATERIAL_STACKS = 8


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
    #: tile ids (tuple) -> their tiles stacked (T, n, n / 4), the MATERIAL_STACKS used last: a
    #: scan looks up the same few tiles ~7 times (hits, kerbs), each time stacking them again
    _material_stacks: dict = field(default_factory=dict, repr=False, compare=False)
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
        out = np.empty(x.shape, dtype=np.uint8)
        if not x.size:
            return out
        if x.ndim != 1 or y.shape != x.shape:  # the kernels take flat arrays
            x, y = np.broadcast_arrays(x, y)
            return self.ground_material(x.ravel(), y.ravel()).reshape(x.shape)
        from blockloc.sim import _kernels

        # tiles numbered within the points' bounding box of tiles (a scan's ground hits span a few):
        # grouping them by a sort (np.unique) took a third of a campus scan's ground lookups
        ti, tj, i0, j0, ni, nj, local, used = _kernels.material_tiles(x, y, tile, 1 << 16)
        if not len(local) and len(x):  # scattered far apart: number them by a sort instead
            uniq, local = np.unique(ti * 1_000_003 + tj, return_inverse=True)
            ids = [(int(k // 1_000_003), int(k % 1_000_003)) for k in uniq]
            ids = [(a + 1, b - 1_000_003) if b > 500_000 else (a, b) for a, b in ids]  # negative tj
            slot = np.arange(len(ids))
        else:
            used = np.flatnonzero(used)
            ids = [(int(i0) + int(k) // int(nj), int(j0) + int(k) % int(nj)) for k in used]
            slot = np.zeros(ni * nj, dtype=np.int64)
            slot[used] = np.arange(len(used))
        key = tuple(ids)
        R = self._material_stacks.pop(key, None)
        if R is None:
            tiles = [self._material_tile(a, b, n, res, tile) for a, b in ids]  # in (ti, tj) order
            R = tiles[0][None] if len(tiles) == 1 else np.stack(tiles)
        self._material_stacks[key] = R  # re-inserted: the newest last
        while len(self._material_stacks) > MATERIAL_STACKS:
            del self._material_stacks[next(iter(self._material_stacks))]
        out[...] = _kernels.material_lookup(R, slot, local.reshape(-1), ti, tj, x, y, tile, res)
        return out

    def _material_tile(self, a: int, b: int, n: int, res: float, tile: float) -> np.ndarray:
        """The packed (n, n / 4) uint8 raster tile (a, b) of :meth:`ground_material`: kept, read
        from ``material_tiles`` or built; marked used last."""
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
        return R

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
        return GROUND_ALBEDO[self.ground_material(x, y)]

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
