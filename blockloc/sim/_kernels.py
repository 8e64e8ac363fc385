"""Numba kernels of the simulator's per-ray models (leaf module: importing it imports numba).

Each kernel is one pass over a scan's rays (~70k) doing what a chain of numpy expressions did in
as many passes, with the same IEEE operations in the same order, so its results are the numpy
expressions' bits (held to them by tests/test_sim_kernels.py). What a kernel must not compute
itself is left to numpy by its caller: random draws (the generator's stream is the scan's bytes)
and numpy's transcendental ufuncs (its SIMD ``exp`` / ``power`` differ from libm's in the last
bit now and then, and a return kept or dropped on such a bit is a different scan). A kernel may
finish a draw the generator's C code finishes with libm (``laplace``: log of a uniform;
``lognormal``: exp of a normal): numba calls the same libm, so those bits are numpy's, and the
kernel takes them only for the rays that use them.

Ray layout: ray ``i = column * 32 + laser``, the lidar model's (A, 32) sweep flattened.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def lidar_ranges(rng_true, normals, dirs, reflect, cat, r_self, self_cat, self_hits,
                 mix_u, mix_frac, mix_prob, gap_m):
    """Self hits, incidence and mixed pixels of one sweep.

    rng_true, reflect (N,) float64 and cat (N,) int64 are the cast's, changed in place where the
    robot's own parts (``r_self`` (N,), inf: none) are nearer (``self_hits``): range r_self,
    reflectance 0.15, category ``self_cat``. normals, dirs: (N, 3) float64 (world).
    mix_u, mix_frac: (N,) the mixed-pixel draws (uniform [0, 1) and [0.1, 0.9); mix_prob 0: none):
    where a laser's next column (wrapping) jumps by more than ``gap_m`` and ``mix_u < mix_prob``
    the range moves ``mix_frac`` of the way to the next one.
    Returns |cos incidence| (N,) and the ranges after mixing (N,) float64 metres.
    """
    n = len(rng_true)
    cosi = np.empty(n)
    if self_hits:
        for i in range(n):
            if r_self[i] < rng_true[i]:
                rng_true[i] = r_self[i]
                cat[i] = self_cat
                reflect[i] = 0.15
    for i in range(n):
        cosi[i] = abs(normals[i, 0] * dirs[i, 0] + normals[i, 1] * dirs[i, 1] + normals[i, 2] * dirs[i, 2])
    out = rng_true.copy()
    if mix_prob > 0:
        for i in range(n):
            j = i + 32 if i + 32 < n else i + 32 - n  # the same laser's next column
            gap = rng_true[j] - rng_true[i]
            if np.isfinite(gap) and abs(gap) > gap_m and mix_u[i] < mix_prob:
                out[i] = rng_true[i] + mix_frac[i] * gap
    return cosi, out


@njit(cache=True, nogil=True)
def lidar_returns(rng_true, cosi, reflect, nrm, tail_u, tail_prob, lap_u, lap_scale, range_offset,
                  use_offset, u_drop, u_graze, gain, max_range, min_range, dropout_prob, grazing_cos):
    """Measured ranges and the returns kept before the weak-signal test.

    rng_true, cosi, reflect: (N,) from :func:`lidar_ranges`. Range noise: ``nrm`` (N,) Gaussian,
    replaced where ``tail_u < tail_prob`` by a Laplace tail of scale ``lap_scale`` drawn from the
    uniform ``lap_u`` (N,) in (0, 1) as numpy's ``Generator.laplace`` does (libm's log, as numpy's
    C code: the same bits), plus the laser's ``range_offset`` (32,) when ``use_offset``.
    u_drop, u_graze: (N,) uniform draws. gain: (32,).
    Returns r (N,) measured range, ok (N,) bool, power (N,) (reflectance-and-incidence, no gain),
    rr (N,) range for the intensity's fall-off (>= 1 m; 1 km where nothing was hit) and snr (N,).
    """
    n = len(rng_true)
    r = np.empty(n)
    ok = np.empty(n, np.bool_)
    power = np.empty(n)
    rr = np.empty(n)
    snr = np.empty(n)
    for i in range(n):
        laser = i % 32
        if tail_u[i] < tail_prob:
            u = lap_u[i]
            noise = 0.0 - lap_scale * np.log(2.0 - u - u) if u >= 0.5 else 0.0 + lap_scale * np.log(u + u)
        else:
            noise = nrm[i]
        if use_offset:
            noise = noise + range_offset[laser]
        rt = rng_true[i]
        r[i] = rt + noise
        fin = np.isfinite(rt)
        ok[i] = (fin and rt <= max_range and r[i] >= min_range and u_drop[i] >= dropout_prob
                 and not (cosi[i] < grazing_cos and u_graze[i] < 0.5))
        p = reflect[i] * (0.2 + 0.8 * cosi[i])
        power[i] = p
        v = rt if fin else 1e3
        v = v if v > 1.0 else 1.0
        rr[i] = v
        q = 10.0 / v
        snr[i] = p * gain[laser] * (q * q)
    return r, ok, power, rr, snr


@njit(cache=True, nogil=True)
def lidar_points(idx, r, d_nom, col_offsets, scale, gain, power, speckle_n, falloff, retro, retro_u):
    """The kept returns ``idx`` (K,) int64 of the N rays: points (K, 3) float64 along the nominal
    directions ``d_nom`` (N, 3) at ranges ``r`` (N,); ring (K,) uint16; time offsets (K,)
    float32 from the columns' ``col_offsets`` (A,) float32; intensity (K,) float32, floor of
    ``scale * gain (32,) * power (N,) * speckle * falloff (K,)`` clipped to 0..255, where the
    speckle is exp of the normal draw ``speckle_n`` (N,) (numpy's ``lognormal``, libm's exp;
    empty: none) and retroreflectors (``retro`` (N,) bool) read ``retro_u`` (N,) instead."""
    k = len(idx)
    pts = np.empty((k, 3))
    ring = np.empty(k, np.uint16)
    toff = np.empty(k, np.float32)
    i_out = np.empty(k, np.float32)
    spk = len(speckle_n) > 0
    for m in range(k):
        i = idx[m]
        ri = r[i]
        pts[m, 0] = d_nom[i, 0] * ri
        pts[m, 1] = d_nom[i, 1] * ri
        pts[m, 2] = d_nom[i, 2] * ri
        ring[m] = i % 32
        toff[m] = col_offsets[i // 32]
        if retro[i]:
            v = retro_u[i]
        else:
            v = scale * gain[i % 32] * power[i]
            if spk:
                v = v * np.exp(speckle_n[i])
            v = v * falloff[m]
        v = 0.0 if v < 0.0 else (255.0 if v > 255.0 else v)
        i_out[m] = np.floor(v)
    return pts, ring, toff, i_out


@njit(cache=True, nogil=True)
def value_noise(x, y, cell_m, seed_term):
    """Smooth noise in [-1, 1] at (x, y) (N,) float64 each: bilinear over a hashed lattice of
    ``cell_m`` cells; ``seed_term`` = seed * 83492791 (int64). See blockloc.sim.scene.value_noise."""
    out = np.empty(len(x))
    for k in range(len(x)):
        out[k] = _noise_at(x[k], y[k], cell_m, seed_term)
    return out


@njit(cache=True, nogil=True, inline="always")
def _noise_at(x, y, cell_m, seed_term):
    gx = x / cell_m
    gy = y / cell_m
    ix = np.int64(np.floor(gx))
    iy = np.int64(np.floor(gy))
    fx = gx - ix
    fy = gy - iy
    sx = fx * fx * (3 - 2 * fx)
    sy = fy * fy * (3 - 2 * fy)
    top = _lattice(ix, iy, seed_term) * (1 - sx) + _lattice(ix + 1, iy, seed_term) * sx
    bot = _lattice(ix, iy + 1, seed_term) * (1 - sx) + _lattice(ix + 1, iy + 1, seed_term) * sx
    return top * (1 - sy) + bot * sy


@njit(cache=True, nogil=True, inline="always")
def _lattice(i, j, seed_term):
    v = (i * np.int64(73856093)) ^ (j * np.int64(19349663)) ^ seed_term
    v = (v ^ (v >> np.int64(13))) * np.int64(1274126177)
    return ((v ^ (v >> np.int64(16))) & np.int64(0xFFFF)) / 32767.5 - 1.0


@njit(cache=True, nogil=True)
def material_tiles(x, y, tile, max_tiles):
    """The raster tiles of side ``tile`` (m) that points (x, y) (N,) float64 fall in: tile
    numbers ti, tj (N,) int64 (floor of x / tile, y / tile), their bounding box of tiles
    (i0, j0, ni, nj) and, when it holds at most ``max_tiles`` tiles, each point's tile within
    it ``(ti - i0) * nj + (tj - j0)`` (N,) and which of them are used (ni * nj,) bool (else
    both empty: the caller numbers the tiles by a sort). N >= 1."""
    n = len(x)
    ti = np.empty(n, np.int64)
    tj = np.empty(n, np.int64)
    for k in range(n):
        ti[k] = np.int64(np.floor(x[k] / tile))
        tj[k] = np.int64(np.floor(y[k] / tile))
    i0, i1, j0, j1 = ti[0], ti[0], tj[0], tj[0]
    for k in range(n):
        i0 = min(i0, ti[k])
        i1 = max(i1, ti[k])
        j0 = min(j0, tj[k])
        j1 = max(j1, tj[k])
    ni, nj = i1 - i0 + 1, j1 - j0 + 1
    if ni * nj > max_tiles:
        return ti, tj, i0, j0, ni, nj, np.empty(0, np.int64), np.empty(0, np.bool_)
    local = np.empty(n, np.int64)
    used = np.zeros(ni * nj, np.bool_)
    for k in range(n):
        c = (ti[k] - i0) * nj + (tj[k] - j0)
        local[k] = c
        used[c] = True
    return ti, tj, i0, j0, ni, nj, local, used


@njit(cache=True, nogil=True)
def material_lookup(R, slot, local, ti, tj, x, y, tile, res):
    """Ground codes (N,) uint8 of points (x, y) (N,) in packed raster tiles R (T, n, n / 4)
    uint8 (four 2-bit codes a byte, column j in bits 2 (j % 4)); point k is in tile
    ``slot[local[k]]`` numbered (ti, tj) (N,); cells of ``res`` m, clamped to the tile."""
    n = R.shape[1]
    out = np.empty(len(x), np.uint8)
    for k in range(len(x)):
        i = np.int64((y[k] - tj[k] * tile) / res)
        j = np.int64((x[k] - ti[k] * tile) / res)
        i = 0 if i < 0 else (n - 1 if i > n - 1 else i)
        j = 0 if j < 0 else (n - 1 if j > n - 1 else j)
        out[k] = (R[slot[local[k]], i, j >> 2] >> ((j & 3) << 1)) & 3
    return out


@njit(cache=True, nogil=True)
def ground_hits(origins, dirs, rng_, cat, terrain_cat):
    """The rays (N,) whose hit is on the terrain (``cat == terrain_cat``): their indices (K,)
    int64 and hit points origin + dir * range (K, 3) float64 (world)."""
    n = len(rng_)
    k = 0
    for i in range(n):
        if cat[i] == terrain_cat:
            k += 1
    idx = np.empty(k, np.int64)
    p = np.empty((k, 3))
    m = 0
    for i in range(n):
        if cat[i] == terrain_cat:
            idx[m] = i
            r = rng_[i]
            p[m, 0] = origins[i, 0] + dirs[i, 0] * r
            p[m, 1] = origins[i, 1] + dirs[i, 1] * r
            p[m, 2] = origins[i, 2] + dirs[i, 2] * r
            m += 1
    return idx, p


@njit(cache=True, nogil=True)
def ground_micro(rng_, dirs, idx, p, mat, seed_term):
    """Micro relief along the ground rays ``idx`` (K,) (of the ranges rng_ (N,) and directions
    dirs (N, 3)): each one's range r = rng_[idx] less noise(p, 0.7 m cells) x (2 cm on grass,
    mat 2; else 4 mm) over the ray's downward slope ``down`` = max(-dz, 0.02). Returns r, the
    new ranges and down (K,) each."""
    k = len(idx)
    r = np.empty(k)
    down = np.empty(k)
    r_new = np.empty(k)
    for m in range(k):
        i = idx[m]
        v = -dirs[i, 2]
        dn = v if v > 0.02 else 0.02
        down[m] = dn
        amp = 0.02 if mat[m] == 2 else 0.004
        micro = _noise_at(p[m, 0], p[m, 1], 0.7, seed_term) * amp
        r[m] = rng_[i]
        r_new[m] = rng_[i] - micro / dn
    return r, r_new, down


@njit(cache=True, nogil=True)
def kerb_rays(idx, mat, origins, dirs, r, down, kerb_m):
    """The ground rays on a sidewalk (``mat == 1``): their positions (S,) in idx (K,), their
    ranges r_0 (S,) (of r (K,)), the ranges r_side (S,) to the surface raised ``kerb_m`` (r_0 -
    kerb_m / down) and that surface's point there, x and y (S,) each (world)."""
    s_n = 0
    for m in range(len(mat)):
        if mat[m] == 1:
            s_n += 1
    side = np.empty(s_n, np.int64)
    r_0 = np.empty(s_n)
    r_side = np.empty(s_n)
    x = np.empty(s_n)
    y = np.empty(s_n)
    s = 0
    for m in range(len(mat)):
        if mat[m] == 1:
            i = idx[m]
            side[s] = m
            r_0[s] = r[m]
            rs = r[m] - kerb_m / down[m]
            r_side[s] = rs
            x[s] = origins[i, 0] + dirs[i, 0] * rs
            y[s] = origins[i, 1] + dirs[i, 1] * rs
            s += 1
    return side, r_0, r_side, x, y


