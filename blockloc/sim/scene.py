"""A session's ray-casting scene: the static world plus that day's movable objects (open3d
``RaycastingScene``), vegetation volumes, surface detail (kerbs, grass, facades), and the moving
pedestrians and vehicles, cast as a small per-scan scene.

Frame: world, z up, metres (see ``blockloc.sim.world``). Large worlds (``preset.scene_window_m``)
are cast in a window around the robot, rebuilt when it moves on: the whole city never sits in one
scene. The terrain is the exception: it sits in one scene of its own per world, shared by every
window and every session of that world in the process, and each ray is cast against both (the
nearer hit wins). In the windows a city's terrain was 96% of each window's triangles: ~140 MB of
BVH per window, four windows kept per drive, rebuilt in ~1.5 s each.
"""

from __future__ import annotations

import logging
import threading
import weakref
from dataclasses import dataclass

import numpy as np

from blockloc.sim.movables import actor_meshes
from blockloc.sim.world import (_ICO_F, _ICO_V, ALBEDO, GROUND_ALBEDO, Movables, World, movable_meshes,
                                stable_hash)
from blockloc.threads import raycast_threads

log = logging.getLogger(__name__)

KERB_M = 0.12  # sidewalks stand this far above the road
#: A windowed scene (``scene_window_m`` = h > 0) is built around the centre of the grid cell of
#: side ``WINDOW_STEP * h`` the sensor is in, so a scan depends only on where it is taken, not on
#: which scans the process cast before (a map build on several workers renders each keyframe in
#: whichever process runs its task). The sensor is within 0.35 h of that centre per axis: rays
#: see 0.65 h of the world around it (as the window re-centred at 0.35 h did).
WINDOW_STEP = 0.7
#: Sectors of bearing round a scan's origin in which the nearest vegetation hull is looked up
#: (:meth:`SessionScene._rays_near_hulls`).
SECTORS = 2048
#: Built windows kept per scene: a drive along a cell border, or through a corner, switches
#: between up to four without building them again.
WINDOW_CACHE = 4

#: id(world) -> (weakref to the world, weakref to its TerrainScene): the terrain scene lives as
#: long as a windowed scene of that world uses it, and is built again after.
_TERRAIN_SCENES: dict = {}
_TERRAIN_LOCK = threading.Lock()


class TerrainScene:
    """The ray-casting scene of a world's terrain mesh alone (``scene``: open3d
    RaycastingScene, world frame, z up; its primitive ids index ``world.meshes["terrain"][1]``)."""

    __slots__ = ("scene", "__weakref__")

    def __init__(self, world: World) -> None:
        from blockloc.open3d_loader import open3d

        o3d = open3d()
        V, F = world.meshes["terrain"]
        used, inv = np.unique(F, return_inverse=True)
        self.scene = o3d.t.geometry.RaycastingScene(nthreads=raycast_threads())
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(V, np.float32)[used]),
                                 o3d.core.Tensor(inv.reshape(-1, 3).astype(np.uint32)))


def terrain_scene(world: World) -> TerrainScene:
    """``world``'s :class:`TerrainScene`, shared by the windowed scenes of every session of that
    world in this process while one of them holds it (a city's: ~135 MB of BVH)."""
    key = id(world)
    with _TERRAIN_LOCK:
        got = _TERRAIN_SCENES.get(key)
        held = got[1]() if got is not None and got[0]() is world else None
        if held is None:
            for k in [k for k, (w, t) in _TERRAIN_SCENES.items() if w() is None or t() is None]:
                del _TERRAIN_SCENES[k]
            held = TerrainScene(world)
            _TERRAIN_SCENES[key] = (weakref.ref(world), weakref.ref(held))
        return held


