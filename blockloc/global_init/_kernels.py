"""Numba kernels of the branch-and-bound search, the place descriptors and the map points' 2D cells
(compiled once, cached on disk).

Conventions: ``levels`` (H+1, NX, NY) uint8 pyramid crop; ``dx, dy`` (A, N) int32 crop-relative cell
offsets of the scan cells rotated by each of the A angles; a node is (angle a, translation tx, ty in
cells, level h) and its bound is sum_k levels[h, dx[a, k] + tx, dy[a, k] + ty] (0 outside the crop).
At level 0 the bound is the exact score.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic


@intrinsic
def _ctpop(typingctx, x):
    """Set bits of a uint64: the CPU's popcount instruction (llvm.ctpop)."""
    if x != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.ctpop", [ir.IntType(64)])
        return builder.call(fn, args)

    return types.uint64(types.uint64), codegen


@njit(cache=True)
def scan_offsets(dx, dy, ny):
    """The scan cells' offsets ``lin`` (A, N) int64 = dx * ny + dy (a crop of ``ny`` columns) and
    their box per angle ``box`` (A, 4) int64: min dx, max dx, min dy, max dy (:func:`_node_score`)."""
    A = dx.shape[0]
    N = dx.shape[1]
    lin = np.empty((A, N), dtype=np.int64)
    box = np.zeros((A, 4), dtype=np.int64)
    for a in range(A):
        if N == 0:
            continue
        x0 = dx[a, 0]
        x1 = dx[a, 0]
        y0 = dy[a, 0]
        y1 = dy[a, 0]
        for k in range(N):
            x = dx[a, k]
            y = dy[a, k]
            lin[a, k] = np.int64(x) * ny + y
            x0 = min(x0, x)
            x1 = max(x1, x)
            y0 = min(y0, y)
            y1 = max(y1, y)
        box[a, 0] = x0
        box[a, 1] = x1
        box[a, 2] = y0
        box[a, 3] = y1
    return lin, box


@njit(cache=True, inline="always")
def _node_score(levels, flat, h, dx, dy, lin, box, a, tx, ty):
    """The bound of node (a, tx, ty) at level h (module docstring). ``flat``: ``levels`` as one
    row; ``lin, box``: :func:`scan_offsets`. A node whose scan cells all lie in the crop (nearly
    every node: the crop spans the scan's reach past the window) sums ``flat`` at the cells'
    offsets, unchecked: the same sum, which the compiler vectorizes (about 3x faster than the
    checked loop, measured on place windows)."""
    nx = levels.shape[1]
    ny = levels.shape[2]
    s = 0
    if box[a, 0] + tx >= 0 and box[a, 1] + tx < nx and box[a, 2] + ty >= 0 and box[a, 3] + ty < ny:
        off = (h * nx + tx) * ny + ty
        for k in range(lin.shape[1]):
            s += flat[np.uint64(lin[a, k] + off)]
        return s
    for k in range(dx.shape[1]):
        i = dx[a, k] + tx
        j = dy[a, k] + ty
        if i >= 0 and j >= 0 and i < nx and j < ny:
            s += levels[h, i, j]
    return s


@njit(cache=True, parallel=True)
def root_scores(levels, h, dx, dy, lin, box, ra, rtx, rty):
    """Bounds (R,) int64 of the nodes (ra, rtx, rty) (R,) at level h; ``lin, box``: :func:`scan_offsets`."""
    flat = levels.reshape(-1)
    out = np.empty(ra.shape[0], dtype=np.int64)
    for r in prange(ra.shape[0]):
        out[r] = _node_score(levels, flat, h, dx, dy, lin, box, ra[r], rtx[r], rty[r])
    return out


@njit(cache=True)
def node_scores(levels, h, dx, dy, ra, rtx, rty):
    """Serial version of :func:`root_scores` (used by tests on single nodes)."""
    flat = levels.reshape(-1)
    lin, box = scan_offsets(dx, dy, levels.shape[2])
    out = np.empty(ra.shape[0], dtype=np.int64)
    for r in range(ra.shape[0]):
        out[r] = _node_score(levels, flat, h, dx, dy, lin, box, ra[r], rtx[r], rty[r])
    return out