@njit(cache=True, nogil=True)
def ground_grass(r_new, down, p, grass, idx, stop_draw, unit_draw, normals, reflect, refl_draw, seed_term):
    """The grass layer (4-12 cm high) along the ground rays ``grass`` (G,) (positions in idx):
    a ray enters it and stops after ``stop_draw`` (G,) (exponential) or at the ground; its normal
    tilts by half the random direction ``unit_draw`` (G, 3) (normal draws, normalized here) and
    its reflectance scales by ``refl_draw`` (G,). Changes r_new (K,), normals and reflect (N, ...)
    (at idx[grass]) in place."""
    for m in range(len(grass)):
        g = grass[m]
        g_h = 0.08 + 0.04 * _noise_at(p[g, 0], p[g, 1], 1.5, seed_term)
        depth = g_h / down[g]
        s = stop_draw[m]
        stop = s if s < depth else depth
        r_new[g] = r_new[g] - depth + stop
        i = idx[g]
        v0, v1, v2 = unit_draw[m, 0], unit_draw[m, 1], unit_draw[m, 2]
        nv = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        a0 = v0 / nv * 0.5 + normals[i, 0]
        a1 = v1 / nv * 0.5 + normals[i, 1]
        a2 = v2 / nv * 0.5 + normals[i, 2]
        na = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        normals[i, 0] = a0 / na
        normals[i, 1] = a1 / na
        normals[i, 2] = a2 / na
        reflect[i] = reflect[i] * refl_draw[m]


