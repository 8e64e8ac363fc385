"""A world that changes between days, with ground truth of what changed (issue 43).

The mapping day is month 0. Sessions ``loc_m3`` and ``loc_m12`` drive the ``loc`` route 3 and 12
months later, ``map_m12`` drives the mapping route 12 months later; its mapping poses carry the
same kind of offline-SLAM error as the mapping day's (``slam_error_m``, ``slam_error_rad``), from
its own random stream, so a map built fresh from it is as good as the mapping day's map was, not
better. Over the year, deterministically from the seed:

=================  ======  ==================================================================
change             month   what
=================  ======  ==================================================================
hedge_cut          2       the hedge pieces around one spot near a route are gone
construction_site  2..8    a fenced lot with two site containers (category ``construction``)
building_added     9       a building where the site stood (category ``new_building``)
building_removed   7       one building near a route demolished (its triangles gone)
wall_added         10      a 10 m garden wall (category ``new_wall``)
parked cars        any     ``session_movables`` rearranges the parked cars and bins of each
                           day; those not where the mapping day had them are ``changed_car`` /
                           ``changed_bin``
=================  ======  ==================================================================

Pedestrians and moving cars are there as on any localization day (``make_actors``).

Every ray-cast point carries a label (:data:`LABEL_STATIC` / ``CHANGED`` / ``MOVING``): what it
hit. A point behind a removed building hits static structure and is static. Boxes are in the
world frame (z up, metres) and in the NCLT map frame (z down) as ``x0 x1 y0 y1 z0 z1``.

Nothing here changes the existing sessions: their scenes, routes and noise are untouched.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from blockloc.errors import SimError
from blockloc.fileio import load_array
from blockloc.sim.presets import Preset
from blockloc.sim.stream import SimSequence, route_points, scene_movables
from blockloc.sim.world import Movables, Volumes, World, box_mesh, movable_meshes, stable_hash

log = logging.getLogger(__name__)

#: session -> (session whose route it drives: "loc" or the first mapping drive, months after)
CHANGE_SESSIONS = {"loc_m3": ("loc", 3), "loc_m12": ("loc", 12), "map_m12": ("map", 12)}
#: (date in NCLT file names, epoch s at UTC noon) of each changed session
CHANGE_DAYS = {"loc_m3": ("2020-09-08", 1599566400), "loc_m12": ("2021-06-08", 1623153600),
               "map_m12": ("2021-06-01", 1622548800)}
LABEL_STATIC, LABEL_CHANGED, LABEL_MOVING = 0, 1, 2
LABEL_NAMES = ("static", "changed", "moving")
#: mesh categories of structure that was not there on the mapping day
CHANGED_CATEGORIES = ("construction", "new_building", "new_wall", "changed_car", "changed_bin")
MOVING_CATEGORIES = ("pedestrian", "vehicle")


def sessions_for_months(months) -> tuple[str, ...]:
    """The changed sessions of ``months`` (e.g. (3, 12) -> loc_m3, loc_m12, map_m12)."""
    out = []
    for m in months:
        got = [s for s, (_, mm) in CHANGE_SESSIONS.items() if mm == int(m)]
        if not got:
            raise SimError(f"--months {m}: expected one of "
                           f"{', '.join(str(v) for v in sorted({mm for _, mm in CHANGE_SESSIONS.values()}))}")
        out += got
    return tuple(out)


@dataclass(frozen=True)
class Change:
    """One change against the mapping day.

    kind: hedge_cut | construction_site | building_added | building_removed | wall_added |
    parked_car | parked_bin. action: added | removed | moved (moved = removed where it was and
    added where it is). months: (first, last) month it holds (last inclusive; 99 = still).
    category: mesh category of the added geometry ('' when removed). box_world: x0 x1 y0 y1 z0 z1
    (world, z up, m) of what appeared or disappeared.
    """

    kind: str
    action: str
    months: tuple[int, int]
    category: str
    box_world: tuple[float, ...]
    ident: int = -1  # building row, volume indices' first, movable uid

    def box_map(self) -> list[float]:
        """The box in the NCLT map frame (x, -y, -z of the world)."""
        x0, x1, y0, y1, z0, z1 = self.box_world
        return [x0, x1, -y1, -y0, -z1, -z0]

    def to_json(self) -> dict:
        return {"kind": self.kind, "action": self.action, "months": list(self.months),
                "category": self.category, "box_world": [round(float(v), 3) for v in self.box_world],
                "box_map": [round(float(v), 3) for v in self.box_map()], "id": int(self.ident)}


@dataclass
class _Plan:
    changes: list[Change]
    removed_hedges: np.ndarray  # volume indices
    removed_building: int  # facade row, -1: none
    meshes: dict  # kind -> (V, F) of the added structure (world)


def _free_spot(world: World, rng: np.random.Generator, half: tuple[float, float], taken: list,
               near: np.ndarray) -> tuple[float, float] | None:
    """A centre (x, y) for an axis-aligned footprint of half extents ``half`` (m) within 6-20 m of
    a route point, clear of routes (3 m), roads, buildings, vegetation, movables and ``taken``."""
    roads = world.roads
    x0, x1, y0, y1 = world.extent
    from scipy.spatial import cKDTree

    tree = cKDTree(near)
    fac = world.facades
    vol = world.volumes
    mv = np.asarray(world.movables.xy, float).reshape(-1, 2)
    hx, hy = half
    for _ in range(4000):
        p = near[rng.integers(len(near))]
        a = rng.uniform(0, 2 * np.pi)
        r = rng.uniform(6.0, 20.0) + max(hx, hy)
        cx, cy = p[0] + r * np.cos(a), p[1] + r * np.sin(a)
        if not (x0 + 10 < cx - hx and cx + hx < x1 - 10 and y0 + 10 < cy - hy and cy + hy < y1 - 10):
            continue
        corners = np.array([[cx + sx * hx, cy + sy * hy] for sx in (-1, 0, 1) for sy in (-1, 0, 1)])
        if tree.query(corners)[0].min() < 3.0 + 0.0 or tree.query([cx, cy])[0] < max(hx, hy) + 3.0:
            continue
        if (roads.distance(corners[:, 0], corners[:, 1]) < roads.width_m / 2 + 2.5).any():
            continue
        if np.isfinite(roads.path_distance(corners[:, 0], corners[:, 1])).any() and \
                (roads.path_distance(corners[:, 0], corners[:, 1]) < 2.5).any():
            continue
        m = 2.0
        if len(fac) and ((fac[:, 0] < cx + hx + m) & (fac[:, 1] > cx - hx - m)
                         & (fac[:, 2] < cy + hy + m) & (fac[:, 3] > cy - hy - m)).any():
            continue
        if vol is not None and len(vol):
            c, rr = vol.center, vol.radii
            if ((np.abs(c[:, 0] - cx) < hx + rr[:, 0] + 1) & (np.abs(c[:, 1] - cy) < hy + rr[:, 1] + 1)).any():
                continue
        if len(mv) and ((np.abs(mv[:, 0] - cx) < hx + 3) & (np.abs(mv[:, 1] - cy) < hy + 3)).any():
            continue
        if any(abs(cx - tx) < hx + thx + 3 and abs(cy - ty) < hy + thy + 3 for tx, ty, thx, thy in taken):
            continue
        taken.append((cx, cy, hx, hy))
        return float(cx), float(cy)
    return None


def _box_of(V: np.ndarray) -> tuple[float, ...]:
    lo, hi = V.min(axis=0), V.max(axis=0)
    return (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])


def plan_changes(world: World) -> _Plan:
    """Every structural change of the year (module docstring), deterministic by the world's seed.
    Changes that find no place (a world without hedges...) are left out."""
    p = world.preset
    rng = np.random.default_rng(np.random.SeedSequence([world.seed, stable_hash("lifelong"), 43]))
    near = route_points(p, world.seed)[::8]
    H = world.terrain.height
    changes: list[Change] = []
    meshes: dict[str, list] = {"construction": [], "new_building": [], "new_wall": []}
    taken: list = []
    from scipy.spatial import cKDTree

    tree = cKDTree(near)
    # hedge cut: the hedge pieces within 6 m of one near a route
    removed_hedges = np.zeros(0, dtype=np.int64)
    vol = world.volumes
    if vol is not None and len(vol):
        hedge = np.flatnonzero(vol.kind == 2)
        if len(hedge):
            d = tree.query(vol.center[hedge, :2])[0]
            cand = hedge[(d > 2.0) & (d < 15.0)]
            if len(cand):
                k = cand[rng.integers(len(cand))]
                removed_hedges = hedge[np.linalg.norm(vol.center[hedge, :2] - vol.center[k, :2], axis=1) < 6.0]
                lo = (vol.center[removed_hedges] - vol.radii[removed_hedges]).min(axis=0)
                hi = (vol.center[removed_hedges] + vol.radii[removed_hedges]).max(axis=0)
                changes.append(Change("hedge_cut", "removed", (2, 99), "",
                                      (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]), int(k)))
    # construction site (months 2..8), then a building on the lot (9..)
    spot = _free_spot(world, rng, (9.0, 7.0), taken, near)
    if spot is not None:
        cx, cy = spot
        z = float(H(cx, cy))
        site = []
        x0, x1, y0, y1 = cx - 9, cx + 9, cy - 7, cy + 7
        for ax, ay, bx, by in ((x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)):
            n = max(1, int(np.hypot(bx - ax, by - ay) / 3.0))
            for k in range(n):
                if (ax, ay) == (x0, y0) and k == n // 2:
                    continue  # the gate
                s = (k + 0.5) / n
                px, py = ax + (bx - ax) * s, ay + (by - ay) * s
                site.append(box_mesh(px, py, float(H(px, py)) - 0.3, float(H(px, py)) + 2.0,
                                     np.hypot(bx - ax, by - ay) / n, 0.08, np.arctan2(by - ay, bx - ax)))
        for dx in (-4.0, 3.5):
            site.append(box_mesh(cx + dx, cy + 1.5, z - 0.2, z + 2.6, 6.0, 2.4, 0.0))
        meshes["construction"] += site
        Vs = np.concatenate([V for V, _ in site])
        changes.append(Change("construction_site", "added", (2, 8), "construction", _box_of(Vs)))
        bh = float(rng.uniform(7.0, 12.0))
        bld = box_mesh(cx, cy, z - 0.5, z + bh, 15.0, 11.0, 0.0)
        meshes["new_building"].append(bld)
        changes.append(Change("building_added", "added", (9, 99), "new_building", _box_of(bld[0])))
    # a wall (10..)
    spot = _free_spot(world, rng, (5.0, 0.6), taken, near)
    if spot is not None:
        cx, cy = spot
        z = float(H(cx, cy))
        wall = box_mesh(cx, cy, z - 0.3, z + 2.5, 10.0, 0.25, 0.0)
        meshes["new_wall"].append(wall)
        changes.append(Change("wall_added", "added", (10, 99), "new_wall", _box_of(wall[0])))
    # a building near a route demolished (7..)
    removed_building = -1
    owner = world.owners.get("building")
    if owner is not None and len(owner):
        rows = np.unique(owner)
        fac = world.facades[rows]
        c = np.c_[(fac[:, 0] + fac[:, 1]) / 2, (fac[:, 2] + fac[:, 3]) / 2]
        half = np.hypot(fac[:, 1] - fac[:, 0], fac[:, 3] - fac[:, 2]) / 2
        d = tree.query(c)[0] - half
        cand = rows[(d > 2.0) & (d < 15.0)]
        if len(cand):
            removed_building = int(cand[rng.integers(len(cand))])
            changes.append(Change("building_removed", "removed", (7, 99), "",
                                  tuple(world.facades[removed_building, :6]), removed_building))
    built = {k: (np.concatenate([V for V, _ in ms]),
                 np.concatenate([F + 8 * i for i, (_, F) in enumerate(ms)]).astype(np.int64))
             for k, ms in meshes.items() if ms}
    return _Plan(changes, removed_hedges, removed_building, built)


def _active(c: Change, month: int) -> bool:
    return c.months[0] <= month <= c.months[1]


def _movable_changes(world: World, session: str) -> tuple[Movables, Movables, list[Change]]:
    """(unchanged movables, changed ones, their changes) of a changed session's day."""
    base = scene_movables(world, "map", True)
    day = scene_movables(world, session, False)
    by_uid = {int(u): k for k, u in enumerate(base.uid)}
    same = np.zeros(len(day), dtype=bool)
    for k, u in enumerate(day.uid):
        j = by_uid.get(int(u))
        same[k] = j is not None and np.allclose(day.xy[k], base.xy[j]) and np.isclose(day.yaw[k], base.yaw[j])
    keep = lambda m, sel: Movables(m.kind[sel], m.xy[sel], m.yaw[sel], m.uid[sel])  # noqa: E731
    unchanged, changed = keep(day, same), keep(day, ~same)
    out = []
    for m, action in ((changed, "added"), (keep(base, ~np.isin(base.uid, unchanged.uid)), "removed")):
        for k in range(len(m)):
            kind = str(m.kind[k])
            V = movable_meshes(keep(m, np.array([k])), world.terrain)[kind][0]
            out.append(Change(f"parked_{kind}", action, (0, 99), f"changed_{kind}" if action == "added" else "",
                              _box_of(V), int(m.uid[k])))
    return unchanged, changed, out