@njit(cache=True)
def greedy_dive(levels, dx, dy, lin, box, a, tx, ty, h, tx_end, ty_end):
    """Descend from node (a, tx, ty, h) always into the child with the highest bound (``lin, box``:
    :func:`scan_offsets`).

    Returns (leaf score, leaf tx, leaf ty): the block-map paper's greedy initial score S0.
    """
    flat = levels.reshape(-1)
    while h > 0:
        half = 1 << (h - 1)
        h -= 1
        best = -1
        btx = tx
        bty = ty
        for c in range(4):
            ctx = tx + half * (c & 1)
            cty = ty + half * (c >> 1)
            if ctx >= tx_end or cty >= ty_end:
                continue
            s = _node_score(levels, flat, h, dx, dy, lin, box, a, ctx, cty)
            if s > best:
                best = s
                btx = ctx
                bty = cty
        tx = btx
        ty = bty
    return _node_score(levels, flat, 0, dx, dy, lin, box, a, tx, ty), tx, ty


@njit(cache=True)
def _insert(cs, ca, cx, cy, n, K, s, a, tx, ty, nms_cells, nms_angles, num_angles, wrap):
    """Insert a leaf into the top-K list with non-maximum suppression; returns the new count."""
    for i in range(n):
        da = abs(ca[i] - a)
        if wrap:
            da = min(da, num_angles - da)
        if da <= nms_angles and abs(cx[i] - tx) <= nms_cells and abs(cy[i] - ty) <= nms_cells:
            if s > cs[i]:
                cs[i] = s
                ca[i] = a
                cx[i] = tx
                cy[i] = ty
            return n
    if n < K:
        cs[n] = s
        ca[n] = a
        cx[n] = tx
        cy[n] = ty
        return n + 1
    worst = 0
    for i in range(1, n):
        if cs[i] < cs[worst]:
            worst = i
    if s > cs[worst]:
        cs[worst] = s
        ca[worst] = a
        cx[worst] = tx
        cy[worst] = ty
    return n


@njit(cache=True)
def branch_and_bound(levels, dx, dy, lin, box, ra, rtx, rty, rbound, top, tx_end, ty_end, threshold0, K,
                     nms_cells, nms_angles, num_angles, wrap, rel_ratio):
    """Depth-first branch and bound from the roots (sorted by ascending bound) at level ``top``.

    A node is expanded only if its bound exceeds the pruning threshold: ``threshold0`` until K
    distinct leaves are held, then the K-th best leaf score (never below ``threshold0``), and never
    below ``rel_ratio`` times the best leaf found (0: off; leaves far below the best are of no use).
    Children are visited best bound first. Returns (scores, angles, tx, ty) of up to K leaves and
    the number of nodes whose bound was computed. ``lin, box``: :func:`scan_offsets`.
    """
    flat = levels.reshape(-1)
    cs = np.full(K, -1, dtype=np.int64)
    ca = np.zeros(K, dtype=np.int64)
    cx = np.zeros(K, dtype=np.int64)
    cy = np.zeros(K, dtype=np.int64)
    n = 0
    R = ra.shape[0]
    cap = R + 4 * (top + 2)
    sa = np.empty(cap, dtype=np.int64)
    stx = np.empty(cap, dtype=np.int64)
    sty = np.empty(cap, dtype=np.int64)
    sh = np.empty(cap, dtype=np.int64)
    sb = np.empty(cap, dtype=np.int64)
    for r in range(R):
        sa[r] = ra[r]
        stx[r] = rtx[r]
        sty[r] = rty[r]
        sh[r] = top
        sb[r] = rbound[r]
    sp = R
    visited = R
    threshold = threshold0
    cb = np.empty(4, dtype=np.int64)
    ctx_ = np.empty(4, dtype=np.int64)
    cty_ = np.empty(4, dtype=np.int64)
    while sp > 0:
        sp -= 1
        b = sb[sp]
        if b <= threshold:
            continue
        a = sa[sp]
        tx = stx[sp]
        ty = sty[sp]
        h = sh[sp]
        if h == 0:
            n = _insert(cs, ca, cx, cy, n, K, b, a, tx, ty, nms_cells, nms_angles, num_angles, wrap)
            if n == K:
                worst = cs[0]
                for i in range(1, n):
                    if cs[i] < worst:
                        worst = cs[i]
                if worst > threshold:
                    threshold = worst
            if rel_ratio > 0.0:
                rel = np.int64(rel_ratio * b) - 1
                if rel > threshold:
                    threshold = rel
            continue
        half = 1 << (h - 1)
        m = 0
        for c in range(4):
            ctx = tx + half * (c & 1)
            cty = ty + half * (c >> 1)
            if ctx >= tx_end or cty >= ty_end:
                continue
            s = _node_score(levels, flat, h - 1, dx, dy, lin, box, a, ctx, cty)
            visited += 1
            if s > threshold:
                cb[m] = s
                ctx_[m] = ctx
                cty_[m] = cty
                m += 1
        # Push ascending so the best child is popped first.
        for i in range(m):
            lo = i
            for j in range(i + 1, m):
                if cb[j] < cb[lo]:
                    lo = j
            if lo != i:
                cb[i], cb[lo] = cb[lo], cb[i]
                ctx_[i], ctx_[lo] = ctx_[lo], ctx_[i]
                cty_[i], cty_[lo] = cty_[lo], cty_[i]
            sa[sp] = a
            stx[sp] = ctx_[i]
            sty[sp] = cty_[i]
            sh[sp] = h - 1
            sb[sp] = cb[i]
            sp += 1
    return cs[:n], ca[:n], cx[:n], cy[:n], visited



