"""Numba kernels of the branch-and-bound search (compiled once, cached on disk).

Conventions: ``levels`` (H+1, NX, NY) uint8 pyramid crop; ``dx, dy`` (A, N) int32 crop-relative cell
offsets of the scan cells rotated by each of the A angles; a node is (angle a, translation tx, ty in
cells, level h) and its bound is sum_k levels[h, dx[a, k] + tx, dy[a, k] + ty] (0 outside the crop).
At level 0 the bound is the exact score.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _node_score(levels, h, dx, dy, a, tx, ty):
    nx = levels.shape[1]
    ny = levels.shape[2]
    s = 0
    for k in range(dx.shape[1]):
        i = dx[a, k] + tx
        j = dy[a, k] + ty
        if i >= 0 and j >= 0 and i < nx and j < ny:
            s += levels[h, i, j]
    return s


@njit(cache=True, parallel=True)
def root_scores(levels, h, dx, dy, ra, rtx, rty):
    """Bounds (R,) int64 of the nodes (ra, rtx, rty) (R,) at level h."""
    out = np.empty(ra.shape[0], dtype=np.int64)
    for r in prange(ra.shape[0]):
        out[r] = _node_score(levels, h, dx, dy, ra[r], rtx[r], rty[r])
    return out


@njit(cache=True)
def node_scores(levels, h, dx, dy, ra, rtx, rty):
    """Serial version of :func:`root_scores` (used by tests on single nodes)."""
    out = np.empty(ra.shape[0], dtype=np.int64)
    for r in range(ra.shape[0]):
        out[r] = _node_score(levels, h, dx, dy, ra[r], rtx[r], rty[r])
    return out


@njit(cache=True)
def greedy_dive(levels, dx, dy, a, tx, ty, h, tx_end, ty_end):
    """Descend from node (a, tx, ty, h) always into the child with the highest bound.

    Returns (leaf score, leaf tx, leaf ty): the block-map paper's greedy initial score S0.
    """
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
            s = _node_score(levels, h, dx, dy, a, ctx, cty)
            if s > best:
                best = s
                btx = ctx
                bty = cty
        tx = btx
        ty = bty
    return _node_score(levels, 0, dx, dy, a, tx, ty), tx, ty


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
def branch_and_bound(levels, dx, dy, ra, rtx, rty, rbound, top, tx_end, ty_end, threshold0, K,
                     nms_cells, nms_angles, num_angles, wrap):
    """Depth-first branch and bound from the roots (sorted by ascending bound) at level ``top``.

    A node is expanded only if its bound exceeds the pruning threshold: ``threshold0`` until K
    distinct leaves are held, then the K-th best leaf score (never below ``threshold0``). Children
    are visited best bound first. Returns (scores, angles, tx, ty) of up to K leaves and the number
    of nodes whose bound was computed.
    """
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
            continue
        half = 1 << (h - 1)
        m = 0
        for c in range(4):
            ctx = tx + half * (c & 1)
            cty = ty + half * (c >> 1)
            if ctx >= tx_end or cty >= ty_end:
                continue
            s = _node_score(levels, h - 1, dx, dy, a, ctx, cty)
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