@dataclass
class Actors:
    """Moving pedestrians and vehicles, each going back and forth along one straight line.

    kind: (K,) 'pedestrian' | 'vehicle'; a, b: (K, 2) ends of its line (world, m);
    offset: (K,) metres to the right of its travel direction; speed: (K,) m/s; phase: (K,) m;
    stride: (K,) m per gait cycle (pedestrians; 0: rigid).
    """

    kind: np.ndarray
    a: np.ndarray
    b: np.ndarray
    offset: np.ndarray
    speed: np.ndarray
    phase: np.ndarray
    stride: np.ndarray | None = None

    def poses(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(K, 2) positions and (K,) headings at session time t (s)."""
        if not len(self.kind):
            return np.zeros((0, 2)), np.zeros(0)
        d = self.b - self.a
        L = np.linalg.norm(d, axis=1)
        u = d / L[:, None]
        s = np.mod(self.phase + self.speed * t, 2 * L)
        back = s > L
        along = np.where(back, 2 * L - s, s)
        dirn = np.where(back[:, None], -u, u)
        right = np.c_[dirn[:, 1], -dirn[:, 0]]
        xy = self.a + u * along[:, None] + right * self.offset[:, None]
        return xy, np.arctan2(dirn[:, 1], dirn[:, 0])

    def gait(self, t: float) -> np.ndarray:
        """(K,) stride phase (rad) at time t; NaN for rigid actors."""
        if self.stride is None:
            return np.full(len(self.kind), np.nan)
        dist = self.phase + self.speed * t
        return np.where(self.stride > 0, 2 * np.pi * dist / np.maximum(self.stride, 1e-9), np.nan)


def make_actors(world: World, session: str) -> Actors:
    """The session's moving people and vehicles (deterministic from seed and session). Mapping
    drives have none (the map is built on a quiet day); localization drives meet walkers, in
    groups when ``detail.crowds``, on sidewalks and footpaths, and cars on the roads."""
    p = world.preset
    empty = Actors(np.zeros(0, dtype="<U10"), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0),
                   np.zeros(0), np.zeros(0), np.zeros(0))
    if p.is_mapping(session):
        return empty
    rng = np.random.default_rng(np.random.SeedSequence([world.seed, stable_hash(session), 3]))
    roads = world.roads
    x0, x1, y0, y1 = world.extent
    hw = roads.width_m / 2
    crowds = p.detail.crowds
    kinds, A, B, off, spd, stride, ph = [], [], [], [], [], [], []
    blocked_y = {roads.ys[e[0][1]] for e in roads.no_traffic}
    paths = list(roads.paths.values())
    n_ped = 0
    while n_ped < p.n_pedestrians:
        if paths and rng.random() < 0.35:  # a group crossing a quad on its footpath
            P = paths[rng.integers(len(paths))]
            a, b = P[0].astype(float), P[-1].astype(float)
            base_off = rng.uniform(-1.0, 1.0)
        else:
            if rng.random() < 0.5:
                x = roads.xs[rng.integers(len(roads.xs))]
                a, b = (x, y0), (x, y1)
            else:
                y = roads.ys[rng.integers(len(roads.ys))]
                a, b = (x0, y), (x1, y)
            a, b = np.array(a, float), np.array(b, float)
            L = np.linalg.norm(b - a)
            s0 = rng.uniform(0, L - 40)
            u = (b - a) / L
            a, b = a + u * s0, a + u * (s0 + rng.uniform(20, 40))
            base_off = rng.choice([-1, 1]) * (hw + rng.uniform(1.0, 2.0))
        n = int(rng.integers(2, 9)) if crowds else 1
        n = min(n, p.n_pedestrians - n_ped)
        v = rng.uniform(0.8, 1.5)
        phase0 = rng.uniform(0, 2 * np.linalg.norm(b - a))
        for _ in range(n):
            kinds.append("pedestrian")
            A.append(a)
            B.append(b)
            off.append(base_off + (rng.uniform(-0.9, 0.9) if n > 1 else 0.0))
            spd.append(v * rng.uniform(0.95, 1.05))
            ph.append(phase0 + rng.uniform(-2.0, 2.0))
            stride.append(rng.uniform(1.2, 1.6) if crowds else 0.0)
        n_ped += n
    for _ in range(p.n_vehicles):
        for _try in range(20):
            if rng.random() < 0.5:
                x = roads.xs[rng.integers(len(roads.xs))]
                a, b = (x, y0), (x, y1)
                break
            y = roads.ys[rng.integers(len(roads.ys))]
            if y not in blocked_y:
                a, b = (x0, y), (x1, y)
                break
        kinds.append("vehicle")
        A.append(np.array(a, float))
        B.append(np.array(b, float))
        off.append(hw - 0.7)  # keeps ~0.7 m clear of the robot (LANE_OFFSET_M)
        spd.append(rng.uniform(3.0, 7.0))
        ph.append(None)
        stride.append(0.0)
    if not kinds:
        return empty
    A, B = np.array(A, float).reshape(-1, 2), np.array(B, float).reshape(-1, 2)
    L = np.linalg.norm(B - A, axis=1)
    phase = np.array([rng.uniform(0, 2 * l) if q is None else q for q, l in zip(ph, L)])
    return Actors(np.array(kinds), A, B, np.array(off), np.array(spd), phase, np.array(stride))


# --- surface detail ---------------------------------------------------------------------------

def value_noise(x: np.ndarray, y: np.ndarray, cell_m: float, seed: int) -> np.ndarray:
    """Smooth deterministic noise in [-1, 1] at (x, y) (broadcastable arrays): bilinear over a
    hashed lattice (``blockloc.sim._kernels.value_noise``, one pass; it was ~12 numpy passes)."""
    from blockloc.sim import _kernels

    x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    out = _kernels.value_noise(x.ravel(), y.ravel(), float(cell_m), np.int64(int(seed) * 83492791))
    return out.reshape(x.shape)


def dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products (N,) of (N, 3) arrays: the bits of ``(a * b).sum(axis=1)`` (the same
    three products added in the same order), in 40% of its time (a scan has ~70k rays)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _random_unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.sqrt(dot3(v, v))[:, None]  # np.linalg.norm(v, axis=1, keepdims=True), its bits


#: Every moving actor's mesh lies within this xy distance of its position (a vehicle's corner:
#: 2.4 m), metres.
ACTOR_RADIUS_M = 3.5
#: A box this deep along a ray behind a window holds a room (shallower: a wall, a pillar).
ROOM_MIN_M = 1.5
BACK_WALL_M = 0.3  # a room's return stops this short of the box's far side


class SessionScene:
    """Static world + one day's movables + vegetation volumes; actors added per scan.

    ``cast(origins, dirs, t)`` returns range (N,) (inf where nothing is hit), unit normals
    (N, 3), reflectance (N,) and a category code (N,) int (index into ``categories``);
    ``cast_full`` also says which returns are glass or retroreflective.
    """

    def __init__(self, world: World, movables: Movables, actors: Actors, session: str = "map"):
        from blockloc.open3d_loader import open3d

        o3d = open3d()
        self._o3d = o3d
        self.world = world
        self.movables = movables
        self.actors = actors
        self.detail = world.preset.detail
        self.categories: list[str] = []
        meshes = dict(world.meshes)
        meshes.update(movable_meshes(movables, world.terrain))
        for name in list(meshes) + ["pedestrian", "vehicle", "foliage", "self", "glass"]:
            if name not in self.categories:
                self.categories.append(name)
        self._cat_index = {c: i for i, c in enumerate(self.categories)}
        self._reflect_by_cat = np.array([ALBEDO.get(c, 0.3) for c in self.categories] + [0.0])
        # all static triangles, with their category and owner (building -> facade row)
        Vs, Fs, cats, owners, n = [], [], [], [], 0
        for name, (V, F) in meshes.items():
            Vs.append(V)
            Fs.append(F + n)
            n += len(V)
            cats.append(np.full(len(F), self._cat_index[name], dtype=np.int64))
            owners.append(world.owners.get(name, np.full(len(F), -1, dtype=np.int64)))
        # index and code arrays in the smallest type that holds them: a city has 3.4M triangles
        # and a drive's process holds these for each drive it renders
        self._V = np.concatenate(Vs).astype(np.float32)
        self._F = np.concatenate(Fs).astype(np.int32 if n < 2**31 else np.int64)
        self._tri_cat = np.concatenate(cats).astype(np.int16)
        self._tri_owner = np.concatenate(owners).astype(np.int32)
        self._tri_xy = None  # (M, 2) centroids of the windowed (non-terrain) triangles
        self._boxed = None  # (M,) their indices
        self.terrain_cat = self._cat_index["terrain"]
        # the terrain's triangles: one run of them (the world's terrain mesh), cast in the world's
        # shared terrain scene when the scene is windowed
        terrain = np.flatnonzero(self._tri_cat == self.terrain_cat)
        self._terrain_first = int(terrain[0]) if len(terrain) else 0
        if len(terrain) and (terrain[-1] - terrain[0] + 1 != len(terrain)
                             or len(terrain) != len(world.meshes["terrain"][1])):
            raise ValueError("terrain triangles: expected the world's terrain mesh, in one run")
        self._terrain_scene = None
        # categories with facade rows (buildings, corridor walls and ceiling)
        self._facade_cats = np.array([self._cat_index[c] for c in world.owners if c in self._cat_index])
        self._is_facade_cat = np.isin(np.arange(len(self.categories)), self._facade_cats)
        # the day's foliage: denser or sparser crowns than on the mapping day (seasons)
        vol = world.volumes
        self._vol_mfp = None
        if vol is not None and len(vol):
            ch = self.detail.foliage_change if not world.preset.is_mapping(session) else 0.0
            rng = np.random.default_rng(np.random.SeedSequence([world.seed, stable_hash(session), 11]))
            self._vol_mfp = vol.mfp * np.exp(rng.uniform(-1.0, 1.0, len(vol)) * 1.2 * ch)
            self._vol_radii = vol.radii * (1.0 + rng.normal(0, 0.06, (len(vol), 1)) * ch)
        # a cast selects the window it needs, then casts in it: one cast at a time (the scene of
        # the mapping sessions is shared by their sequences, which threads may render at once)
        self._lock = threading.RLock()
        self._window = None  # (center, half size, grid cell) of the window in use
        self._windows: dict = {}  # grid cell -> built (scene, sel, vol_scene, vsel), oldest first
        self._seed = world.seed
        if world.preset.scene_window_m <= 0:
            self._build(None)

    # --- scenes ---------------------------------------------------------------------------------
    def _build(self, center) -> None:
        """(Re)build the static and vegetation scenes: everything, or a window around center."""
        o3d = self._o3d
        half = self.world.preset.scene_window_m
        if center is None or half <= 0:
            sel = np.arange(len(self._F))
            vsel = np.arange(len(self._vol_mfp)) if self._vol_mfp is not None else np.zeros(0, int)
        else:
            if self._tri_xy is None:
                self._boxed = np.flatnonzero(self._tri_cat != self.terrain_cat)
                self._tri_xy = self._V[self._F[self._boxed]].mean(axis=1)[:, :2]
                self._terrain = terrain_scene(self.world)  # held: the scene lives while we do
                self._terrain_scene = self._terrain.scene
            lo, hi = np.asarray(center) - half, np.asarray(center) + half
            sel = self._boxed[((self._tri_xy >= lo) & (self._tri_xy <= hi)).all(axis=1)]
            vsel = np.zeros(0, int)
            if self._vol_mfp is not None:
                c = self.world.volumes.center[:, :2]
                vsel = np.flatnonzero(((c >= lo) & (c <= hi)).all(axis=1))
        self.scene = o3d.t.geometry.RaycastingScene(nthreads=raycast_threads())
        if len(sel):  # a window may hold nothing but terrain (cast in the terrain scene)
            F = self._F[sel]
            used, inv = np.unique(F, return_inverse=True)
            self.scene.add_triangles(o3d.core.Tensor(self._V[used]),
                                     o3d.core.Tensor(inv.reshape(-1, 3).astype(np.uint32)))
        self._sel = sel
        self._vol_scene = None
        self._vol_discs = None
        self._vsel = vsel
        if len(vsel):
            vol = self.world.volumes
            k = len(_ICO_V)
            # hulls circumscribing the ellipsoids (the 80-face sphere is inscribed in the unit one)
            V = (_ICO_V[None] * 1.1 * self._vol_radii[vsel, None, :] + vol.center[vsel, None, :]).reshape(-1, 3)
            F = (_ICO_F[None] + k * np.arange(len(vsel))[:, None, None]).reshape(-1, 3)
            self._vol_scene = o3d.t.geometry.RaycastingScene(nthreads=raycast_threads())
            self._vol_scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)),
                                          o3d.core.Tensor(F.astype(np.uint32)))
            # each hull's disc in xy: its centre and the farthest vertex (+ 1 cm for the float32
            # vertices), which the first vegetation pass uses to leave out rays that end short
            xy = V.reshape(len(vsel), k, 3)[:, :, :2] - vol.center[vsel, None, :2]
            self._vol_discs = (np.ascontiguousarray(vol.center[vsel, :2]),
                               np.sqrt((xy * xy).sum(axis=2)).max(axis=1) + 0.01)

    def _ensure_window(self, center: np.ndarray) -> None:
        half = self.world.preset.scene_window_m
        if half <= 0:
            return
        step = WINDOW_STEP * half
        cell = tuple(int(c) for c in np.floor(np.asarray(center[:2], float) / step))
        if self._window is not None and self._window[2] == cell:
            return
        built = self._windows.pop(cell, None)
        if built is None:
            self._build((np.asarray(cell, float) + 0.5) * step)
            built = (self.scene, self._sel, self._vol_scene, self._vsel, self._vol_discs)
        self.scene, self._sel, self._vol_scene, self._vsel, self._vol_discs = built
        self._windows[cell] = built  # the newest last
        while len(self._windows) > WINDOW_CACHE:
            self._windows.pop(next(iter(self._windows)))
        self._window = ((np.asarray(cell, float) + 0.5) * step, half, cell)

    # --- casting --------------------------------------------------------------------------------
    def _cast_static(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast (N, 6) float32 rays (origin, unit direction) at the static scene in use: range
        (N,) float64 (inf: no hit), triangle (N,) int64 (index into ``_F``; -1: no hit), unit
        normals (N, 3) float64. A windowed scene casts the window and the world's terrain scene
        and keeps the nearer hit (the window's on a tie)."""
        o3d = self._o3d
        tensor = o3d.core.Tensor(rays)
        ans = self.scene.cast_rays(tensor, nthreads=raycast_threads())
        if self._terrain_scene is None:
            from blockloc.sim import _kernels

            return _kernels.static_hits(ans["t_hit"].numpy(), ans["primitive_ids"].numpy(),
                                        ans["primitive_normals"].numpy(), self._sel)
        t = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        normals = ans["primitive_normals"].numpy()
        hit = np.isfinite(t)
        tri = np.full(len(t), -1, np.int64)
        tri[hit] = self._sel[prim[hit]]
        if self._terrain_scene is not None:
            g = self._terrain_scene.cast_rays(tensor, nthreads=raycast_threads())
            t_g = g["t_hit"].numpy()
            nearer = t_g < t
            if nearer.any():
                t = np.where(nearer, t_g, t)
                tri = np.where(nearer, self._terrain_first + g["primitive_ids"].numpy().astype(np.int64), tri)
                normals = np.where(nearer[:, None], g["primitive_normals"].numpy(), normals)
        return t.astype(np.float64), tri, normals.astype(np.float64)

    def cast(self, origins: np.ndarray, dirs: np.ndarray, t: float | None = None,
             max_range: float = np.inf, rng: np.random.Generator | None = None):
        h = self.cast_full(origins, dirs, t, max_range, rng)
        return h["range"], h["normal"], h["reflect"], h["cat"]

    def cast_full(self, origins: np.ndarray, dirs: np.ndarray, t: float | None = None,
                  max_range: float = np.inf, rng: np.random.Generator | None = None) -> dict:
        """Cast rays (world origins, unit dirs, (N, 3) each) at session time t (None: no moving
        actors). rng draws the stochastic parts (foliage stops, grass, glass); default seeded 0.
        Returns dict range, normal, reflect, cat, glass (bool), retro (bool)."""
        with self._lock:
            return self._cast_full(origins, dirs, t, max_range, rng)

    def _cast_full(self, origins, dirs, t, max_range, rng) -> dict:
        from blockloc.sim import _kernels

        rng = rng if rng is not None else np.random.default_rng(0)
        self._ensure_window(origins[len(origins) // 2])
        rays = _kernels.make_rays(origins, dirs)
        rng_, tri, normals = self._cast_static(rays)
        cat, reflect = _kernels.hit_categories(rng_, tri, self._tri_cat, self._reflect_by_cat)
        glass = np.zeros(len(rng_), dtype=bool)
        g_idx, p = _kernels.ground_hits(origins, dirs, rng_, cat, self.terrain_cat)
        if len(g_idx):
            if self.detail.ground_relief:  # the material is looked up once, for both
                mat = self.world.ground_material(p[:, 0], p[:, 1])
                reflect[g_idx] = GROUND_ALBEDO[mat]
                self._ground_relief(g_idx, origins, dirs, rng_, normals, reflect, rng, p, mat)
            else:
                reflect[g_idx] = self.world.ground_albedo(p[:, 0], p[:, 1])
        lost_at = np.full(len(rng_), np.inf)  # range of the pane a ray is lost at
        if len(self.world.facades):  # the rays on a facade take its row's reflectance (in the kernel)
            on_bldg, owner = _kernels.facade_rays(cat, tri, self._tri_owner, self._is_facade_cat,
                                                  self.world.facades, reflect)
            if len(on_bldg) and self.detail.facade_detail:
                self._facades(on_bldg, owner, origins, dirs, rng_, normals, reflect, glass, rng, cat, lost_at)
        if self._vol_scene is not None:
            self._vegetation(origins, dirs, rays, rng_, normals, reflect, cat, rng)
        if t is not None and len(self.actors.kind):
            self._cast_actors(origins, dirs, rays, t, max_range, rng_, normals, reflect, cat)
        # A ray lost at a pane stays lost: vegetation or actors stop it only in front of the pane
        # (before, foliage behind a lost window returned, labelled glass).
        at_pane = np.isfinite(lost_at)
        if at_pane.any():
            rng_[at_pane & (rng_ >= lost_at)] = np.inf
            glass &= ~(at_pane & np.isfinite(rng_))
        retro = np.zeros(len(rng_), dtype=bool)
        if self.detail.retroreflectors and "sign" in self._cat_index:
            retro = cat == self._cat_index["sign"]
        glass_cat = self._cat_index["glass"]
        cat = np.where(glass & np.isfinite(rng_), glass_cat, cat)
        return {"range": rng_, "normal": normals, "reflect": reflect, "cat": cat, "glass": glass,
                "retro": retro}

    def _ground_relief(self, idx, origins, dirs, rng_, normals, reflect, rng, p, mat) -> None:
        """Kerbs (sidewalks KERB_M above the road), grass (a layer 4-12 cm high that rays
        enter and stop in) and a few cm of micro relief, applied along each ground ray ``idx``
        (of the rays ``origins``, ``dirs`` (N, 3)), which hit the terrain at ``p`` (len(idx), 3),
        of ground material ``mat``."""
        from blockloc.sim import _kernels

        world = self.world
        seed = self._seed
        r, r_new, down = _kernels.ground_micro(rng_, dirs, idx, p, mat, np.int64(seed * 83492791))
        # kerb: the sidewalk surface is raised; a ray whose raised hit falls back over the road
        # meets the kerb's face instead
        side, r_0, r_side, x1, y1 = _kernels.kerb_rays(idx, mat, origins, dirs, r, down, KERB_M)
        if len(side):
            face = world.ground_material(x1, y1) == 0
            r_s = r_side.copy()
            if face.any():  # only those rays meet the kerb's face
                at = idx[side[face]]
                o_f, d_f = origins[at], dirs[at]
                lo, hi = r_side[face], r_0[face]
                for _ in range(5):  # bisect on the road edge along the ray
                    mid = 0.5 * (lo + hi)
                    pm = o_f + d_f * mid[:, None]
                    on_road = world.ground_material(pm[:, 0], pm[:, 1]) == 0
                    lo = np.where(on_road, mid, lo)
                    hi = np.where(on_road, hi, mid)
                r_s[face] = hi
                n_face = np.c_[-d_f[:, :2], np.zeros(len(d_f))]
                n_face /= np.maximum(np.linalg.norm(n_face, axis=1, keepdims=True), 1e-9)
                normals[at] = n_face
            r_new[side] = r_s + (r_new[side] - r_0)
        grass = np.flatnonzero(mat == 2)
        if len(grass):  # the draws in their order: stops, tilts, reflectances
            stop = rng.exponential(0.25, len(grass))
            tilt = rng.normal(size=(len(grass), 3))
            refl = rng.uniform(0.6, 1.4, len(grass))
            _kernels.ground_grass(r_new, down, p, grass, idx, stop, tilt, normals, reflect, refl,
                                  np.int64((seed + 1) * 83492791))
        rng_[idx] = np.maximum(r_new, 0.05)

    def _facades(self, idx, owner, origins, dirs, rng_, normals, reflect, glass, rng, cat, lost_at) -> None:
        """Windows (glass recessed 18 cm: mostly lost, or a return from the room behind, or a
        dim one off the pane), pilasters standing 15 cm out and floor ledges 20 cm out.

        The room behind a window lies inside the box the window is in: its return is no deeper
        than the box along the ray (less the back wall). A box too thin to hold a room along the
        ray (ROOM_MIN_M: a corridor wall, a passage's pillar) has none: the ray passes the pane
        and returns from what lies behind (cast on from the far side; seen before: "room" returns
        1-6 m beyond a 0.3 m corridor wall, out in the street, where a map built from inside the
        corridor then held structure that no other session saw)."""
        from blockloc.sim import _kernels

        # the draws in their order (glass, then room depths), then one pass (numpy's operations
        # in its order: the bits of the numpy this was, tests/sim/test_kernels.py)
        u_g = rng.random(len(idx))
        room_draw = rng.uniform(1.0, 6.0, len(idx))
        r, flags, depth, u, z = _kernels.facade_faces(idx, owner, self.world.facades, origins, dirs, rng_, normals,
                                                      u_g, room_draw, ROOM_MIN_M, BACK_WALL_M)
        inside = (flags & _kernels.FACADE_INSIDE) != 0
        through = np.flatnonzero(inside & ((flags & _kernels.FACADE_ROOM) == 0))
        passed = np.zeros(len(idx), bool)
        if len(through):
            self._through_pane(idx[through], origins, dirs, rng_[idx[through]] + depth[through], r, through,
                               normals, reflect, cat)
            passed[through] = True  # what lies behind is no glass return
        _kernels.facade_finish(idx, r, flags, passed, u, z, np.int64(int(self._seed + 2) * 83492791),
                               ALBEDO["glass"], rng_, reflect, glass, lost_at)

    def _through_pane(self, rays, origins, dirs, t_exit, r, at, normals, reflect, cat) -> None:
        """Rays ``rays`` (indices) leave a thin box at ``t_exit`` (m along the ray): cast them on
        through the static scene; their range goes to ``r[at]``, their hit's normal, reflectance
        and category to the arrays (vegetation and actors are applied afterwards to every ray)."""
        start = t_exit + 0.02
        o = origins[rays] + dirs[rays] * start[:, None]
        t2, tri, n2 = self._cast_static(np.concatenate([o, dirs[rays]], axis=1).astype(np.float32))
        hit = np.isfinite(t2)
        c2 = np.where(hit, self._tri_cat[tri].astype(np.int64), -1)
        r[at] = np.where(hit, start + t2, np.inf)
        normals[rays] = np.where(hit[:, None], n2, normals[rays])
        cat[rays] = c2
        refl = self._reflect_by_cat[c2]
        ground = c2 == self.terrain_cat
        if ground.any():
            p = o[ground] + dirs[rays][ground] * t2[ground, None]
            refl[ground] = self.world.ground_albedo(p[:, 0], p[:, 1])
        reflect[rays] = refl

    def _vegetation(self, origins, dirs, rays, rng_, normals, reflect, cat, rng) -> None:
        """Rays through crowns, bushes and hedges: inside a volume a ray stops after an
        exponential free path (mean ``mfp``), or leaves it and goes on (to the trunk, another
        crown, the ground). Up to four volumes a ray. ``rays``: (N, 6) float32 origins and
        directions, the first pass's rays (every ray from its origin)."""
        from blockloc.sim import _kernels

        o3d = self._o3d
        vol = self.world.volumes
        # the first pass casts only the rays that could meet a hull before their range: a hull
        # met at or beyond it is not taken (vegetation_hits), so the others' answers are not read
        active = self._rays_near_hulls(origins, dirs, rng_)
        if len(active) < len(rng_):
            rays = rays[active]
        t_cur = np.zeros(len(rng_))
        fol = self._cat_index["foliage"]
        for k in range(4):
            if not len(active):
                break
            if k:  # on from where each ray left its last volume
                rays = _kernels.vegetation_rays(origins, dirs, active, t_cur)
            a = self._vol_scene.cast_rays(o3d.core.Tensor(rays), nthreads=raycast_threads())
            active, th, v, t_in, t_out, miss = _kernels.vegetation_hits(
                a["t_hit"].numpy(), a["primitive_ids"].numpy(), active, t_cur, rng_, self._vsel, len(_ICO_F),
                origins, dirs, vol.center, self._vol_radii, k == 0)
            if not len(active):
                break
            free_path = rng.exponential(self._vol_mfp[v])
            j, active = _kernels.vegetation_stops(active, th, t_in, t_out, miss, free_path, rng_, t_cur)
            normals[j] = _random_unit(rng, len(j))
            reflect[j] = ALBEDO["foliage"] * rng.uniform(0.4, 1.4, len(j))
            cat[j] = fol

    def _rays_near_hulls(self, origins, dirs, rng_) -> np.ndarray:
        """Indices (M,) of the rays (origins, dirs (N, 3), ranges rng_ (N,)) that might meet a
        vegetation hull before their range: the others point, in xy, into a sector (``SECTORS``
        round the scan's middle origin) whose nearest hull disc lies farther than their range
        takes them in xy. Conservative by 5 cm and a sector each side."""
        from blockloc.sim import _kernels

        if self._vol_discs is None or not len(rng_):
            return np.arange(len(rng_))
        c0 = np.ascontiguousarray(origins[len(origins) // 2, :2])
        reach = _kernels.sector_reach(c0, _kernels.xy_spread(origins, c0), self._vol_discs[0], self._vol_discs[1],
                                      SECTORS)
        return _kernels.rays_reaching(dirs, rng_, reach, 0.05)

    def actor_mesh(self, t: float, center: np.ndarray, radius: float):
        """Actors within ``radius`` of ``center`` (2,) at time t: (V, F, category per triangle)."""
        xy, yaw = self.actors.poses(t)
        gait = self.actors.gait(t)
        near = np.flatnonzero(np.linalg.norm(xy - center[:2], axis=1) < radius)
        if not len(near):
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=int)
        kind = self.actors.kind[near]
        V, F, owner = actor_meshes(kind, xy[near, 0], xy[near, 1], yaw[near], gait[near], self.world.terrain)
        kind_cat = np.array([self._cat_index[str(k)] for k in kind])
        return V, F, kind_cat[owner]

    def _cast_actors(self, origins, dirs, rays, t, max_range, rng_, normals, reflect, cat) -> None:
        """Overwrite (in place) the returns of rays that hit a moving actor first. Only rays
        pointing at an actor's bounding circle are cast against the per-scan actor scene."""
        o3d = self._o3d
        center = origins[len(origins) // 2]
        V, F, tri_cat = self.actor_mesh(t, center, max_range + 10.0)
        if not len(F):
            return
        xy, _ = self.actors.poses(t)
        near = np.linalg.norm(xy - center[:2], axis=1) < max_range + 10.0
        # select per column when rays come in columns sharing an origin (the lidar model casts
        # 32 a column), then the rays of the column long enough to reach an actor's circle; the
        # bounding circle is 3.5 m, wider than any actor, for the tilt margin (the lidar model's
        # columns are exactly equal: that check first, ~40x cheaper than allclose)
        first, last = origins[::32], origins[31::32]
        step = 32 if len(rays) % 32 == 0 and (np.array_equal(first, last) or np.allclose(first, last)) else 1
        from blockloc.sim import _kernels

        idx = _kernels.actor_rays(np.ascontiguousarray(xy[near]), origins, dirs, rng_, step, ACTOR_RADIUS_M, 0.1)
        if not len(idx):
            return
        dyn = o3d.t.geometry.RaycastingScene(nthreads=raycast_threads())
        dyn.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
        a2 = dyn.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays[idx])), nthreads=raycast_threads())
        r2 = a2["t_hit"].numpy().astype(np.float64)
        closer = r2 < rng_[idx]
        if closer.any():
            j = idx[closer]
            rng_[j] = r2[closer]
            normals[j] = a2["primitive_normals"].numpy()[closer]
            c2 = tri_cat[a2["primitive_ids"].numpy()[closer].astype(np.int64)]
            cat[j] = c2
            reflect[j] = self._reflect_by_cat[c2]

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (N,) from world points (N, 3) to the static scene's surfaces."""
        o3d = self._o3d
        query = o3d.core.Tensor(np.asarray(points, np.float32))
        with self._lock:
            self._ensure_window(np.asarray(points, float).mean(axis=0))
            d = self.scene.compute_distance(query).numpy()
            if self._terrain_scene is not None:
                d = np.minimum(d, self._terrain_scene.compute_distance(query).numpy())
        return d