@njit(cache=True, parallel=True)
def polar_bits(occ, pi, pj, tab_s0, tab_n, tab_ring, num_sectors, num_rings):
    """Polar occupancy of places on an occupancy raster, as bits.

    occ: (NX, NY) bool occupied cells. pi, pj: (P,) int64 raster indices of the lattice corner each
    place stands on. tab_s0, tab_n, tab_ring: (2R, 2R) tables indexed [di + R, dj + R] for the cell
    at offset (di, dj) from the corner: first sector, number of sectors it subtends (0: outside the
    range annulus) and ring. Returns (P, num_rings, W) uint64, W = ceil(num_sectors / 64): bit s of
    ring r is set when an occupied cell of ring r covers sector s.
    """
    P = pi.shape[0]
    nx = occ.shape[0]
    ny = occ.shape[1]
    R2 = tab_s0.shape[0]
    R = R2 // 2
    W = (num_sectors + 63) // 64
    out = np.zeros((P, num_rings, W), dtype=np.uint64)
    one = np.uint64(1)
    for p in prange(P):
        for a in range(R2):
            i = pi[p] + a - R
            if i < 0 or i >= nx:
                continue
            for b in range(R2):
                j = pj[p] + b - R
                if j < 0 or j >= ny:
                    continue
                n = tab_n[a, b]
                if n == 0 or not occ[i, j]:
                    continue
                r = tab_ring[a, b]
                s0 = tab_s0[a, b]
                for k in range(n):
                    sk = (s0 + k) % num_sectors
                    out[p, r, sk >> 6] |= one << np.uint64(sk & 63)
    return out


@njit(cache=True, inline="always")
def _popcount(x):
    return _ctpop(x)


@njit(cache=True, parallel=True)
def polar_overlaps(scan_shifted, places, rows):
    """Common bits of every shifted scan (K, NR, W) uint64 with places[rows] (P, NR, W) uint64:
    (len(rows), K) int32."""
    n = rows.shape[0]
    K = scan_shifted.shape[0]
    NR = places.shape[1]
    W = places.shape[2]
    out = np.zeros((n, K), dtype=np.int32)
    for q in prange(n):
        p = rows[q]
        for k in range(K):
            c = np.uint64(0)
            for r in range(NR):
                for w in range(W):
                    c += _popcount(scan_shifted[k, r, w] & places[p, r, w])
            out[q, k] = np.int32(c)
    return out


@njit(cache=True, parallel=True)
def polar_weighted_overlaps(scan_shifted, places, rows, weights):
    """Like :func:`polar_overlaps`, with the common bits of ring r of place p weighted by
    ``weights[p, r]`` (P, NR) float32: (len(rows), K) float32."""
    n = rows.shape[0]
    K = scan_shifted.shape[0]
    NR = places.shape[1]
    W = places.shape[2]
    out = np.zeros((n, K), dtype=np.float32)
    for q in prange(n):
        p = rows[q]
        for k in range(K):
            acc = 0.0
            for r in range(NR):
                c = np.uint64(0)
                for w in range(W):
                    c += _popcount(scan_shifted[k, r, w] & places[p, r, w])
                acc += weights[p, r] * np.float32(c)
            out[q, k] = acc
    return out