def changed_world(world: World, session: str) -> tuple[World, Movables, list[Change]]:
    """(the world as it stands on ``session``'s day, that day's unchanged movables, the changes
    against the mapping day). The returned world's ``meshes`` hold the added structure under the
    :data:`CHANGED_CATEGORIES` (changed movables as ``changed_car`` / ``changed_bin``)."""
    if session not in CHANGE_SESSIONS:
        raise SimError(f"sim session {session!r}: expected one of {', '.join(CHANGE_SESSIONS)}")
    month = CHANGE_SESSIONS[session][1]
    plan = plan_changes(world)
    active = [c for c in plan.changes if _active(c, month)]
    meshes = dict(world.meshes)
    owners = dict(world.owners)
    if any(c.kind == "building_removed" for c in active):
        V, F = meshes["building"]
        keep = owners["building"] != plan.removed_building
        meshes["building"] = (V, F[keep])
        owners["building"] = owners["building"][keep]
    for c in active:
        if c.category and c.category in plan.meshes and c.category not in meshes:
            meshes[c.category] = plan.meshes[c.category]
    volumes = world.volumes
    if any(c.kind == "hedge_cut" for c in active) and len(plan.removed_hedges):
        keep = np.ones(len(volumes), dtype=bool)
        keep[plan.removed_hedges] = False
        volumes = Volumes(volumes.center[keep], volumes.radii[keep], volumes.mfp[keep], volumes.kind[keep])
    unchanged, changed, mv_changes = _movable_changes(world, session)
    for kind, (V, F) in movable_meshes(changed, world.terrain).items():
        meshes[f"changed_{kind}"] = (V, F)
    day = dataclasses.replace(world, meshes=meshes, owners=owners, volumes=volumes)
    return day, unchanged, active + mv_changes


