"""A session's ray-casting scene: the static world plus that day's movable objects (one open3d
``RaycastingScene``), and the moving pedestrians and vehicles, cast as a small per-scan scene.

Frame: world, z up, metres (see ``blockloc.sim.world``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from blockloc.sim.world import ALBEDO, MeshBuilder, Movables, World, movable_mesh, stable_hash

log = logging.getLogger(__name__)


@dataclass
class Actors:
    """Moving pedestrians and vehicles, each going back and forth along one straight road.

    kind: (K,) 'pedestrian' | 'vehicle'; a, b: (K, 2) ends of its line (world, m);
    offset: (K,) metres to the right of its travel direction; speed: (K,) m/s; phase: (K,) m.
    """

    kind: np.ndarray
    a: np.ndarray
    b: np.ndarray
    offset: np.ndarray
    speed: np.ndarray
    phase: np.ndarray

    def poses(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(K, 2) positions and (K,) headings at session time t (s)."""
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


def make_actors(world: World, session: str) -> Actors:
    """The session's moving people and vehicles (deterministic from seed and session)."""
    rng = np.random.default_rng(np.random.SeedSequence([world.seed, stable_hash(session), 3]))
    roads, p = world.roads, world.preset
    x0, x1, y0, y1 = world.extent
    hw = roads.width_m / 2
    kinds, A, B, off, spd = [], [], [], [], []
    for k in range(p.n_pedestrians + p.n_vehicles):
        ped = k < p.n_pedestrians
        if rng.random() < 0.5:
            x = roads.xs[rng.integers(len(roads.xs))]
            a, b = (x, y0), (x, y1)
        else:
            y = roads.ys[rng.integers(len(roads.ys))]
            a, b = (x0, y), (x1, y)
        if ped:  # a stretch of sidewalk
            a, b = np.array(a, float), np.array(b, float)
            L = np.linalg.norm(b - a)
            s0 = rng.uniform(0, L - 40)
            u = (b - a) / L
            a, b = a + u * s0, a + u * (s0 + rng.uniform(20, 40))
            kinds.append("pedestrian")
            off.append(rng.choice([-1, 1]) * (hw + rng.uniform(1.0, 2.0)))
            spd.append(rng.uniform(0.8, 1.5))
        else:
            kinds.append("vehicle")
            off.append(hw - 0.7)  # keeps ~0.7 m clear of the robot (LANE_OFFSET_M)
            spd.append(rng.uniform(3.0, 7.0))
        A.append(a)
        B.append(b)
    A, B = np.array(A, float).reshape(-1, 2), np.array(B, float).reshape(-1, 2)
    L = np.linalg.norm(B - A, axis=1)
    return Actors(np.array(kinds), A, B, np.array(off), np.array(spd), rng.uniform(0, 2 * L))


