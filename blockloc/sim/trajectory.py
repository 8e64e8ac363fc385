"""Routes on the road graph, a C2 robot trajectory along them, and the IMU it implies.

Internal frames: ``world`` (z up, x east) and ``flu`` (body: x forward, y left, z up). The NCLT
frames are ``map`` (z down) and ``body`` (x forward, y right, z down):
``T_map_body = D @ T_world_flu @ D`` with ``D = diag(1, -1, -1, 1)``.

The robot is a unicycle (Segway-like) driven by smooth speed / yaw-rate profiles (quintic
ramps): it accelerates, cruises, stops, turns in place and drives curves. The integrated planar
state is sampled at 100 Hz and interpolated by cubic splines (C2), so position, velocity and
acceleration are continuous; z, roll and pitch follow the (C2) terrain under it.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np

from blockloc.geometry import so3_log
from blockloc.sim.presets import PlatformModel, Preset
from blockloc.sim.world import Roads, World, smootherstep, smootherstep_d

log = logging.getLogger(__name__)

D4 = np.diag([1.0, -1.0, -1.0, 1.0])  # world(z up) <-> map(z down), flu <-> frd
GRAVITY_WORLD = np.array([0.0, 0.0, -9.81])
LANE_OFFSET_M = 0.8  # the robot keeps right of the road centre line
_DT = 0.01  # integration / spline knot step, s


# --- routes -----------------------------------------------------------------------------------

Node = tuple[int, int]


def _edge(a: Node, b: Node) -> tuple[Node, Node]:
    return (a, b) if a <= b else (b, a)


def cover_route(roads: Roads, rng: np.random.Generator, length_m: float, start: Node,
                allowed=None, prefix: list[Node] | None = None) -> list[Node]:
    """A node walk that first covers unvisited road edges (greedy, BFS to the nearest unvisited
    one), then wanders without immediate U-turns, until ``length_m`` is driven. ``allowed``:
    node -> bool, the part of the graph to cover (default all); ``prefix``: nodes driven first."""
    ok = allowed or (lambda n: True)
    route = list(prefix) if prefix else [start]
    visited: set = {_edge(a, b) for a, b in zip(route[:-1], route[1:])}
    total = sum(roads.edge_length(a, b) for a, b in zip(route[:-1], route[1:]))
    all_edges = {_edge(a, b) for a in _all_nodes(roads) if ok(a) for b in roads.neighbours(a) if ok(b)}
    while total < length_m:
        cur = route[-1]
        nbrs = [n for n in roads.neighbours(cur) if ok(n)] or roads.neighbours(cur)
        fresh = [n for n in nbrs if _edge(cur, n) not in visited]
        if fresh:
            nxt = fresh[rng.integers(len(fresh))]
        elif len(visited & all_edges) < len(all_edges):
            path = _bfs_to_unvisited(roads, cur, visited, ok)
            nxt = path[1]
        else:
            back = route[-2] if len(route) > 1 else None
            opts = [n for n in nbrs if n != back] or nbrs
            nxt = opts[rng.integers(len(opts))]
        visited.add(_edge(cur, nxt))
        total += roads.edge_length(cur, nxt)
        route.append(nxt)
    return route


def _all_nodes(roads: Roads) -> list[Node]:
    return [(i, j) for i in range(len(roads.xs)) for j in range(len(roads.ys))]


def _bfs_to_unvisited(roads: Roads, start: Node, visited: set, ok=lambda n: True) -> list[Node]:
    from collections import deque

    prev = {start: None}
    q = deque([start])
    while q:
        cur = q.popleft()
        for n in roads.neighbours(cur):
            if not ok(n):
                continue
            if _edge(cur, n) not in visited:
                path = [n, cur]
                while prev[path[-1]] is not None:
                    path.append(prev[path[-1]])
                return path[::-1]
            if n not in prev:
                prev[n] = cur
                q.append(n)
    raise RuntimeError("no unvisited edge")


def relocalization_route(roads: Roads, rng: np.random.Generator, length_m: float, start: Node,
                         map_route: list[Node]) -> list[Node]:
    """A walk on the edges the mapping route drove (so it stays inside the map), preferring
    edges driven least and in the direction opposite to the mapping drive."""
    mapped_dir = {(a, b) for a, b in zip(map_route[:-1], map_route[1:])}
    mapped = {_edge(a, b) for a, b in mapped_dir}
    uses: dict = {}
    route = [start]
    total = 0.0
    while total < length_m:
        cur = route[-1]
        back = route[-2] if len(route) > 1 else None
        opts = [n for n in roads.neighbours(cur) if _edge(cur, n) in mapped]
        if not opts:
            raise RuntimeError(f"node {cur} is not on the mapping route")
        if len(opts) > 1 and back in opts:
            opts.remove(back)
        # hard places (footpaths over open quads, passages, the corridor) are sought out
        score = [uses.get(_edge(cur, n), 0) * 2.0 + (1.0 if (cur, n) in mapped_dir else 0.0)
                 - (1.5 if _edge(cur, n) in roads.special and not uses.get(_edge(cur, n)) else 0.0)
                 + rng.uniform(0, 0.9) for n in opts]
        nxt = opts[int(np.argmin(score))]
        uses[_edge(cur, nxt)] = uses.get(_edge(cur, nxt), 0) + 1
        total += roads.edge_length(cur, nxt)
        route.append(nxt)
    return route


def crossing_route(roads: Roads, rng: np.random.Generator, length_m: float, mapped: set,
                   n_via: int = 6) -> list[Node]:
    """A drive across the mapped part of the graph (edges ``mapped``): from its western end to
    its eastern end through ``n_via`` random mapped nodes in between (shortest paths on the
    mapped edges), as far as ``length_m``."""
    from collections import deque

    nodes = sorted({n for e in mapped for n in e})
    adj: dict = {}
    for a, b in mapped:
        adj.setdefault(a, []).append(b)
        adj.setdefault(b, []).append(a)
    xs = np.array([roads.node_xy(n)[0] for n in nodes])
    order = np.argsort(xs)
    start = nodes[order[len(order) // 20]]
    goal = nodes[order[-1 - len(order) // 20]]
    via = [nodes[i] for i in np.sort(rng.choice(order[len(order) // 10:-len(order) // 10], n_via,
                                                 replace=False), kind="stable")]
    via = sorted(via, key=lambda n: roads.node_xy(n)[0])
    route = [start]
    for target in via + [goal]:
        prev = {route[-1]: None}
        q = deque([route[-1]])
        while q and target not in prev:
            cur = q.popleft()
            for n in adj.get(cur, []):
                if n not in prev:
                    prev[n] = cur
                    q.append(n)
        if target not in prev:
            continue
        leg = [target]
        while prev[leg[-1]] is not None:
            leg.append(prev[leg[-1]])
        route += leg[::-1][1:]
    total = 0.0
    for k in range(1, len(route)):
        total += roads.edge_length(route[k - 1], route[k])
        if total >= length_m:
            return route[:k + 1]
    return route


def lane_waypoints(roads: Roads, route: list[Node], length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(K, 2) corner points of the route, offset LANE_OFFSET_M to the right of the centre
    line, truncated to ``length_m``, and (K,) bool: the point lies inside a curving footpath
    (to be driven through in a curve, never stopped at). U-turns get two points."""
    P, smooth = [roads.node_xy(route[0])], [False]
    for a, b in zip(route[:-1], route[1:]):
        E = roads.edge_points(a, b)
        P.extend(E[1:])
        smooth.extend([True] * (len(E) - 2) + [False])
    P = np.array(P)
    pts, sm = [], []
    for k in range(len(P)):
        d_in = _unit(P[k] - P[k - 1]) if k > 0 else _unit(P[1] - P[0])
        d_out = _unit(P[k + 1] - P[k]) if k + 1 < len(P) else d_in
        r_in = np.array([d_in[1], -d_in[0]]) * LANE_OFFSET_M
        r_out = np.array([d_out[1], -d_out[0]]) * LANE_OFFSET_M
        if np.dot(d_in, d_out) < -0.5:  # U-turn: end of the inbound lane, start of the outbound
            pts += [P[k] + r_in, P[k] + r_out]
            sm += [False, False]
            continue
        if abs(d_in[0] * d_out[1] - d_in[1] * d_out[0]) < 1e-6:
            pts.append(P[k] + r_in)
        else:  # intersection of the two offset lines
            A = np.c_[d_in, -d_out]
            s = np.linalg.solve(A, (P[k] + r_out) - (P[k] + r_in))
            pts.append(P[k] + r_in + s[0] * d_in)
        sm.append(smooth[k])
    pts, sm = np.array(pts), np.array(sm, dtype=bool)
    # truncate to length
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    cum = np.concatenate([[0], np.cumsum(seg)])
    if cum[-1] > length_m:
        k = int(np.searchsorted(cum, length_m))
        end = pts[k - 1] + (pts[k] - pts[k - 1]) * (length_m - cum[k - 1]) / max(seg[k - 1], 1e-9)
        pts = np.vstack([pts[:k], end])
        sm = np.r_[sm[:k], False]
    return pts, sm