def open_session(preset: str, session: str, seed: int, **overrides):
    """``blockloc.sim.stream.open_sim_sequence``, plus the changed days (``loc_m3``, ``loc_m12``,
    ``map_m12``): what ``sim:<preset>/<session>@<seed>`` names open."""
    from blockloc.sim.presets import get_preset
    from blockloc.sim.stream import open_sim_sequence

    if session in CHANGE_SESSIONS:
        return ChangedSimSequence(get_preset(preset, **overrides), session, int(seed))
    return open_sim_sequence(preset, session, seed, **overrides)


class ChangedSimSequence(SimSequence):
    """A changed session (``loc_m3``, ``loc_m12``, ``map_m12``): the route of ``loc`` / the
    mapping drive, on a later day, in the changed world; its own sensor noise, day and name.
    ``frame_with_labels`` gives scene categories; :meth:`point_labels` maps them to labels."""

    def __init__(self, preset: Preset, session: str, seed: int):
        if session not in CHANGE_SESSIONS:
            raise SimError(f"sim session {session!r}: expected one of {', '.join(CHANGE_SESSIONS)}")
        base = CHANGE_SESSIONS[session][0]
        if base == "map":
            base = preset.sessions[0]
        if base not in preset.sessions:
            raise SimError(f"sim session {session!r}: preset {preset.name} has no {base!r} drive to follow")
        super().__init__(preset, base, seed)
        self.base_session = base
        self.session = session
        self.month = CHANGE_SESSIONS[session][1]
        self.date, epoch = CHANGE_DAYS[session]
        self.epoch_us = int(epoch) * 1_000_000
        self._az0 = float(np.random.default_rng([self.seed, stable_hash(session), 9]).uniform(0, 2 * np.pi))
        self.info = dataclasses.replace(self.info, name=f"sim:{preset.name}/{session}@{self.seed}")
        self._changes = None
        self._label_of_cat = None

    @property
    def scene(self):
        if self._scene is None:
            from blockloc.sim.scene import SessionScene, make_actors

            day, unchanged, self._changes = changed_world(self.world, self.session)
            self._scene = SessionScene(day, unchanged, make_actors(self.world, self.session), self.session)
            lab = np.full(len(self._scene.categories) + 1, LABEL_STATIC, dtype=np.uint8)
            for k, c in enumerate(self._scene.categories):
                if c in CHANGED_CATEGORIES:
                    lab[k] = LABEL_CHANGED
                elif c in MOVING_CATEGORIES:
                    lab[k] = LABEL_MOVING
            self._label_of_cat = lab
        return self._scene

    def carries_slam_error(self) -> bool:
        """``map_m12`` (a drive of the mapping route) is mapped as the mapping day was: its
        mapping poses carry an offline-SLAM error of the same size, from its own random stream
        (the session name seeds it); ``loc_m3`` and ``loc_m12`` give ground truth."""
        return self.base_session == self.preset.sessions[0]

    def changes(self) -> list[Change]:
        """The changes against the mapping day that hold on this session's day."""
        self.scene  # noqa: B018 (built on first access)
        return list(self._changes)

    def point_labels(self, category: np.ndarray) -> np.ndarray:
        """(N,) uint8 label (static 0, changed 1, moving 2) of (N,) scene categories."""
        self.scene  # noqa: B018
        return self._label_of_cat[np.asarray(category, dtype=np.int64)]

    def frame_labels(self, index: int) -> tuple:
        """(frame, (N,) uint8 labels) of frame ``index``."""
        frame, cat = self.frame_with_labels(index)
        return frame, self.point_labels(cat)