class SessionScene:
    """Static world + one day's movables in a RaycastingScene; actors added per scan.

    ``cast(origins, dirs, t)`` returns range (N,) (inf where nothing is hit), unit normals
    (N, 3), albedo (N,) and a category code (N,) int (index into ``categories``).
    """

    def __init__(self, world: World, movables: Movables, actors: Actors):
        from blockloc._open3d import open3d

        o3d = open3d()
        self.world = world
        self.movables = movables
        self.actors = actors
        self.scene = o3d.t.geometry.RaycastingScene()
        self.categories: list[str] = []
        self._albedo_by_gid: dict[int, float] = {}
        self._cat_by_gid: dict[int, int] = {}
        meshes = dict(world.meshes)
        mb = {k: MeshBuilder() for k in ("car", "bin")}
        for kind, (x, y), yaw in zip(movables.kind, movables.xy, movables.yaw):
            for V, F in movable_mesh(str(kind), x, y, yaw, world.terrain):
                mb[str(kind)].add(V, F)
        for k, b in mb.items():
            V, F = b.build()
            if len(F):
                meshes[k] = (V, F)
        for name, (V, F) in meshes.items():
            gid = self.scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)),
                                           o3d.core.Tensor(F.astype(np.uint32)))
            self._register(gid, name)
        self.terrain_gid = [g for g, c in self._cat_by_gid.items() if self.categories[c] == "terrain"][0]
        for name in ("pedestrian", "vehicle"):
            if name not in self.categories:
                self.categories.append(name)
        self._o3d = o3d
        n = max(self._cat_by_gid) + 2  # the last slot stands for "no hit"
        self._alb_lut = np.zeros(n)
        self._cat_lut = np.full(n, -1, dtype=np.int64)
        for g in self._cat_by_gid:
            self._alb_lut[g] = self._albedo_by_gid[g]
            self._cat_lut[g] = self._cat_by_gid[g]

    def _register(self, gid: int, name: str) -> None:
        if name not in self.categories:
            self.categories.append(name)
        self._cat_by_gid[int(gid)] = self.categories.index(name)
        self._albedo_by_gid[int(gid)] = ALBEDO[name]

    def actor_mesh(self, t: float, center: np.ndarray, radius: float):
        """Actors within ``radius`` of ``center`` (2,) at time t: (V, F, category per triangle)."""
        xy, yaw = self.actors.poses(t)
        near = np.linalg.norm(xy - center[:2], axis=1) < radius
        b = MeshBuilder()
        cats = []
        for k in np.flatnonzero(near):
            kind = str(self.actors.kind[k])
            for V, F in movable_mesh(kind, xy[k, 0], xy[k, 1], yaw[k], self.world.terrain):
                b.add(V, F)
                cats.append(np.full(len(F), self.categories.index(kind)))
        V, F = b.build()
        return V, F, (np.concatenate(cats) if cats else np.zeros(0, dtype=int))

    def cast(self, origins: np.ndarray, dirs: np.ndarray, t: float | None = None,
             max_range: float = np.inf):
        o3d = self._o3d
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        rng_ = ans["t_hit"].numpy().astype(np.float64)
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        normals = ans["primitive_normals"].numpy().astype(np.float64)
        hit = np.isfinite(rng_)
        gid_safe = np.where(hit, gid, len(self._alb_lut) - 1)
        albedo = self._alb_lut[gid_safe]
        cat = self._cat_lut[gid_safe]
        if t is not None and len(self.actors.kind):
            self._cast_actors(origins, dirs, rays, t, max_range, rng_, normals, albedo, cat)
        on_ground = cat == self._cat_by_gid[self.terrain_gid]
        if on_ground.any():
            p = origins[on_ground] + dirs[on_ground] * rng_[on_ground, None]
            albedo[on_ground] = self.world.ground_albedo(p[:, 0], p[:, 1])
        return rng_, normals, albedo, cat

    def _cast_actors(self, origins, dirs, rays, t, max_range, rng_, normals, albedo, cat) -> None:
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
        # 32 a column); the bounding circle is 3.5 m, wider than any actor, for the tilt margin
        step = 32 if len(rays) % 32 == 0 and np.allclose(origins[::32], origins[31::32]) else 1
        o = origins[::step, :2]
        dv = dirs[::step, :2]
        hx = np.hypot(dv[:, 0], dv[:, 1]) + 1e-12
        sel_c = np.zeros(len(o), dtype=bool)
        for p in xy[near]:
            rel = p - o
            dist = np.hypot(rel[:, 0], rel[:, 1])
            along = (rel[:, 0] * dv[:, 0] + rel[:, 1] * dv[:, 1]) / hx
            perp2 = np.maximum(dist * dist - along * along, 0.0)
            sel_c |= (perp2 < 3.5 * 3.5) & ((along > 0) | (dist < 3.5))
        sel = np.repeat(sel_c, step)
        idx = np.flatnonzero(sel)
        if not len(idx):
            return
        dyn = o3d.t.geometry.RaycastingScene()
        dyn.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
        a2 = dyn.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays[idx])))
        r2 = a2["t_hit"].numpy().astype(np.float64)
        closer = r2 < rng_[idx]
        if closer.any():
            j = idx[closer]
            rng_[j] = r2[closer]
            normals[j] = a2["primitive_normals"].numpy()[closer]
            c2 = tri_cat[a2["primitive_ids"].numpy()[closer].astype(np.int64)]
            cat[j] = c2
            albedo[j] = np.array([ALBEDO[c] for c in self.categories])[c2]

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (N,) from world points (N, 3) to the static scene's surfaces."""
        o3d = self._o3d
        return self.scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy()