def _unit(v):
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.array([1.0, 0.0])


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


# --- motion plan ------------------------------------------------------------------------------

class _Integrator:
    """Unicycle integrated at _DT; records (t, x, y, psi)."""

    def __init__(self, x, y, psi):
        self.x, self.y, self.psi, self.v = float(x), float(y), float(psi), 0.0
        self.rows = [(0.0, self.x, self.y, self.psi)]

    def run(self, v_fn, w_fn, T):
        """Apply v(u), w(u) for u in (0, 1] over T seconds (u = elapsed / T)."""
        n = max(1, int(round(T / _DT)))
        u = np.arange(1, n + 1) / n
        v = v_fn(u)
        w = w_fn(u)
        v_prev = np.concatenate([[self.v], v[:-1]])
        w_prev = np.concatenate([[w_fn(np.array([0.0]))[0]], w[:-1]])
        psi = self.psi + np.cumsum(0.5 * (w + w_prev) * _DT)
        psi_mid = np.concatenate([[self.psi], psi[:-1]]) * 0.5 + psi * 0.5
        vm = 0.5 * (v + v_prev)
        x = self.x + np.cumsum(vm * np.cos(psi_mid) * _DT)
        y = self.y + np.cumsum(vm * np.sin(psi_mid) * _DT)
        t0 = self.rows[-1][0]
        t = t0 + np.arange(1, n + 1) * _DT
        self.rows.extend(zip(t, x, y, psi))
        self.x, self.y, self.psi, self.v = float(x[-1]), float(y[-1]), float(psi[-1]), float(v[-1])

    def wait(self, T):
        self.run(lambda u: np.zeros_like(u), lambda u: np.zeros_like(u), T)

    def turn_in_place(self, dpsi, rate=0.6):
        T = max(1.5, 1.875 * abs(dpsi) / rate)  # peak yaw rate ~ rate rad/s
        self.run(lambda u: np.zeros_like(u), lambda u: dpsi * smootherstep_d(u) / T, T)

    def ramp_speed(self, v1, accel=0.5, dpsi=0.0):
        v0 = self.v
        T = max(0.5, 1.875 * abs(v1 - v0) / accel)
        self.run(lambda u: v0 + (v1 - v0) * smootherstep(u), lambda u: dpsi * smootherstep_d(u) / T, T)
        return 0.5 * (v0 + v1) * T

    def cruise(self, dist, dpsi=0.0):
        if dist <= 1e-3:
            return
        T = dist / max(self.v, 1e-3)
        v = self.v
        self.run(lambda u: np.full_like(u, v), lambda u: dpsi * smootherstep_d(u) / T, T)

    def curve(self, dpsi, v, rate=0.3):
        T = max(2.0, abs(dpsi) / rate)
        self.run(lambda u: np.full_like(u, v), lambda u: dpsi * smootherstep_d(u) / T, T)