@njit(cache=True, parallel=True)
def polar_llr(occ_shifted, grown, occ_w, free_shifted, raw, free_w):
    """Per place p and shift k: sum over rings r of occ_w[p, r] * |occ_shifted[k, r] & grown[p, r]|
    + free_w[p, r] * |free_shifted[k, r] & raw[p, r]| (bit sets (K, NR, W) and (P, NR, W) uint64,
    weights (P, NR) float32): the hit terms of the place index's log-likelihood ratio. (P, K) float32.

    Every shift of a place at once, ring by ring (the scan's bits laid out shift-last): the same
    float32 sums in the same order as one shift at a time, which the compiler vectorizes over the
    shifts (~3x faster on the campus index's 17k places)."""
    P = grown.shape[0]
    K = occ_shifted.shape[0]
    NR = grown.shape[1]
    W = grown.shape[2]
    occ_t = np.empty((NR, W, K), dtype=np.uint64)
    free_t = np.empty((NR, W, K), dtype=np.uint64)
    for k in range(K):
        for r in range(NR):
            for w in range(W):
                occ_t[r, w, k] = occ_shifted[k, r, w]
                free_t[r, w, k] = free_shifted[k, r, w]
    out = np.zeros((P, K), dtype=np.float32)
    for p in prange(P):
        acc = np.zeros(K, dtype=np.float32)
        c1 = np.empty(K, dtype=np.uint64)
        c2 = np.empty(K, dtype=np.uint64)
        for r in range(NR):
            c1[:] = 0
            c2[:] = 0
            for w in range(W):
                g = grown[p, r, w]
                b = raw[p, r, w]
                for k in range(K):
                    c1[k] += _popcount(occ_t[r, w, k] & g)
                    c2[k] += _popcount(free_t[r, w, k] & b)
            ow = occ_w[p, r]
            fw = free_w[p, r]
            for k in range(K):
                acc[k] += ow * np.float32(c1[k]) + fw * np.float32(c2[k])
        out[p] = acc
    return out


@njit(cache=True)
def popcounts(bits):
    """Set bits per row of (P, NR, W) uint64: (P, NR) int32."""
    P, NR, W = bits.shape
    out = np.zeros((P, NR), dtype=np.int32)
    for p in range(P):
        for r in range(NR):
            c = np.uint64(0)
            for w in range(W):
                c += _popcount(bits[p, r, w])
            out[p, r] = np.int32(c)
    return out


@njit(cache=True, parallel=True)
def visible_polar_bits(occ, ci, cj, res, num_rays, min_range, ring_width, num_rings, num_sectors, depth):
    """Polar occupancy bits of the cells a 2D scan from each place would see.

    occ: (NX, NY) bool. ci, cj: (P,) int64 raster indices of the lattice corner each place stands on.
    From each place ``num_rays`` rays march outwards in steps of res / 2 from ``min_range`` to
    ``min_range + num_rings * ring_width``; a ray stops ``depth`` metres past its first occupied
    cell, and every occupied cell it passes sets the bit of its (ring, sector).
    Returns (P, num_rings, W) uint64.
    """
    P = ci.shape[0]
    nx = occ.shape[0]
    ny = occ.shape[1]
    W = (num_sectors + 63) // 64
    out = np.zeros((P, num_rings, W), dtype=np.uint64)
    one = np.uint64(1)
    step = 0.5 * res
    max_range = min_range + num_rings * ring_width
    for p in prange(P):
        x0 = ci[p] * res
        y0 = cj[p] * res
        for k in range(num_rays):
            ang = (k + 0.5) * 2.0 * np.pi / num_rays
            c = np.cos(ang)
            s = np.sin(ang)
            sector = int(ang / (2.0 * np.pi) * num_sectors) % num_sectors
            stop = max_range
            r = min_range
            while r < stop:
                i = int(np.floor((x0 + r * c) / res))
                j = int(np.floor((y0 + r * s) / res))
                if i < 0 or j < 0 or i >= nx or j >= ny:
                    break
                if occ[i, j]:
                    if stop == max_range:
                        stop = min(max_range, r + depth)
                    ring = int((r - min_range) / ring_width)
                    out[p, ring, sector >> 6] |= one << np.uint64(sector & 63)
                r += step
    return out


