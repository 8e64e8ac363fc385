"""The world's layout: the road grid and its footpaths, buildings (and their facade rows),
fences, passages under buildings, and vegetation (scattering volumes or solid crowns).

The builders take the mesh builders ``b`` (category -> ``MeshBuilder``), the world's generator
``rng`` and the terrain height ``H(x, y)``; ``blockloc.sim.world.build_world`` calls them in a
fixed order (the draws' order is the world: do not reorder them)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from blockloc.sim.meshes import ALBEDO, box_mesh, cylinder_mesh, ellipsoid_mesh


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
