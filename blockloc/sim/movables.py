"""Objects that change between sessions: parked cars and bins (a session's "day" moves,
removes and adds some), and the meshes of movables and of moving actors (pedestrians, vehicles)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.sim.meshes import _BOX_F, box_mesh
from blockloc.sim.seeds import stable_hash
from blockloc.sim.terrain import Terrain

MOVABLE_KINDS = ("car", "bin")
#: half length and half width (m) of each movable's footprint, as :func:`movable_meshes` draws it
MOVABLE_HALF_EXTENT_M = {"car": (2.2, 0.9), "bin": (0.3, 0.3)}
#: how close (m) a movable's footprint may come to a route: the robot's half width and a margin
ROUTE_CLEARANCE_M = 0.8


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


def session_movables(world, session: str, base: bool) -> Movables:
    """The movable objects present on a session's day (``world``: a ``blockloc.sim.world.World``).

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


def _boxes_each(cx, cy, z0, z1, lx, ly, yaw) -> np.ndarray:
    """:func:`box_mesh` of M boxes of their own sizes (lx, ly (M,) too): vertices (M, 8, 3), the
    same arithmetic as one box at a time."""
    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.empty((len(yaw), 4, 2))
    corners[:, :, 0] = np.stack([-lx, lx, lx, -lx], axis=1)
    corners[:, :, 1] = np.stack([-ly, -ly, ly, ly], axis=1)
    corners *= 0.5
    R = np.empty((len(yaw), 2, 2))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = c, s, -s, c
    xy = np.matmul(corners, R) + np.stack([cx, cy], axis=-1)[:, None, :]
    V = np.empty((len(yaw), 8, 3))
    V[:, :4, :2] = V[:, 4:, :2] = xy
    V[:, :4, 2], V[:, 4:, 2] = z0[:, None], z1[:, None]
    return V


def _limbs(bx, by, bz, yaw, swing, length: float, thick: float) -> tuple:
    """:func:`_limb` of M limbs (bx, by, bz, yaw, swing (M,)): the box_mesh arguments, arrays."""
    c, s = np.cos(yaw), np.sin(yaw)
    sw, cw = np.sin(swing), np.cos(swing)
    tx, ty, tz = bx + length * (sw * c), by + length * (sw * s), bz + length * -cw
    mx, my = (bx + tx) / 2, (by + ty) / 2
    L = np.abs(sw) * length + thick
    th = np.full(len(yaw), thick)
    return mx, my, np.minimum(bz, tz), np.maximum(bz, tz), np.maximum(L, th), th, yaw


def actor_meshes(kind: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, gait: np.ndarray,
                 terrain: Terrain) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The meshes :func:`movable_mesh` gives actor by actor ('vehicle', 'pedestrian'; gait (K,)
    rad, NaN: a rigid walker), built at once: vertices (P * 8, 3), triangles (P * 12, 3) and the
    actor (K,) index of each triangle, the parts in the actors' order (a scan's 20-40 actors were
    ~150 boxes built one at a time)."""
    kind = np.asarray(kind).astype(str)
    z = terrain.height(x, y)
    veh = kind == "vehicle"
    walk = (kind == "pedestrian") & np.isfinite(gait)
    rigid = (kind == "pedestrian") & ~np.isfinite(gait)
    unknown = ~(veh | walk | rigid)
    if unknown.any():
        raise ValueError(f"actor kinds {sorted(set(kind[unknown].tolist()))}: "
                         "expected vehicle, pedestrian")
    nparts = np.where(veh, 2, np.where(walk, 6, 1))
    first = np.concatenate([[0], np.cumsum(nparts)[:-1]]).astype(np.int64)
    V = np.empty((int(nparts.sum()), 8, 3))

    def put(sel, part, boxes):
        V[first[sel] + part] = _boxes_each(*boxes)

    if veh.any():
        m = veh
        xv, yv, zv, a = x[m], y[m], z[m], yaw[m]
        one = np.ones(len(a))
        put(m, 0, (xv, yv, zv + 0.25, zv + 1.0, 4.4 * one, 1.8 * one, a))
        put(m, 1, (xv - 0.2 * np.cos(a), yv - 0.2 * np.sin(a), zv + 1.0, zv + 1.5, 2.4 * one, 1.6 * one,
                   a))
    if rigid.any():
        m = rigid
        one = np.ones(int(m.sum()))
        put(m, 0, (x[m], y[m], z[m] - 0.05, z[m] + 1.75, 0.35 * one, 0.5 * one, yaw[m]))
    if walk.any():  # pedestrian_mesh, height 1.75 m (k = 1)
        m = walk
        xw, yw, zw, a = x[m], y[m], z[m], yaw[m]
        k = 1.75 / 1.75
        one = np.ones(len(a))
        hip = zw + 0.9 * k
        latx, laty = -np.sin(a), np.cos(a)
        put(m, 0, (xw, yw, hip, zw + 1.5 * k, 0.24 * one, 0.42 * one, a))
        put(m, 1, (xw, yw, zw + 1.52 * k, zw + 1.75, 0.2 * one, 0.18 * one, a))
        swing = 0.45 * np.sin(gait[m])
        for j, (side, sgn) in enumerate(((-1, 1), (1, -1))):
            put(m, 2 + 2 * j, _limbs(xw + latx * side * 0.1, yw + laty * side * 0.1, hip + 0.0 * side * 0.1,
                                     a, sgn * swing, 0.9 * k, 0.14))
            put(m, 3 + 2 * j, _limbs(xw + latx * side * 0.25, yw + laty * side * 0.25,
                                     zw + 1.45 * k + 0.0 * side * 0.25, a, -sgn * 0.8 * swing,
                                     0.65 * k, 0.09))
    F = (_BOX_F[None] + 8 * np.arange(len(V))[:, None, None]).reshape(-1, 3).astype(np.int64)
    owner = np.repeat(np.repeat(np.arange(len(kind)), nparts), len(_BOX_F))
    return V.reshape(-1, 3), F, owner