# ----------------------------------------------------------------------------- map points in 2D cells
# (refinement: the points of a box, ``refine.Footprint``). ``R2`` (2, 3) float64: the first two rows
# of R_L_map (map frame -> levelled xy).


@njit(cache=True)
def cell_bounds(points, R2, cell_m):
    """(min x, min y, max x, max y) int64 of the levelled cells floor(R2 @ p / cell_m) of points (N, 3)."""
    lo0 = lo1 = np.int64(1) << 62
    hi0 = hi1 = -(np.int64(1) << 62)
    for k in range(points.shape[0]):
        x = points[k, 0] * R2[0, 0] + points[k, 1] * R2[0, 1] + points[k, 2] * R2[0, 2]
        y = points[k, 0] * R2[1, 0] + points[k, 1] * R2[1, 1] + points[k, 2] * R2[1, 2]
        i = np.int64(np.floor(x / cell_m))
        j = np.int64(np.floor(y / cell_m))
        lo0 = min(lo0, i)
        hi0 = max(hi0, i)
        lo1 = min(lo1, j)
        hi1 = max(hi1, j)
    return lo0, lo1, hi0, hi1


@njit(cache=True)
def cell_counts(points, R2, cell_m, lo0, lo1, nx, ny):
    """(nx, ny) int32 counts of points (N, 3) per levelled cell, cells [lo, lo + (nx, ny))."""
    out = np.zeros((nx, ny), np.int32)
    for k in range(points.shape[0]):
        x = points[k, 0] * R2[0, 0] + points[k, 1] * R2[0, 1] + points[k, 2] * R2[0, 2]
        y = points[k, 0] * R2[1, 0] + points[k, 1] * R2[1, 1] + points[k, 2] * R2[1, 2]
        i = np.int64(np.floor(x / cell_m)) - lo0
        j = np.int64(np.floor(y / cell_m)) - lo1
        if i >= 0 and j >= 0 and i < nx and j < ny:
            out[i, j] += 1
    return out


@njit(cache=True)
def levelled_cells(points, R2, cell_m):
    """(N, 2) int64 levelled cells floor(R2 @ p / cell_m) of points (N, 3), computed as
    ``cell_counts`` computes them (the same cell for the same point, to the last bit)."""
    out = np.empty((points.shape[0], 2), np.int64)
    for k in range(points.shape[0]):
        x = points[k, 0] * R2[0, 0] + points[k, 1] * R2[0, 1] + points[k, 2] * R2[0, 2]
        y = points[k, 0] * R2[1, 0] + points[k, 1] * R2[1, 1] + points[k, 2] * R2[1, 2]
        out[k, 0] = np.int64(np.floor(x / cell_m))
        out[k, 1] = np.int64(np.floor(y / cell_m))
    return out


@njit(cache=True)
def in_levelled_box(points, R2, x0, y0, x1, y1):
    """(N,) bool: points (N, 3) whose levelled xy lies in [x0, x1] x [y0, y1] (m)."""
    out = np.empty(points.shape[0], np.bool_)
    for k in range(points.shape[0]):
        x = points[k, 0] * R2[0, 0] + points[k, 1] * R2[0, 1] + points[k, 2] * R2[0, 2]
        y = points[k, 0] * R2[1, 0] + points[k, 1] * R2[1, 1] + points[k, 2] * R2[1, 2]
        out[k] = x >= x0 and x <= x1 and y >= y0 and y <= y1
    return out