@njit(cache=True, nogil=True)
def actor_rays(xy, origins, dirs, rng_, step, radius, margin):
    """The rays (M,) int64, ascending, that could hit a moving actor before their range: the
    rays (N,) come in columns of ``step`` sharing an origin (origins, dirs (N, 3), ranges rng_
    (N,)); a column is taken if it points within an actor's bounding circle (``radius`` m round
    its position ``xy`` (K, 2), widened by 0.1 m a metre of distance: a column's beams fan out
    in xy when the sensor tilts) ahead of its origin (or the origin is inside the circle), and
    of its rays those whose range reaches that circle's near side (a hit on the actor is at least
    the xy distance to the circle away along the ray: ``rng_ > dist - radius - margin``).
    Conservative: a ray it leaves out cannot meet an actor before its range, so its cast is not
    needed (the others' casts do not depend on it)."""
    n = len(rng_)
    keep = np.zeros(n, np.bool_)
    for c in range(n // step):
        i0 = c * step
        ox, oy = origins[i0, 0], origins[i0, 1]
        dx, dy = dirs[i0, 0], dirs[i0, 1]
        hx = np.hypot(dx, dy) + 1e-12
        for k in range(len(xy)):
            rx = xy[k, 0] - ox
            ry = xy[k, 1] - oy
            dist = np.hypot(rx, ry)
            along = (rx * dx + ry * dy) / hx
            perp2 = max(dist * dist - along * along, 0.0)
            lim = radius + 0.1 * dist
            if perp2 < lim * lim and (along > 0 or dist < radius):
                near = dist - radius - margin
                for i in range(i0, i0 + step):
                    if rng_[i] > near:
                        keep[i] = True
    return np.flatnonzero(keep)


@njit(cache=True, nogil=True)
def vegetation_rays(origins, dirs, active, t_cur):
    """(M, 6) float32 rays (origin, direction) of the ``active`` rays (M,) of origins, dirs
    (N, 3), starting ``t_cur`` (N,) metres along them (where they left their last volume)."""
    out = np.empty((len(active), 6), np.float32)
    for q in range(len(active)):
        i = active[q]
        t = t_cur[i]
        for c in range(3):
            out[q, c] = origins[i, c] + dirs[i, c] * t
            out[q, 3 + c] = dirs[i, c]
    return out


@njit(cache=True, nogil=True)
def vegetation_hits(th32, prim, active, t_cur, rng_, vsel, faces_per_volume, origins, dirs, center, radii,
                    first):
    """The ``active`` rays (M,) that meet a vegetation volume's hull before their range, after
    their cast at the hulls (float32 distances ``th32`` (M,), inf: none, from the origin when
    ``first``, else from ``t_cur`` (N,) along the ray; hull triangles ``prim`` (M,), volume
    ``vsel[prim // faces_per_volume]``). For those rays (H,): indices, hull distance from the
    origin th, volume v, and the stretch of the ray inside the volume's ellipsoid (``center``,
    semi-axes ``radii`` (V, 3); origins, dirs (N, 3)): t_in (from t_cur on) and t_out, both th
    where the ray misses the ellipsoid (miss True)."""
    m = len(active)
    h = 0
    for q in range(m):
        t = np.float64(th32[q])
        if not first:
            t = t + t_cur[active[q]]
        if np.isfinite(t) and t < rng_[active[q]]:
            h += 1
    act = np.empty(h, np.int64)
    th = np.empty(h)
    v = np.empty(h, np.int64)
    t_in = np.empty(h)
    t_out = np.empty(h)
    miss = np.empty(h, np.bool_)
    j = 0
    for q in range(m):
        i = active[q]
        t = np.float64(th32[q])
        if not first:
            t = t + t_cur[i]
        if not (np.isfinite(t) and t < rng_[i]):
            continue
        k = vsel[np.int64(prim[q]) // faces_per_volume]
        act[j], th[j], v[j] = i, t, k
        o0 = (origins[i, 0] - center[k, 0]) / radii[k, 0]
        o1 = (origins[i, 1] - center[k, 1]) / radii[k, 1]
        o2 = (origins[i, 2] - center[k, 2]) / radii[k, 2]
        d0 = dirs[i, 0] / radii[k, 0]
        d1 = dirs[i, 1] / radii[k, 1]
        d2 = dirs[i, 2] / radii[k, 2]
        a = d0 * d0 + d1 * d1 + d2 * d2
        b = o0 * d0 + o1 * d1 + o2 * d2
        cc = o0 * o0 + o1 * o1 + o2 * o2 - 1.0
        disc = b * b - a * cc
        sq = np.sqrt(disc) if disc >= 0 else np.nan
        ti = (-b - sq) / a
        if np.isfinite(ti):
            miss[j] = False
            tc = t_cur[i]
            t_in[j] = ti if ti >= tc else tc
            t_out[j] = (-b + sq) / a
        else:
            miss[j] = True
            t_in[j] = t
            t_out[j] = t
        j += 1
    return act, th, v, t_in, t_out, miss


@njit(cache=True, nogil=True)
def vegetation_stops(act, th, t_in, t_out, miss, free_path, rng_, t_cur):
    """Where the rays ``act`` (H,) stop inside their volume: at t_in + ``free_path`` (H,) (the
    exponential draws) when that lies before both the ray's exit ``t_out`` and its range
    ``rng_`` (N,), which it becomes (in place). The others go on: ``t_cur`` (N,) (in place)
    moves 1 mm past where they leave the volume. Returns the stopped rays' indices and the rays
    going on."""
    h = len(act)
    stop = np.empty(h, np.bool_)
    ns = 0
    for q in range(h):
        ts = t_in[q] + free_path[q]
        stop[q] = (not miss[q]) and ts < t_out[q] and ts < rng_[act[q]]
        if stop[q]:
            ns += 1
    stopped = np.empty(ns, np.int64)
    going = np.empty(h - ns, np.int64)
    a = b = 0
    for q in range(h):
        i = act[q]
        if stop[q]:
            rng_[i] = t_in[q] + free_path[q]
            stopped[a] = i
            a += 1
        else:
            to, tt = t_out[q], th[q]
            t_cur[i] = (to if to >= tt else tt) + 1e-3
            going[b] = i
            b += 1
    return stopped, going


@njit(cache=True, nogil=True)
def make_rays(origins, dirs):
    """(N, 6) float32 rays (origin, direction) of origins, dirs (N, 3) float64."""
    out = np.empty((len(origins), 6), np.float32)
    for i in range(len(origins)):
        for c in range(3):
            out[i, c] = origins[i, c]
            out[i, 3 + c] = dirs[i, c]
    return out


@njit(cache=True, nogil=True)
def static_hits(t32, prim, n32, sel):
    """An open3d cast's answer as the scene uses it: range (N,) float64 (inf: no hit), triangle
    (N,) int64 (``sel[prim]``: the scene's triangles are a selection of the world's; -1: no hit)
    and normals (N, 3) float64 (t_hit (N,) float32, primitive ids (N,) uint32, normals (N, 3)
    float32)."""
    n = len(t32)
    t = np.empty(n)
    tri = np.empty(n, np.int64)
    nrm = np.empty((n, 3))
    for i in range(n):
        t[i] = t32[i]
        tri[i] = sel[np.int64(prim[i])] if np.isfinite(t32[i]) else -1
        for c in range(3):
            nrm[i, c] = n32[i, c]
    return t, tri, nrm


@njit(cache=True, nogil=True)
def hit_categories(rng_, tri, tri_cat, reflect_by_cat):
    """Category (N,) int64 of each hit (``tri_cat[tri]``; -1 where ``rng_`` is inf) and its
    reflectance (N,) (``reflect_by_cat[cat]``; the last entry: no hit)."""
    n = len(rng_)
    cat = np.empty(n, np.int64)
    refl = np.empty(n)
    for i in range(n):
        c = np.int64(tri_cat[tri[i]]) if np.isfinite(rng_[i]) else np.int64(-1)
        cat[i] = c
        refl[i] = reflect_by_cat[c]
    return cat, refl


@njit(cache=True, nogil=True)
def _pseudo_angle(x, y):
    """A number in [0, 4) growing with the angle atan2(y, x) in [0, 2 pi) (NaN at x = y = 0):
    the sector lookups below need the order of angles, not their values (no atan2 a ray)."""
    s = abs(x) + abs(y)
    if not s > 0:  # numba raises on a division by zero
        return np.nan
    p = x / s
    return 1.0 - p if y >= 0 else 3.0 + p


@njit(cache=True, nogil=True)
def sector_reach(c0, spread, centers, radii, n_bins):
    """Per sector (n_bins (B,) equal steps of :func:`_pseudo_angle` round ``c0`` (2,), xy
    metres), a horizontal distance no ray from within ``spread`` metres of ``c0`` pointing into
    that sector travels before it can meet one of the discs ``centers`` (K, 2) / ``radii`` (K,)
    (inf: no disc lies that way). A disc at distance D is met only by directions within
    asin(r' / D) of its bearing (r' = radius + spread: a ray from anywhere within ``spread`` is
    a ray from ``c0`` shifted by at most that), and not before D - r'. The sectors a disc
    touches are widened by one each side (rounding)."""
    out = np.full(n_bins, np.inf)
    scale = n_bins / 4.0
    for k in range(len(centers)):
        dx = centers[k, 0] - c0[0]
        dy = centers[k, 1] - c0[1]
        D = np.hypot(dx, dy)
        rr = radii[k] + spread
        near = D - rr
        if rr >= 0.99 * D:  # c0 inside (or next to) the disc: every direction
            for b in range(n_bins):
                out[b] = min(out[b], near)
            continue
        beta = np.arcsin(rr / D)
        alpha = np.arctan2(dy, dx)
        lo = int(np.floor(_pseudo_angle(np.cos(alpha - beta), np.sin(alpha - beta)) * scale)) - 1
        hi = int(np.floor(_pseudo_angle(np.cos(alpha + beta), np.sin(alpha + beta)) * scale)) + 1
        if lo <= hi:
            for b in range(lo, hi + 1):
                out[b % n_bins] = min(out[b % n_bins], near)
        else:  # the sector wraps through angle 0
            for b in range(lo, n_bins):
                out[b] = min(out[b], near)
            for b in range(0, hi + 1):
                out[b] = min(out[b], near)
    return out


@njit(cache=True, nogil=True)
def rays_reaching(dirs, rng_, reach, margin):
    """Indices (M,) of the rays (directions ``dirs`` (N, 3), ranges ``rng_`` (N,) in their
    lengths) whose range takes them in xy as far as the :func:`sector_reach` distance ``reach``
    (B,) of the sector their xy direction points into, less ``margin`` metres. Kept too: rays
    with no xy direction, or an infinite range."""
    n = len(rng_)
    scale = len(reach) / 4.0
    keep = np.empty(n, np.bool_)
    m = 0
    for i in range(n):
        pa = _pseudo_angle(dirs[i, 0], dirs[i, 1])
        if np.isfinite(pa) and np.isfinite(rng_[i]):
            b = min(max(int(pa * scale), 0), len(reach) - 1)
            lim = reach[b] - margin
            # range * |xy of dir| < lim, squared (no square root a ray)
            keep[i] = not (lim > 0 and rng_[i] * rng_[i] * (dirs[i, 0] * dirs[i, 0] + dirs[i, 1] * dirs[i, 1])
                           < lim * lim)
        else:
            keep[i] = True
        if keep[i]:
            m += 1
    out = np.empty(m, np.int64)
    j = 0
    for i in range(n):
        if keep[i]:
            out[j] = i
            j += 1
    return out


@njit(cache=True, nogil=True)
def xy_spread(origins, c0):
    """The largest xy distance (m) of any of ``origins`` (N, 3) from ``c0`` (2,) (a bound:
    the hypot of the largest distances per axis)."""
    mx = 0.0
    my = 0.0
    for i in range(len(origins)):
        mx = max(mx, abs(origins[i, 0] - c0[0]))
        my = max(my, abs(origins[i, 1] - c0[1]))
    return np.hypot(mx, my)


@njit(cache=True, nogil=True)
def nclt_words(pts, intensity, ring, offset, scale):
    """``blockloc.datasets.nclt._encode_words`` of a rendered scan in one pass: points (K, 3)
    float64, intensity (K,) float32, ring (K,) uint16 -> (words (M,) uint64 of the kept points,
    keep (K,) bool), its bits (the same rint of the same quotient; the same clips). ``offset``,
    ``scale``: ``NCLT_POINT_OFFSET``, ``NCLT_POINT_SCALE``."""
    n = pts.shape[0]
    flat = pts.reshape(-1)
    q = np.empty(3 * n)
    for j in range(3 * n):  # no branch: a vectorised loop
        q[j] = np.rint((flat[j] - offset) / scale)
    words = np.empty(n, np.uint64)
    keep = np.empty(n, np.bool_)
    m = 0
    for i in range(n):
        qx, qy, qz = q[3 * i], q[3 * i + 1], q[3 * i + 2]
        # False for NaN, and +-inf is outside
        ok = qx >= 0 and qx <= 65535 and qy >= 0 and qy <= 65535 and qz >= 0 and qz <= 65535
        keep[i] = ok
        if not ok:
            continue
        v = np.rint(np.float64(intensity[i]))
        if v != v:  # NaN: 0
            v = 0.0
        v = min(max(v, 0.0), 255.0)
        r = min(np.uint64(ring[i]), np.uint64(255))
        words[m] = (np.uint64(qx) | (np.uint64(qy) << np.uint64(16)) | (np.uint64(qz) << np.uint64(32))
                    | (np.uint64(v) << np.uint64(48)) | (r << np.uint64(56)))
        m += 1
    return words[:m], keep


@njit(cache=True, nogil=True, inline="always")
def _np_mod(a, b):
    """numpy's float ``np.mod(a, b)`` (``npy_remainder``: fmod, then the divisor's sign)."""
    mod = np.fmod(a, b)
    if b == 0.0:
        return mod
    if mod != 0.0:
        if (b < 0.0) != (mod < 0.0):
            mod += b
    else:
        mod = np.copysign(0.0, b)
    return mod


@njit(cache=True, nogil=True)
def facade_rays(cat, tri, tri_owner, is_facade_cat, facades, reflect):
    """The rays (N,) whose hit is on a category with facade rows (``is_facade_cat[cat]``; no hit:
    ``cat`` -1): their indices (K,) int64 and rows ``tri_owner[tri]`` (K,) int64; each one's
    reflectance set to its row's (``facades[row, 6]``; ``facades`` (B, 10), not empty) in place."""
    n = len(cat)
    k = 0
    for i in range(n):
        c = cat[i]
        if c >= 0 and is_facade_cat[c]:
            k += 1
    idx = np.empty(k, np.int64)
    owner = np.empty(k, np.int64)
    m = 0
    for i in range(n):
        c = cat[i]
        if c >= 0 and is_facade_cat[c]:
            idx[m] = i
            o = np.int64(tri_owner[tri[i]])
            owner[m] = o
            reflect[i] = facades[o, 6]
            m += 1
    return idx, owner


@njit(cache=True, nogil=True, inline="always")
def _box_far(o, d, box):
    """Distance along a ray (origin o, direction d (3,)) at which it leaves the axis-aligned box
    ``box`` (x0 x1 y0 y1 z0 z1, the first six of a facade row), metres: of each axis' two slab
    distances, the larger, where both are finite; the least of those (inf: none)."""
    far = np.inf
    for a in range(3):
        da = d[a]
        if da == 0.0:  # both slab distances inf or NaN: not finite
            continue
        t_lo = (box[2 * a] - o[a]) / da
        t_hi = (box[2 * a + 1] - o[a]) / da
        if np.isfinite(t_lo) and np.isfinite(t_hi):
            fa = t_lo if t_lo > t_hi else t_hi
            if fa < far:
                far = fa
    return far


@njit(cache=True, nogil=True)
def box_exit(origins, dirs, box):
    """(N,) distance along each ray (origins, dirs (N, 3)) at which it leaves its axis-aligned
    box (N, 6+) x0 x1 y0 y1 z0 z1 (a facade row's layout), metres (the facades' kernel's)."""
    out = np.empty(len(origins))
    for i in range(len(origins)):
        out[i] = _box_far(origins[i], dirs[i], box[i])
    return out


#: facade_faces' per-ray flags
FACADE_WINDOW, FACADE_LOST, FACADE_INSIDE, FACADE_ROOM = 1, 2, 4, 8


@njit(cache=True, nogil=True)
def facade_faces(idx, owner, facades, origins, dirs, rng_, normals, u_g, room_draw, room_min, back_wall):
    """Windows, pilasters and ledges of the facade rays ``idx`` (K,) (rows ``owner`` (K,) of
    ``facades`` (B, 10): box x0 x1 y0 y1 z0 z1, reflectance, floor height, bay width, bay offset):
    ``SessionScene._facades`` up to the panes passed. u_g (K,): the glass draws (uniform [0, 1));
    room_draw (K,): the room depth draws (uniform [1, 6)).

    Returns the new ranges r (K,) (inf: lost at the pane), flags (K,) uint8 (FACADE_*), the depth
    (K,) of the box behind the face along the rays into a window (0 elsewhere), and the facade
    coordinates u, z (K,) the reflectance noise is taken at."""
    k_n = len(idx)
    r = np.empty(k_n)
    flags = np.zeros(k_n, np.uint8)
    depth = np.zeros(k_n)
    u_out = np.empty(k_n)
    z_out = np.empty(k_n)
    for k in range(k_n):
        i = idx[k]
        o = owner[k]
        n0, n1, n2 = normals[i, 0], normals[i, 1], normals[i, 2]
        d0, d1, d2 = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        ri = rng_[i]
        vertical = np.abs(n2) < 0.5
        p0 = origins[i, 0] + d0 * ri
        p1 = origins[i, 1] + d1 * ri
        p2 = origins[i, 2] + d2 * ri
        u = p1 if np.abs(n0) > np.abs(n1) else p0
        floor_h = facades[o, 7]
        hz = p2 - (facades[o, 4] + 0.5)
        level = np.floor(hz / floor_h)
        v = hz - level * floor_h
        uu = _np_mod(u + facades[o, 9], facades[o, 8]) / facades[o, 8]
        c = np.abs(n0 * d0 + n1 * d1 + n2 * d2)
        cos_i = 0.25 if c < 0.25 else c  # np.maximum(c, 0.25), NaN kept
        ledge = vertical and level >= 1 and v < 0.4
        window = (vertical and not ledge and uu > 0.25 and uu < 0.85 and v > 0.9 and v < floor_h - 0.5
                  and hz > 0.3)
        pilaster = vertical and not ledge and not window and uu < 0.12
        out = 0.2 if ledge else (0.15 if pilaster else (-0.18 if window else 0.0))
        rk = ri - out / cos_i
        g = u_g[k]
        lost = window and g < 0.55
        inside = window and g >= 0.55 and g < 0.85
        fl = np.uint8(0)
        if window:
            fl |= np.uint8(FACADE_WINDOW)
        if lost:
            fl |= np.uint8(FACADE_LOST)
        if inside:
            fl |= np.uint8(FACADE_INSIDE)
            dk = _box_far(origins[i], dirs[i], facades[o]) - ri
            depth[k] = dk
            if dk >= room_min:
                fl |= np.uint8(FACADE_ROOM)
                b = dk - back_wall
                w = room_draw[k]
                rk = rk + (w if w < b else b)  # np.minimum(w, b)
        if lost:
            rk = np.inf
        r[k] = rk
        flags[k] = fl
        u_out[k] = u
        z_out[k] = p2
    return r, flags, depth, u_out, z_out


@njit(cache=True, nogil=True)
def facade_finish(idx, r, flags, passed, u, z, seed_term, glass_albedo, rng_, reflect, glass, lost_at):
    """The end of ``SessionScene._facades``: each facade ray's reflectance (its own times 1 +
    0.25 noise(u, z, 0.8 m cells); glass's on a pane return; a ray ``passed`` (K,) through a
    pane keeps what the cast behind gave it), glass flag, the range it is lost at (``lost_at``)
    and its new range ``r``, written in place at ``idx``."""
    for k in range(len(idx)):
        i = idx[k]
        fl = flags[k]
        window = (fl & FACADE_WINDOW) != 0
        inside = (fl & FACADE_INSIDE) != 0
        on_glass = window and not inside and not passed[k]
        if passed[k]:
            refl = reflect[i]
        elif on_glass:
            refl = glass_albedo
        else:
            refl = reflect[i] * (1.0 + 0.25 * _noise_at(u[k], z[k], 0.8, seed_term))
        lost_at[i] = rng_[i] if (fl & FACADE_LOST) != 0 else np.inf
        rng_[i] = r[k]
        reflect[i] = refl
        glass[i] = on_glass