def _curve_lead(dpsi: float, v: float, rate=0.3) -> float:
    """Distance before a corner at which a curve of heading change dpsi (speed v) must start
    so that the path is tangent to both legs."""
    it = _Integrator(0.0, 0.0, 0.0)
    it.v = v
    it.curve(dpsi, v, rate)
    ex, ey = it.x, it.y
    return float(ex - ey / np.tan(dpsi))


def plan_motion(waypoints: np.ndarray, preset: Preset, rng: np.random.Generator,
                smooth: np.ndarray | None = None) -> np.ndarray:
    """Drive through ``waypoints`` (K, 2); returns (N, 4) rows t (s from 0), x, y, psi (rad,
    unwrapped) at 100 Hz. Sharp corners (> 100 deg) and a share of the others are taken by
    stopping and turning in place; the rest by curves; random stops on legs. ``smooth`` (K,)
    bool: points inside a curving path, always driven through in a curve."""
    v_c = preset.cruise_speed_mps
    decel_dist = 1.875 * v_c * v_c  # distance covered by ramp_speed(0.0) from v_c (accel 0.5)
    P = np.asarray(waypoints, dtype=float)
    psi0 = np.arctan2(*(P[1] - P[0])[::-1])
    it = _Integrator(P[0, 0], P[0, 1], psi0)
    it.wait(2.0)  # standing start: lets estimators initialise gravity and biases
    n = len(P)
    # corner modes decided up front: True = stop and turn in place
    in_place = [True] * n
    for k in range(1, n - 1):
        d1, d2 = P[k] - P[k - 1], P[k + 1] - P[k]
        ang = abs(_wrap(np.arctan2(d2[1], d2[0]) - np.arctan2(d1[1], d1[0])))
        in_place[k] = ang > np.deg2rad(100) or ang < np.deg2rad(5) or rng.random() < preset.turn_in_place_prob
        if np.linalg.norm(d1) < 8 or np.linalg.norm(d2) < 8:
            in_place[k] = True
        if smooth is not None and smooth[k] and ang < np.deg2rad(60):
            in_place[k] = False
    for k in range(1, n):
        target = P[k]
        to = target - np.array([it.x, it.y])
        dist = float(np.linalg.norm(to))
        heading = float(np.arctan2(to[1], to[0]))
        dpsi = _wrap(heading - it.psi)
        if it.v < 1e-6 and abs(dpsi) > np.deg2rad(2):
            it.turn_in_place(dpsi)
            dpsi = 0.0
        # where this leg ends: a stop at the corner, or the start of a curve
        if k == n - 1 or in_place[k]:
            end_lead, stop = 0.0, True
            next_dpsi = 0.0
        else:
            d2 = P[k + 1] - P[k]
            next_dpsi = _wrap(np.arctan2(d2[1], d2[0]) - heading)
            end_lead = _curve_lead(next_dpsi, v_c) if abs(next_dpsi) > 0.01 else 0.0
            stop = False
        avail = dist - end_lead
        stops = []
        if stop and rng.random() < preset.stop_prob and avail > 4 * decel_dist:
            stops.append(rng.uniform(0.3, 0.7) * avail)
        legs = np.diff(np.concatenate([[0.0], stops, [avail]]))
        for li, L in enumerate(legs):
            last = li == len(legs) - 1
            ends_stopped = stop or not last
            v_leg = v_c
            if it.v < 1e-6 and ends_stopped:  # short leg from rest to rest: lower top speed
                v_leg = min(v_c, float(np.sqrt(max(L, 0.01) / 3.75)))
            ramp_up = 0.0
            if it.v < v_leg - 1e-6:
                ramp_up = it.ramp_speed(v_leg, dpsi=dpsi if li == 0 else 0.0)
            elif li == 0 and abs(dpsi) > 0:
                it.cruise(min(4.0, 0.3 * L), dpsi=dpsi)
                ramp_up = min(4.0, 0.3 * L)
            remaining = L - ramp_up
            if not ends_stopped:
                it.cruise(remaining)
            else:
                it.cruise(remaining - 1.875 * v_leg * v_leg)
                it.ramp_speed(0.0)
                if not last:
                    it.wait(rng.uniform(2.0, 5.0))
        if not stop and abs(next_dpsi) > 0.01:
            it.curve(next_dpsi, v_c)
    it.ramp_speed(0.0)
    it.wait(2.0)
    return np.array(it.rows)