@njit(cache=True, parallel=True)
def search_each_window(levels, dx, dy, lin, box, ra, rtx, rty, starts, top, threshold0, K, nms_cells, nms_angles,
                       num_angles, rel_ratio, n_dives, s0_ratio, use_s0):
    """:func:`branch_and_bound` of W windows at once, one thread per window (``bnb.search_windows``
    with ``per_window_k``). Window w's roots at level ``top`` are ``ra, rtx, rty[starts[w]:starts[w+1]]``
    (any order: sorted here by ascending bound, stably, as the serial search sorts them); its
    threshold starts at ``threshold0``, raised to just below ``s0_ratio`` x its S0 (the best leaf of
    greedy dives from its ``n_dives`` best roots) with ``use_s0``, and to just below ``rel_ratio``
    x the best S0 of all windows: S0 is a leaf's score, so the best leaf of all is at least that,
    and a window's leaves below ``rel_ratio`` x the best of all are dropped by the caller anyway
    (a window whose best leaf falls below returns none instead of one dropped later). Returns per
    window (W, K) scores (-1: none), angles, tx, ty, and (W,) S0 and nodes visited. ``lin, box``:
    :func:`scan_offsets`."""
    flat = levels.reshape(-1)
    W = starts.shape[0] - 1
    cs = np.full((W, K), -1, dtype=np.int64)
    ca = np.zeros((W, K), dtype=np.int64)
    cx = np.zeros((W, K), dtype=np.int64)
    cy = np.zeros((W, K), dtype=np.int64)
    s0 = np.zeros(W, dtype=np.int64)
    visited = np.zeros(W, dtype=np.int64)
    big = np.int64(1) << 60
    R = ra.shape[0]
    sa = np.empty(R, dtype=np.int64)  # each window's roots, sorted by ascending bound
    sx = np.empty(R, dtype=np.int64)
    sy = np.empty(R, dtype=np.int64)
    sb = np.empty(R, dtype=np.int64)
    # Phase 1: root bounds and S0 of every window.
    for w in prange(W):
        a0 = starts[w]
        a1 = starts[w + 1]
        if a1 <= a0:
            continue
        n = a1 - a0
        b = np.empty(n, dtype=np.int64)
        for r in range(n):
            b[r] = _node_score(levels, flat, top, dx, dy, lin, box, ra[a0 + r], rtx[a0 + r], rty[a0 + r])
        order = np.argsort(b, kind="mergesort")
        for r in range(n):
            sa[a0 + r] = ra[a0 + order[r]]
            sx[a0 + r] = rtx[a0 + order[r]]
            sy[a0 + r] = rty[a0 + order[r]]
            sb[a0 + r] = b[order[r]]
        if use_s0:
            best = -1
            for i in range(1, min(n_dives, n) + 1):
                s, _, _ = greedy_dive(levels, dx, dy, lin, box, sa[a1 - i], sx[a1 - i], sy[a1 - i], top, big, big)
                if s > best:
                    best = s
            s0[w] = best
    floor = threshold0
    if use_s0 and rel_ratio > 0.0 and W > 0:
        floor = max(floor, np.int64(rel_ratio * s0.max()) - 1)
    # Phase 2: each window's branch and bound.
    for w in prange(W):
        a0 = starts[w]
        a1 = starts[w + 1]
        if a1 <= a0:
            continue
        threshold = floor
        if use_s0:
            threshold = max(threshold, np.int64(s0_ratio * s0[w]) - 1)
        s_, a_, x_, y_, v = branch_and_bound(levels, dx, dy, lin, box, sa[a0:a1], sx[a0:a1], sy[a0:a1], sb[a0:a1],
                                             top, big, big, threshold, K, nms_cells, nms_angles, num_angles, True,
                                             rel_ratio)
        for i in range(s_.shape[0]):
            cs[w, i] = s_[i]
            ca[w, i] = a_[i]
            cx[w, i] = x_[i]
            cy[w, i] = y_[i]
        visited[w] = v
    return cs, ca, cx, cy, s0, visited


@njit(cache=True)
def greedy_nms(xy, order, min_dist, k):
    """Greedy non-maximum suppression of points ``xy`` (P, 2) float64 taken in ``order`` (N,) int64:
    a point is kept unless one kept before lies closer than ``min_dist`` (hypot); stops at ``k``
    kept. Returns the kept indices (into ``xy``), in the order kept."""
    out = np.empty(min(k, order.shape[0]), dtype=np.int64)
    n = 0
    for i in range(order.shape[0]):
        if n >= k:
            break
        o = order[i]
        x = xy[o, 0]
        y = xy[o, 1]
        near = False
        for j in range(n):
            dx = xy[out[j], 0] - x
            dy = xy[out[j], 1] - y
            if abs(dx) < min_dist and abs(dy) < min_dist and np.hypot(dx, dy) < min_dist:
                near = True
                break
        if not near:
            out[n] = o
            n += 1
    return out[:n]
