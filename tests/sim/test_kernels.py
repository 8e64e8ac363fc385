"""The simulator's numba kernels give the bits of the numpy code they replaced.

The reference functions below are the numpy implementations as they were before the kernels
(blockloc 24340d4), kept here only as the yardstick: a scan of a given seed must not change by
one bit when its per-ray models move into compiled code (other engineers measure accuracy on
the simulator's output, and the realism bands were measured on it).
"""

from __future__ import annotations


import numpy as np
import pytest

from blockloc.sim.lidar import SensorCalibration, _beams, simulate_scan
from blockloc.sim.presets import LidarModel
from blockloc.sim.scene import value_noise


# --- the numpy references (24340d4) -----------------------------------------------------------

def _ref_value_noise(x, y, cell_m, seed):
    gx, gy = np.asarray(x) / cell_m, np.asarray(y) / cell_m
    ix, iy = np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)
    fx, fy = gx - ix, gy - iy

    def h(i, j):
        v = (i * 73856093) ^ (j * 19349663) ^ (seed * 83492791)
        v = (v ^ (v >> 13)) * 1274126177
        return ((v ^ (v >> 16)) & 0xFFFF) / 32767.5 - 1.0

    sx, sy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    top = h(ix, iy) * (1 - sx) + h(ix + 1, iy) * sx
    bot = h(ix, iy + 1) * (1 - sx) + h(ix + 1, iy + 1) * sx
    return top * (1 - sy) + bot * sy