# --- writing ----------------------------------------------------------------------------------

LABELS_DIR = "point_labels"  # <session>/point_labels/<utime>.npy, NCLT layout


def labelled_frames(seq: ChangedSimSequence, n: int, labels_dir: Path):
    """Yield seq's frames 0..n-1, writing each frame's labels to ``labels_dir/<utime>.npy`` as it
    goes: (N,) uint8 in the order the NCLT writer stores the frame's points (the points it drops
    left out, sorted by time as it does; ``blockloc.datasets.nclt.write_session``)."""
    from blockloc.datasets.nclt import encode_points

    labels_dir = Path(labels_dir)
    labels_dir.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        frame, labels = seq.frame_labels(i)
        utime = int(round(frame.stamp * 1e6))
        _, keep = encode_points(frame.points, frame.intensity, frame.ring)
        lab = labels[keep]
        if frame.time_offsets is not None:
            t_us = utime + np.rint(np.asarray(frame.time_offsets, np.float64)[keep] * 1e6).astype(np.int64)
            lab = lab[np.argsort(t_us, kind="stable")]
        np.save(labels_dir / f"{utime}.npy", lab.astype(np.uint8))
        yield frame


def finish_session(session_dir: Path, labels_dir: Path, seq: ChangedSimSequence) -> None:
    """Move the labels written by :func:`labelled_frames` into ``session_dir/point_labels`` and
    write ``session_dir/changes.json`` (both inside the dataset's temp directory)."""
    Path(labels_dir).rename(Path(session_dir) / LABELS_DIR)
    write_changes_json(Path(session_dir) / "changes.json", seq)


def write_changes_json(path: Path, seq: ChangedSimSequence) -> None:
    """The session's changes (``Change.to_json``) with its month and the label codes."""
    doc = {"session": seq.session, "follows": seq.base_session, "month": seq.month,
           "labels": dict(enumerate(LABEL_NAMES)), "changes": [c.to_json() for c in seq.changes()]}
    Path(path).write_text(json.dumps(doc, indent=1) + "\n")


def read_point_labels(session_dir: str | Path, utime: int) -> np.ndarray:
    """The (N,) uint8 labels of the scan ``velodyne_sync/<utime>.bin`` of a written session: one
    per point of the file, in its order (the NCLT loader's range filter comes after)."""
    return load_array(Path(session_dir) / LABELS_DIR / f"{int(utime)}.npy")