# --- the trajectory ---------------------------------------------------------------------------

@dataclass
class SimTrajectory:
    """Robot body trajectory over [0, duration] s (session-relative time).

    ``T_world_flu(t)``: (N, 4, 4); ``T_map_body(t)``: NCLT frames (z down). The body origin
    rides ``body_height_m`` above the terrain, its z axis along the terrain normal.
    """

    samples: np.ndarray  # (N, 4) t, x, y, psi at 100 Hz
    world: World
    body_height_m: float
    platform: PlatformModel | None = None  # the Segway's own attitude (None: follows the terrain)
    seed: int = 0

    def __post_init__(self, tilt_samples: tuple | None = None) -> None:
        t = self.samples[:, 0]
        self.duration = float(t[-1])
        self._tilt_samples = None
        pm = self.platform
        if pm is not None and (pm.balance_pitch or pm.wobble_deg > 0 or pm.vibration_deg > 0
                               or pm.vibration_z_m > 0):
            self._tilt_samples = tilt_samples or self._balance(t, pm)

    # The splines are built on first use, not with the trajectory: a city drive's five hold ~80 MB
    # (coefficients (4, N-1) over 400k samples each), and a process may open a drive without
    # evaluating it (planning from the disk-cached mapping poses, or reading a session's route).
    @functools.cached_property
    def _planar_splines(self) -> tuple:
        from scipy.interpolate import CubicSpline

        t = self.samples[:, 0]
        return tuple(CubicSpline(t, self.samples[:, k]) for k in (1, 2, 3))

    @property
    def _sx(self):
        return self._planar_splines[0]

    @property
    def _sy(self):
        return self._planar_splines[1]

    @property
    def _sp(self):
        return self._planar_splines[2]

    @functools.cached_property
    def _tilt(self) -> tuple | None:
        """(pitch spline, roll spline, vibration phases (3,)) of the platform, or None."""
        from scipy.interpolate import CubicSpline

        if self._tilt_samples is None:
            return None
        pitch, roll, phases = self._tilt_samples
        t = self.samples[:, 0]
        return CubicSpline(t, pitch), CubicSpline(t, roll), phases

    def state(self) -> dict:
        """This trajectory's fields without the world, and its platform's pitch / roll samples
        (the balance loop, a city drive's costliest part): :meth:`from_state` with the same
        world gives the same trajectory (its splines built again from the same samples: the
        same coefficients), for ~16 MB a city drive against ~90 MB with the splines pickled."""
        return {"samples": self.samples, "body_height_m": self.body_height_m,
                "platform": self.platform, "seed": self.seed, "tilt_samples": self._tilt_samples}

    @classmethod
    def from_state(cls, state: dict, world: World) -> "SimTrajectory":
        """The trajectory of :meth:`state` over ``world``, without running the balance loop."""
        traj = cls.__new__(cls)  # the dataclass __init__ would run the balance loop
        traj.samples, traj.world, traj.body_height_m = state["samples"], world, state["body_height_m"]
        traj.platform, traj.seed = state["platform"], state["seed"]
        traj.__post_init__(state["tilt_samples"])
        return traj

    def _balance(self, t: np.ndarray, pm: PlatformModel) -> tuple:
        """Pitch and roll samples (N,) of the balancing platform at ``t`` (rad) and the
        vibration phases (3,)."""
        from scipy.interpolate import CubicSpline

        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0xBA1A]))
        psi = self.samples[:, 3]
        pitch = np.zeros(len(t))
        if pm.balance_pitch:
            # lean atan(a / g) into each acceleration, through an underdamped balance loop
            a_long = self._sx(t, 2) * np.cos(psi) + self._sy(t, 2) * np.sin(psi)
            target = np.arctan(a_long / 9.81)
            w = 2 * np.pi * pm.pitch_natural_hz
            th, dth = 0.0, 0.0
            for k in range(len(t)):
                dt = t[k] - t[k - 1] if k else 0.0
                dth += (w * w * (target[k] - th) - 2 * pm.pitch_damping * w * dth) * dt
                th += dth * dt
                pitch[k] = th
        roll = np.zeros(len(t))
        if pm.wobble_deg > 0:
            knots = np.arange(t[0] - 1.0, t[-1] + 2.0, 0.8)
            wob = CubicSpline(knots, rng.normal(0, 1, (len(knots), 2)))(t)
            pitch += np.deg2rad(pm.wobble_deg) * wob[:, 0]
            roll += 0.5 * np.deg2rad(pm.wobble_deg) * wob[:, 1]
        phases = rng.uniform(0, 2 * np.pi, 3)
        return pitch, roll, phases

    def _vibration(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Speed-proportional shake: (pitch rad, z m) at times t (analytic, not sampled)."""
        pm, (_, _, ph) = self.platform, self._tilt
        v = np.hypot(self._sx(t, 1), self._sy(t, 1)) / 1.3
        s1 = np.sin(2 * np.pi * 11.0 * t + ph[0]) + 0.6 * np.sin(2 * np.pi * 17.3 * t + ph[1])
        return (np.deg2rad(pm.vibration_deg) * v * s1,
                pm.vibration_z_m * v * np.sin(2 * np.pi * 13.1 * t + ph[2]))

    def planar(self, t: np.ndarray, order: int = 0):
        t = np.asarray(t, dtype=np.float64)
        return self._sx(t, order), self._sy(t, order), self._sp(t, order)

    def position(self, t: np.ndarray) -> np.ndarray:
        x, y, _ = self.planar(t)
        z = self.world.terrain.height(x, y) + self.body_height_m
        if self._tilt is not None and self.platform.vibration_z_m > 0:
            z = z + self._vibration(np.asarray(t, dtype=np.float64))[1]
        return np.stack([x, y, z], axis=-1)

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """(N, 3, 3) R_world_flu."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        _, _, psi = xyp = self.planar(t)
        _, hx, hy = self.world.terrain.height_grad(*xyp[:2])
        return self._rotation(t, psi, hx, hy, None if self._tilt is None else self._vibration(t))

    def _rotation(self, t: np.ndarray, psi, hx, hy, vibration) -> np.ndarray:
        """:meth:`rotation` at times ``t`` (N,) from the heading ``psi``, the terrain's gradient
        ``hx``, ``hy`` there and :meth:`_vibration` at ``t`` (None without a platform tilt)."""
        n = np.stack([-hx, -hy, np.ones_like(hx)], axis=-1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        f = np.stack([np.cos(psi), np.sin(psi), np.zeros_like(psi)], axis=-1)
        xa = f - np.sum(f * n, axis=-1, keepdims=True) * n
        xa /= np.linalg.norm(xa, axis=-1, keepdims=True)
        ya = np.cross(n, xa)
        R = np.stack([xa, ya, n], axis=-1)
        if self._tilt is None:
            return R
        sp, sr, _ = self._tilt
        pitch = sp(t) + vibration[0]  # positive: nose down (leaning forward)
        roll = sr(t)
        cp, spn, cr, srn = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
        Ry = np.zeros((len(t), 3, 3))
        Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 1, 1], Ry[:, 2, 0], Ry[:, 2, 2] = cp, spn, 1.0, -spn, cp
        Rx = np.zeros((len(t), 3, 3))
        Rx[:, 0, 0], Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = 1.0, cr, -srn, srn, cr
        return R @ Ry @ Rx

    def T_world_flu(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) body (x forward, y left, z up) in the world at times t (N,) s: the pose of
        :meth:`rotation` and :meth:`position`, their shared parts (the planar splines, the
        terrain's height and gradient, the vibration) evaluated once (a scan's 2000 column poses
        took ~4 ms with each evaluated twice)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        x, y, psi = self.planar(t)
        h, hx, hy = self.world.terrain.height_grad(x, y)
        vibration = None if self._tilt is None else self._vibration(t)
        z = h + self.body_height_m  # as position(t)
        if vibration is not None and self.platform.vibration_z_m > 0:
            z = z + vibration[1]
        T = np.zeros((len(t), 4, 4))
        T[:, :3, :3] = self._rotation(t, psi, hx, hy, vibration)
        T[:, :3, 3] = np.stack([x, y, z], axis=-1)
        T[:, 3, 3] = 1.0
        return T

    def T_map_body(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) NCLT ground truth: body (x fwd, y right, z down) in map (z down)."""
        return D4 @ self.T_world_flu(t) @ D4

    def imu_ideal(self, t: np.ndarray, h: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free specific force (N, 3) m/s^2 and angular rate (N, 3) rad/s in the NCLT body
        frame (FRD) at times t: f = R^T (a - g), omega from the rotation's derivative."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        ax = self._sx(t, 2)
        ay = self._sy(t, 2)
        z = lambda tt: self.position(tt)[:, 2]  # noqa: E731
        az = (z(t + h) - 2.0 * z(t) + z(t - h)) / (h * h)
        a_w = np.stack([ax, ay, az], axis=-1)
        R = self.rotation(t)
        f_flu = np.einsum("nji,nj->ni", R, a_w - GRAVITY_WORLD)
        Rm, Rp = self.rotation(t - h), self.rotation(t + h)
        w_flu = so3_log(np.einsum("nji,njk->nik", Rm, Rp)) / (2.0 * h)
        flip = np.array([1.0, -1.0, -1.0])
        return f_flu * flip, w_flu * flip

    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.samples[:, 1:3], axis=0), axis=1).sum())