def _ref_ground_material(world, x, y):
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    res, tile = 0.25, 128.0
    n = int(tile / res)
    out = np.empty(x.shape, dtype=np.uint8)
    ti = np.floor(x / tile).astype(np.int64)
    tj = np.floor(y / tile).astype(np.int64)
    uniq, local = np.unique(ti * 1_000_003 + tj, return_inverse=True)
    ids = [(int(k // 1_000_003), int(k % 1_000_003)) for k in uniq]
    ids = [(a + 1, b - 1_000_003) if b > 500_000 else (a, b) for a, b in ids]
    local = local.reshape(x.shape)
    tiles = [world._material_tile(a, b, n, res, tile) for a, b in ids]
    R = np.stack(tiles)
    i = np.clip(((y - tj * tile) / res).astype(np.int64), 0, n - 1)
    j = np.clip(((x - ti * tile) / res).astype(np.int64), 0, n - 1)
    out[...] = (R[local, i, j >> 2] >> ((j & 3) << 1).astype(np.uint8)) & 3
    return out


def _dot3(a, b):
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _ref_mixed_pixels(r, model, rng):
    nxt = np.roll(r, -1, axis=0)
    with np.errstate(invalid="ignore"):
        gap = nxt - r
    edge = np.isfinite(gap) & (np.abs(gap) > model.mixed_pixel_gap_m)
    mix = edge & (rng.random(r.shape) < model.mixed_pixel_prob)
    frac = rng.uniform(0.1, 0.9, r.shape)
    return np.where(mix, r + frac * np.where(np.isfinite(gap), gap, 0.0), r)


def _ref_simulate_scan(scene, T_world_lidar_cols, col_offsets, model, rng, t_mid, az0=0.0, calib=None):
    A = len(col_offsets)
    d_nom, d_true, r_self = _beams(A, az0, calib)
    R = T_world_lidar_cols[:, :3, :3]
    dirs = np.matmul(d_true, R.transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat(T_world_lidar_cols[:, :3, 3], 32, axis=0)
    h = scene.cast_full(origins, dirs, t_mid, model.max_range_m, rng)
    rng_true, normals, reflect, cat = h["range"], h["normal"], h["reflect"], h["cat"]
    n = len(rng_true)
    if model.self_hits:
        mine = r_self < rng_true
        rng_true = np.where(mine, r_self, rng_true)
        cat = np.where(mine, scene.categories.index("self"), cat)
        reflect = np.where(mine, 0.15, reflect)
    cosi = np.abs(_dot3(normals, dirs))
    if model.mixed_pixel_prob > 0:
        rng_true = _ref_mixed_pixels(rng_true.reshape(A, 32), model, rng).reshape(-1)
    noise = rng.normal(0.0, model.range_noise_m, n)
    if model.range_tail_prob > 0:
        tail = rng.random(n) < model.range_tail_prob
        noise = np.where(tail, rng.laplace(0.0, model.range_tail_scale_m, n), noise)
    laser = np.tile(np.arange(32), A)
    if calib is not None:
        noise = noise + calib.range_offset_m[laser]
    u_drop = rng.random(n)
    u_graze = rng.random(n)
    u_weak = rng.random(n)
    speckle = rng.lognormal(0.0, model.intensity_speckle, n) if model.intensity_speckle > 0 else np.ones(n)
    r = rng_true + noise
    ok = np.isfinite(rng_true) & (rng_true <= model.max_range_m) & (r >= model.min_range_m)
    ok &= u_drop >= model.dropout_prob
    ok &= ~((cosi < model.grazing_dropout_cos) & (u_graze < 0.5))
    gain = calib.gain[laser] if calib is not None else np.ones(n)
    power = reflect * (0.2 + 0.8 * cosi)
    rr = np.maximum(np.where(np.isfinite(rng_true), rng_true, 1e3), 1.0)
    inten = (model.intensity_scale * gain * power * speckle
             * np.minimum(1.0, (model.intensity_knee_m / rr) ** model.intensity_exponent))
    if model.weak_return_dropout:
        snr = power * gain * (10.0 / rr) ** 2
        ok &= u_weak >= np.exp(-snr / 0.004)
    retro = h["retro"]
    inten = np.where(retro, rng.uniform(180.0, 255.0, n), inten)
    idx = np.flatnonzero(ok)
    pts = d_nom.reshape(-1, 3)[idx] * r[idx, None]
    ring = laser[idx].astype(np.uint16)
    toff = np.repeat(col_offsets.astype(np.float32), 32)[idx]
    i_out = np.floor(np.clip(inten[idx], 0.0, 255.0)).astype(np.float32)
    return pts, i_out, ring, toff, cat[idx]


# --- a scene that returns a drawn cast --------------------------------------------------------

class _DrawnScene:
    """Stands in for a SessionScene: ``cast_full`` returns a cast drawn from ``seed`` (ranges
    0.3-120 m with misses, edges and duplicates, unit normals, reflectance, a few retroreflectors)
    and draws from the scan's generator as the real one does (its stream position matters)."""

    categories = ["terrain", "building", "sign", "self", "glass"]

    def __init__(self, seed: int):
        self.seed = seed

    def cast_full(self, origins, dirs, t, max_range, rng):
        g = np.random.default_rng(self.seed)
        n = len(origins)
        r = g.choice([0.3, 0.95, 5.0, 30.0, 99.9, 100.0, 120.0], n) * g.uniform(0.5, 1.5, n)
        r[g.random(n) < 0.1] = np.inf
        r[g.random(n) < 0.05] = 100.0  # exactly at the maximum range
        nrm = g.normal(size=(n, 3))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        rng.random(7)  # the scene's own draws move the stream
        return {"range": r, "normal": nrm, "reflect": g.uniform(0.02, 0.9, n),
                "cat": g.integers(0, 3, n).astype(np.int64), "glass": np.zeros(n, bool),
                "retro": g.random(n) < 0.02}


def _poses(A: int, seed: int) -> np.ndarray:
    g = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (A, 1, 1))
    yaw = 0.3 + 0.01 * np.arange(A) + g.normal(0, 0.01)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    T[:, :3, 3] = g.normal(0, 10, 3) + np.arange(A)[:, None] * [0.001, 0.0005, 0.0]
    return T


MODELS = {
    "default": LidarModel(azimuth_steps=360),
    "no errors": LidarModel(azimuth_steps=360, range_noise_m=0.0, range_tail_prob=0.0, dropout_prob=0.0,
                            mixed_pixel_prob=0.0, weak_return_dropout=False, self_hits=False,
                            intensity_speckle=0.0),
    "exponent 1.7": LidarModel(azimuth_steps=200, intensity_exponent=1.7, intensity_knee_m=7.0),
}


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("calibrated", [False, True])
def test_simulate_scan_gives_the_numpy_models_bits(name, calibrated):
    model = MODELS[name]
    A = model.azimuth_steps
    calib = SensorCalibration.draw(model, 4) if calibrated else None
    T = _poses(A, 2)
    off = np.arange(A) * (0.1 / A)
    got = simulate_scan(_DrawnScene(9), T, off, model, np.random.default_rng(5), 1.0, 0.2, calib)
    want = _ref_simulate_scan(_DrawnScene(9), T, off, model, np.random.default_rng(5), 1.0, 0.2, calib)
    assert 0 < len(want[0]) < A * 32  # some returns dropped, some kept
    for a, b, what in zip((got.points, got.intensity, got.ring, got.time_offsets, got.category), want,
                          ("points", "intensity", "ring", "time_offsets", "category")):
        assert a.dtype == b.dtype and a.shape == b.shape, what
        assert a.tobytes() == b.tobytes(), what


def test_value_noise_gives_the_numpy_bits():
    g = np.random.default_rng(3)
    x = np.concatenate([g.uniform(-3000, 3000, 20000), np.arange(-5.0, 5.0, 0.35), [0.0, -0.0]])
    y = np.concatenate([g.uniform(-3000, 3000, 20000), np.arange(5.0, -5.0, -0.35), [-0.0, 0.0]])
    for cell, seed in ((0.7, 1), (1.5, 2), (0.8, 123456)):
        assert value_noise(x, y, cell, seed).tobytes() == _ref_value_noise(x, y, cell, seed).tobytes()
    # strided inputs (columns of a point array) and a 2-D grid
    P = np.stack([x, y, x], axis=1)
    assert value_noise(P[:, 0], P[:, 1], 0.7, 5).tobytes() == _ref_value_noise(P[:, 0], P[:, 1], 0.7, 5).tobytes()
    X, Y = np.meshgrid(np.linspace(-9, 9, 40), np.linspace(-3, 3, 30))
    assert np.array_equal(value_noise(X, Y, 1.5, 2), _ref_value_noise(X, Y, 1.5, 2))


def test_ground_material_gives_the_numpy_lookup():
    from blockloc.sim.presets import get_preset
    from blockloc.sim.world import build_world

    world = build_world(get_preset("tiny"), 3)
    g = np.random.default_rng(1)
    x0, x1, y0, y1 = world.extent
    # a scan's ground hits (a few tiles), tile borders and negative coordinates
    x = np.concatenate([g.uniform(x0, x1, 5000), [-128.0, -0.1, 0.0, 127.99, 128.0]])
    y = np.concatenate([g.uniform(y0, y1, 5000), [0.0, -128.0, 127.99, -0.01, 5.0]])
    got = world.ground_material(x, y)
    assert got.dtype == np.uint8 and np.array_equal(got, _ref_ground_material(world, x, y))
    assert set(np.unique(got)) >= {0, 1, 2}
    # scattered far apart (more than 2**16 tiles in their box): numbered by a sort
    xs = np.array([-40_000.0, 40_000.0, 3.0])
    ys = np.array([-40_000.0, 40_000.0, 4.0])
    assert np.array_equal(world.ground_material(xs, ys), _ref_ground_material(world, xs, ys))
    # 2-D input keeps its shape
    X, Y = np.meshgrid(np.linspace(x0, x1, 7), np.linspace(y0, y1, 5))
    assert np.array_equal(world.ground_material(X, Y), _ref_ground_material(world, X.ravel(), Y.ravel()).reshape(5, 7))


# --- the scene's ground relief and vegetation (24340d4) ----------------------------------------

def _ref_random_unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.sqrt(_dot3(v, v))[:, None]


def _ref_ellipsoid_interval(o, d, c, r):
    oo, dd = (o - c) / r, d / r
    a = _dot3(dd, dd)
    b = _dot3(oo, dd)
    cc = _dot3(oo, oo) - 1.0
    disc = b * b - a * cc
    sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
    return (-b - sq) / a, (-b + sq) / a


def _ref_ground_relief(self, idx, origins, dirs, rng_, normals, reflect, rng, p, mat):
    from blockloc.sim.scene import KERB_M

    o, d = origins[idx], dirs[idx]
    world = self.world
    r = rng_[idx]
    down = np.maximum(-d[:, 2], 0.02)
    seed = self._seed
    micro = _ref_value_noise(p[:, 0], p[:, 1], 0.7, seed) * np.where(mat == 2, 0.02, 0.004)
    r_new = r - micro / down
    side = mat == 1
    if side.any():
        o_s, d_s, r_0 = o[side], d[side], r[side]
        r_side = r_0 - KERB_M / down[side]
        p1 = o_s + d_s * r_side[:, None]
        face = _ref_ground_material(world, p1[:, 0], p1[:, 1]) == 0
        r_s = r_side.copy()
        if face.any():
            o_f, d_f = o_s[face], d_s[face]
            lo, hi = r_side[face], r_0[face]
            for _ in range(5):
                mid = 0.5 * (lo + hi)
                pm = o_f + d_f * mid[:, None]
                on_road = _ref_ground_material(world, pm[:, 0], pm[:, 1]) == 0
                lo = np.where(on_road, mid, lo)
                hi = np.where(on_road, hi, mid)
            r_s[face] = hi
            n_face = np.c_[-d_f[:, :2], np.zeros(len(d_f))]
            n_face /= np.maximum(np.linalg.norm(n_face, axis=1, keepdims=True), 1e-9)
            nn = normals[idx[side]]
            nn[face] = n_face
            normals[idx[side]] = nn
        r_new[side] = r_s + (r_new[side] - r_0)
    grass = mat == 2
    if grass.any():
        g_h = 0.08 + 0.04 * _ref_value_noise(p[grass, 0], p[grass, 1], 1.5, seed + 1)
        depth = g_h / down[grass]
        stop = np.minimum(rng.exponential(0.25, grass.sum()), depth)
        r_new[grass] = r_new[grass] - depth + stop
        i_g = idx[grass]
        n_g = _ref_random_unit(rng, len(i_g)) * 0.5 + normals[i_g]
        normals[i_g] = n_g / np.sqrt(_dot3(n_g, n_g))[:, None]
        reflect[idx[grass]] *= rng.uniform(0.6, 1.4, grass.sum())
    rng_[idx] = np.maximum(r_new, 0.05)


def _ref_vegetation(self, origins, dirs, rays, rng_, normals, reflect, cat, rng):
    from blockloc.sim.scene import raycast_threads
    from blockloc.sim.world import _ICO_F, ALBEDO

    o3d = self._o3d
    vol = self.world.volumes
    active = np.arange(len(rng_))
    t_cur = np.zeros(len(rng_))
    fol = self._cat_index["foliage"]
    for k in range(4):
        if not len(active):
            break
        if k:
            o = origins[active] + dirs[active] * t_cur[active, None]
            rays = np.concatenate([o, dirs[active]], axis=1).astype(np.float32)
        a = self._vol_scene.cast_rays(o3d.core.Tensor(rays), nthreads=raycast_threads())
        th = a["t_hit"].numpy().astype(np.float64)
        if k:
            th += t_cur[active]
        hit = np.isfinite(th) & (th < rng_[active])
        active, th = active[hit], th[hit]
        if not len(active):
            break
        v = self._vsel[a["primitive_ids"].numpy()[hit].astype(np.int64) // len(_ICO_F)]
        t_in, t_out = _ref_ellipsoid_interval(origins[active], dirs[active], vol.center[v], self._vol_radii[v])
        miss = ~np.isfinite(t_in)
        t_in = np.where(miss, th, np.maximum(t_in, t_cur[active]))
        t_out = np.where(miss, th, t_out)
        t_stop = t_in + rng.exponential(self._vol_mfp[v])
        stop = ~miss & (t_stop < t_out) & (t_stop < rng_[active])
        j = active[stop]
        rng_[j] = t_stop[stop]
        normals[j] = _ref_random_unit(rng, len(j))
        reflect[j] = ALBEDO["foliage"] * rng.uniform(0.4, 1.4, len(j))
        cat[j] = fol
        go = ~stop
        active = active[go]
        t_cur[active] = np.maximum(t_out[go], th[go]) + 1e-3


# ``scene._box_exit`` as it was before the facades' kernel
def _box_exit(origins: np.ndarray, dirs: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(N,) distance along each ray (origins, dirs (N, 3)) at which it leaves its axis-aligned
    box (N, 6) x0 x1 y0 y1 z0 z1 (the facade rows' layout), metres."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_lo = (box[:, 0::2] - origins) / dirs
        t_hi = (box[:, 1::2] - origins) / dirs
    far = np.where(np.isfinite(t_lo) & np.isfinite(t_hi), np.maximum(t_lo, t_hi), np.inf)
    return far.min(axis=1)


def _ref_facades(self, idx, owner, origins, dirs, rng_, normals, reflect, glass, rng, cat, lost_at) -> None:
    """``SessionScene._facades`` as 2af77ae had it: the box behind the face measured along every
    ray that hits a facade (now only along the rays into a room)."""
    from blockloc.sim.scene import ALBEDO, BACK_WALL_M, ROOM_MIN_M, dot3, value_noise

    f = self.world.facades[owner]
    n = normals[idx]
    d = dirs[idx]
    vertical = np.abs(n[:, 2]) < 0.5
    p = origins[idx] + d * rng_[idx, None]
    u = np.where(np.abs(n[:, 0]) > np.abs(n[:, 1]), p[:, 1], p[:, 0])
    hz = p[:, 2] - (f[:, 4] + 0.5)
    level = np.floor(hz / f[:, 7])
    v = hz - level * f[:, 7]
    uu = np.mod(u + f[:, 9], f[:, 8]) / f[:, 8]
    cos_i = np.maximum(np.abs(dot3(n, d)), 0.25)
    ledge = vertical & (level >= 1) & (v < 0.4)
    window = vertical & ~ledge & (uu > 0.25) & (uu < 0.85) & (v > 0.9) & (v < f[:, 7] - 0.5) & (hz > 0.3)
    pilaster = vertical & ~ledge & ~window & (uu < 0.12)
    out = np.where(ledge, 0.2, np.where(pilaster, 0.15, np.where(window, -0.18, 0.0)))
    r = rng_[idx] - out / cos_i
    u_g = rng.random(len(idx))
    lost = window & (u_g < 0.55)
    inside = window & (u_g >= 0.55) & (u_g < 0.85)
    depth = _box_exit(origins[idx], d, f[:, 0:6]) - rng_[idx]
    room = inside & (depth >= ROOM_MIN_M)
    r = np.where(room, r + np.minimum(rng.uniform(1.0, 6.0, len(idx)), depth - BACK_WALL_M), r)
    r = np.where(lost, np.inf, r)
    through = np.flatnonzero(inside & ~room)
    if len(through):
        self._through_pane(idx[through], origins, dirs, rng_[idx[through]] + depth[through], r, through,
                           normals, reflect, cat)
        inside[through] = False
    refl = reflect[idx] * (1.0 + 0.25 * value_noise(u, p[:, 2], 0.8, self._seed + 2))
    passed = np.zeros(len(idx), bool)
    passed[through] = True
    refl = np.where(window & ~inside & ~passed, ALBEDO["glass"], refl)
    refl = np.where(passed, reflect[idx], refl)
    lost_at[idx] = np.where(lost, rng_[idx], np.inf)
    rng_[idx] = r
    reflect[idx] = refl
    glass[idx] = window & ~inside & ~passed


def _cast_sweeps(scene, casts, seed: int, timed: bool = True):
    """``scene.cast_full`` of each of :func:`_tiny_sweeps`' casts, the k-th drawing from generator
    ``seed + k``; ``timed`` False: without the sweep's time (the world's static structure)."""
    return [scene.cast_full(o, d, t if timed else None, 100.0, np.random.default_rng(seed + k))
            for k, (o, d, t) in enumerate(casts)]


def _assert_same_casts(got, want):
    """Two lists of casts bit for bit the same, field by field."""
    for g, w in zip(got, want):
        for key in ("range", "normal", "reflect", "cat", "glass", "retro"):
            assert g[key].dtype == w[key].dtype and g[key].tobytes() == w[key].tobytes(), key


def _tiny_sweeps(A: int):
    """The tiny world's localization day (seed 3) and three sweeps of ``A`` columns x 32 beams from
    it: (scene, [(origins (A*32, 3), directions (A*32, 3), mid-sweep time s)])."""
    from blockloc.sim.stream import open_sim_sequence

    seq = open_sim_sequence("tiny", "loc", 3)
    col = np.arange(A) * (0.1 / A)
    casts = []
    for t0 in (4.0, 20.0, 33.0):
        T = seq.trajectory.T_world_flu(t0 + col) @ seq.T_flu_lidar
        d_true = _beams(A, 0.0, None)[1]
        casts.append((np.repeat(T[:, :3, 3], 32, axis=0),
                      np.matmul(d_true, T[:, :3, :3].transpose(0, 2, 1)).reshape(-1, 3), t0 + 0.05))
    return seq.scene, casts


def test_facades_measure_the_room_behind_a_window_only_for_rays_into_it(monkeypatch):
    """A tiny-world scan's facades (windows lost, glass returns, rooms, panes passed)
    with the box depth taken only for the rays into a window, and with it taken for every facade
    ray (2af77ae): the same bits."""
    from blockloc.sim.scene import SessionScene

    scene, casts = _tiny_sweeps(1000)
    room_rays = []
    real_facades = SessionScene._facades

    def counting(self, idx, owner, origins, dirs, rng_, *rest):
        before = rng_[idx].copy()
        real_facades(self, idx, owner, origins, dirs, rng_, *rest)
        room_rays.append(int((rng_[idx] - before > 0.9).sum()))  # returns from a room behind a pane

    monkeypatch.setattr(SessionScene, "_facades", counting)
    got = _cast_sweeps(scene, casts, 11, timed=False)
    monkeypatch.setattr(SessionScene, "_facades", _ref_facades)
    want = _cast_sweeps(scene, casts, 11, timed=False)
    assert sum(room_rays) > 20 and sum(int(w["glass"].sum()) for w in want) > 20
    _assert_same_casts(got, want)


def test_scene_cast_gives_the_numpy_ground_and_vegetation_bits(monkeypatch):
    """A real scene's cast (tiny world, a localization day: grass, kerbs, crowns, walkers), with
    the kernels and with the numpy they replaced, from the same generator: the same bits."""
    from blockloc.sim.scene import SessionScene

    scene, casts = _tiny_sweeps(720)

    got = _cast_sweeps(scene, casts, 7)
    monkeypatch.setattr(SessionScene, "_ground_relief", _ref_ground_relief)
    monkeypatch.setattr(SessionScene, "_vegetation", _ref_vegetation)
    want = _cast_sweeps(scene, casts, 7)
    fol, grass_like = scene.categories.index("foliage"), scene.categories.index("terrain")
    assert sum(int((w["cat"] == fol).sum()) for w in want) > 50  # rays stopped in crowns
    assert sum(int((w["cat"] == grass_like).sum()) for w in want) > 1000
    _assert_same_casts(got, want)


def test_column_poses_at_once_are_the_rotation_and_position_evaluated_apart():
    """``T_world_flu`` evaluates the planar splines, the terrain and the platform's vibration
    once for both parts of a pose: its bits are those of ``rotation`` and ``position`` (each
    evaluating them on its own, as every scan's column poses did), on a drive with the tilting
    platform and at a single time."""
    from blockloc.sim.stream import open_sim_sequence

    tr = open_sim_sequence("tiny", "loc", 2).trajectory
    assert tr._tilt is not None and tr.platform.vibration_z_m > 0
    t = np.sort(np.random.default_rng(5).uniform(0.0, tr.duration, 3000))
    T = tr.T_world_flu(t)
    assert T[:, :3, :3].tobytes() == tr.rotation(t).tobytes()
    assert T[:, :3, 3].tobytes() == np.ascontiguousarray(tr.position(t)).tobytes()
    assert np.array_equal(T[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1)))
    assert tr.T_world_flu(t[11]).tobytes() == T[11:12].tobytes()


def test_first_vegetation_pass_leaves_out_only_rays_that_end_short_of_every_hull(monkeypatch):
    """The first vegetation pass casts only the rays whose range reaches, in xy, the nearest hull
    disc of their bearing's sector: on the tiny world's sweeps it leaves out most rays, and the
    cast is bit for bit the one casting every ray (a hull met at or past a ray's range is not
    taken, so the answers left out were never read)."""
    from blockloc.sim.scene import SessionScene

    scene, casts = _tiny_sweeps(720)
    kept = []
    real = SessionScene._rays_near_hulls

    def counting(self, origins, dirs, rng_):
        out = real(self, origins, dirs, rng_)
        kept.append((len(out), len(rng_)))
        return out

    monkeypatch.setattr(SessionScene, "_rays_near_hulls", counting)
    got = _cast_sweeps(scene, casts, 5)
    assert sum(k for k, _ in kept) < 0.6 * sum(n for _, n in kept)  # most rays left out
    monkeypatch.setattr(SessionScene, "_rays_near_hulls", lambda self, o, d, r: np.arange(len(r)))
    want = _cast_sweeps(scene, casts, 5)
    assert sum(int((w["cat"] == scene.categories.index("foliage")).sum()) for w in want) > 50
    _assert_same_casts(got, want)


def test_actor_cast_leaves_out_only_rays_that_end_short_of_every_actor(monkeypatch):
    """The actors' cast takes, of the columns pointing at an actor, only the rays whose range
    reaches its bounding circle: on the tiny world's sweeps (walkers and cars about) it leaves
    out many of them, and the cast is bit for bit the one casting every ray at the actors."""
    from blockloc.sim import _kernels
    from blockloc.sim.scene import SessionScene

    scene, casts = _tiny_sweeps(720)
    kept = []
    real = _kernels.actor_rays

    def counting(xy, origins, dirs, rng_, step, radius, margin):
        out = real(xy, origins, dirs, rng_, step, radius, margin)
        cols = real(xy, origins, dirs, np.full(len(rng_), np.inf), step, radius, margin)
        kept.append((len(out), len(cols)))
        return out

    monkeypatch.setattr(_kernels, "actor_rays", counting)
    got = _cast_sweeps(scene, casts, 5)
    assert sum(k for k, _ in kept) < 0.8 * sum(n for _, n in kept)  # rays of the columns left out
    monkeypatch.setattr(_kernels, "actor_rays", lambda xy, o, d, r, *rest: np.arange(len(r)))
    want = _cast_sweeps(scene, casts, 5)
    actors = [scene.categories.index(c) for c in ("pedestrian", "vehicle")]
    assert sum(int(np.isin(w["cat"], actors).sum()) for w in want) > 50
    _assert_same_casts(got, want)


def test_actor_meshes_lie_within_the_bounding_radius():
    """Every walker's and car's mesh lies within ACTOR_RADIUS_M of its position in xy (the
    actors' cast leaves out rays by it)."""
    from blockloc.sim.scene import ACTOR_RADIUS_M
    from blockloc.sim.stream import open_sim_sequence

    scene = open_sim_sequence("tiny", "loc", 3).scene
    worst = 0.0
    for t in (3.0, 17.5, 31.0):
        xy, _ = scene.actors.poses(t)
        V, F, tri_cat = scene.actor_mesh(t, np.r_[xy.mean(axis=0), 0.0], 1e6)
        d = np.hypot(V[:, None, 0] - xy[None, :, 0], V[:, None, 1] - xy[None, :, 1]).min(axis=1)
        worst = max(worst, float(d.max()))
        assert len(set(tri_cat.tolist())) == 2  # both kinds met
    assert 1.0 < worst < ACTOR_RADIUS_M


def test_sector_reach_keeps_every_ray_whose_range_meets_a_disc():
    """Brute force over random discs and rays from near a point (any direction length, infinite
    and zero ranges, vertical rays): every ray whose xy segment meets a disc is kept by
    ``rays_reaching``, and rays far short of every disc are left out."""
    from blockloc.sim import _kernels

    g = np.random.default_rng(3)
    centers = g.uniform(-60, 60, (300, 2))
    radii = g.uniform(0.2, 4.0, 300)
    c0 = np.array([1.5, -2.0])
    n = 6000
    origins = np.c_[c0 + g.uniform(-0.3, 0.3, (n, 2)), g.uniform(0, 2, n)]
    dirs = g.normal(size=(n, 3)) * g.uniform(0.5, 2.0, (n, 1))
    dirs[:50, :2] = 0.0  # straight up or down
    rng_ = g.uniform(0.0, 40.0, n)
    rng_[50:80] = np.inf
    spread = _kernels.xy_spread(origins, c0)
    assert spread <= np.hypot(0.3, 0.3) + 1e-12
    reach = _kernels.sector_reach(c0, spread, centers, radii, 2048)
    kept = np.zeros(n, bool)
    kept[_kernels.rays_reaching(dirs, rng_, reach, 0.05)] = True
    # the xy segment origin .. origin + range * dir against each disc
    o, d = origins[:, None, :2], dirs[:, None, :2]
    s_end = np.where(np.isfinite(rng_), rng_, 1e6)[:, None]
    rel = centers[None] - o
    dd = (d * d).sum(axis=2)
    s = np.clip(np.where(dd > 0, (rel * d).sum(axis=2) / np.where(dd > 0, dd, 1.0), 0.0), 0.0, s_end)
    gap = np.linalg.norm(rel - d * s[..., None], axis=2)
    meets = (gap <= radii[None]).any(axis=1)
    assert meets.sum() > 300 and kept[meets].all()
    assert kept[:80].all()
    assert (~kept).sum() > 0.2 * n


def test_gauss_markov_recursion_gives_lfilters_bits():
    """The IMU's bias instability is filtered without scipy.signal: the bits of
    ``lfilter([1], [1, -phi], w, axis=0)`` it replaced (empty, one sample, a long run)."""
    from scipy.signal import lfilter

    from blockloc.sim.stream import _ar1

    g = np.random.default_rng(4)
    phi = float(np.exp(-0.01 / 300.0))
    for n in (0, 1, 2, 5000):
        w = g.normal(0.0, 0.02, (n, 3))
        want = lfilter([1.0], [1.0, -phi], w, axis=0)
        got = _ar1(w, phi)
        assert got.dtype == want.dtype and got.shape == want.shape and got.tobytes() == want.tobytes()


def test_the_workers_point_words_are_write_sessions_bits():
    """blockloc.sim.parallel._encode_words (the kernel nclt_words) against nclt._encode_words:
    points on and around the 5 mm grid's ties and the format's range, NaN and inf, intensities
    rounded, clipped and NaN, rings over 255; other dtypes go to nclt's own."""
    from blockloc.datasets import nclt
    from blockloc.sim.parallel import _encode_words

    rng = np.random.default_rng(7)
    n = 5000
    pts = rng.uniform(-120.0, 240.0, (n, 3))
    pts[:500] = np.round(pts[:500] / 0.0025) * 0.0025  # half-way between grid points (ties)
    pts[500:520] = [-100.0, 227.675, 0.0]  # the range's ends
    pts[520:530] = [-100.0025, 227.6775, 1.0]
    pts[530, 1], pts[531, 2], pts[532, 0] = np.nan, np.inf, -np.inf
    inten = rng.uniform(-20.0, 300.0, n).astype(np.float32)
    inten[:40] = np.round(inten[:40]) + 0.5  # ties
    inten[40:45] = [np.nan, -0.4, 254.5, 255.5, 0.5]
    ring = rng.integers(0, 300, n).astype(np.uint16)
    want_w, want_k = nclt._encode_words(pts, inten, ring)
    got_w, got_k = _encode_words(pts, inten, ring)
    assert got_w.dtype == want_w.dtype and np.array_equal(got_k, want_k) and not want_k.all()
    assert got_w.tobytes() == want_w.tobytes()
    # a scan as the lidar model gives it (every point kept), and another dtype (nclt's own path)
    ok = want_k
    w2, k2 = _encode_words(pts[ok], inten[ok], ring[ok])
    assert k2.all() and w2.tobytes() == want_w.tobytes()
    w3, k3 = _encode_words(pts.astype(np.float32), inten, ring.astype(np.int64))
    r3 = nclt._encode_words(pts.astype(np.float32), inten, ring.astype(np.int64))
    assert w3.tobytes() == r3[0].tobytes() and np.array_equal(k3, r3[1])
