"""Branch-and-bound over (x, y, yaw) on a max pyramid (coarse to fine).

Angles: the step is acos(1 - r^2 / (2 d_max^2)) (r: cell size, d_max: the scan's farthest cell), so
one angular step moves the farthest scan cell by at most one cell. Each angle has its own roots at
the top pyramid level tiling the translation window; the search is depth first, best child first
(Cartographer), with the pruning threshold raised from the start to ``s0_ratio`` times the block-map
paper's greedy initial score S0 (a greedy dive from the best roots) instead of waiting for leaves.
The K best distinct leaves (non-maximum suppression over ``nms_m`` and ``nms_deg``) are returned.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from blockloc.global_init.pyramid import Pyramid

log = logging.getLogger(__name__)


@dataclass
class Candidate2D:
    """A leaf of the search: the levelled body at (x, y) metres (levelled frame L) with the levelled
    scan rotated by ``theta`` rad; ``score`` in [0, 1] (mean raster value under the scan cells)."""

    x: float
    y: float
    theta: float
    score: float
    window: int = -1  # index of its window in :func:`search_windows` with ``per_window_k`` (else -1)


@dataclass
class SearchStats:
    num_angles: int
    angle_step_rad: float
    num_roots: int
    nodes_visited: int
    s0: float  # greedy initial score, [0, 1]; 0 when not used
    time_s: float
    regions: int = 1  # pyramid crops searched (search_windows groups nearby windows)


def angle_step(resolution: float, max_range: float) -> float:
    """acos(1 - r^2 / (2 d^2)): the rotation moving a point at range d by one cell of side r."""
    d = max(max_range, resolution)
    return math.acos(1.0 - resolution**2 / (2.0 * d**2))


def make_angles(theta_center: float, yaw_window_rad: float, step: float) -> tuple[np.ndarray, bool]:
    """Angles (A,) covering ``theta_center`` +- window/2 and whether they wrap the full circle."""
    if yaw_window_rad >= 2.0 * math.pi - 1e-9:
        n = int(math.ceil(2.0 * math.pi / step))
        return theta_center + np.arange(n) * (2.0 * math.pi / n), True
    n_half = int(math.ceil(0.5 * yaw_window_rad / step))
    return theta_center + np.arange(-n_half, n_half + 1) * step, False


def rotated_cells(xy: np.ndarray, angles: np.ndarray, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Cells (A, N) int64 of the scan cell centres xy (N, 2) rotated by each angle (A,)."""
    c = np.cos(angles)[:, None]
    s = np.sin(angles)[:, None]
    x = xy[None, :, 0]
    y = xy[None, :, 1]
    cx = np.floor((c * x - s * y) / resolution).astype(np.int64)
    cy = np.floor((s * x + c * y) / resolution).astype(np.int64)
    return cx, cy


def _s0_pruning(pyramid: Pyramid, dx, dy, offsets, ra, rtx, rty, top: int, tx_end: int, ty_end: int,
                n_dives: int, full: int, threshold: int, s0_ratio: float) -> tuple[float, int]:
    """Greedy initial score S0 (block-map paper): the best leaf of greedy dives from the
    ``n_dives`` best roots (the root arrays sorted by score, ascending). Returns (S0 as a
    fraction of ``full``, the pruning threshold raised to just below ``s0_ratio`` x S0).
    ``offsets``: ``_kernels.scan_offsets`` of dx, dy."""
    from blockloc.global_init import _kernels as K

    best = -1
    for i in range(1, min(n_dives, len(ra)) + 1):
        s, _, _ = K.greedy_dive(pyramid.levels, dx, dy, *offsets, ra[-i], rtx[-i], rty[-i], top, tx_end, ty_end)
        best = max(best, int(s))
    # Prune below a fraction of S0 (not S0 itself) so near-best candidates survive for the
    # ambiguity check and the NDT verification; the S0 leaf is found again by the search.
    threshold = max(threshold, int(s0_ratio * best) - 1)
    return best / full, threshold


def search(pyramid: Pyramid, scan_xy: np.ndarray, center_xy: np.ndarray, window_m: float,
           theta_center: float = 0.0, yaw_window_rad: float = 2.0 * math.pi, top_k: int = 5,
           use_s0: bool = True, s0_ratio: float = 0.9, min_score: float = 0.05,
           nms_m: float = 1.0, nms_deg: float = 5.0, n_dives: int = 8,
           max_range: float | None = None) -> tuple[list[Candidate2D], SearchStats]:
    """Top-K poses of the scan cells ``scan_xy`` (N, 2), levelled body frame, in the pyramid.

    The body is searched over the square ``center_xy`` (2,) +- window_m/2 (levelled frame, metres)
    and over angles ``theta_center`` +- yaw_window_rad/2. The pyramid must cover every cell the scan
    can reach from there (see :func:`required_cells`). Scores are in [0, 1].
    """
    from blockloc.global_init import _kernels as K

    t0 = time.perf_counter()
    r = pyramid.resolution
    top = pyramid.num_levels - 1
    n_pts = len(scan_xy)
    d_max = max_range if max_range is not None else float(np.hypot(*scan_xy.T).max())
    step = angle_step(r, d_max)
    angles, wrap = make_angles(theta_center, yaw_window_rad, step)
    cx, cy = rotated_cells(scan_xy, angles, r)
    dx = (cx - pyramid.origin[0]).astype(np.int32)
    dy = (cy - pyramid.origin[1]).astype(np.int32)
    half_cells = int(math.ceil(0.5 * window_m / r))
    c0 = np.floor(np.asarray(center_xy, float) / r).astype(np.int64)
    tx0, ty0 = int(c0[0] - half_cells), int(c0[1] - half_cells)
    n_t = 2 * half_cells + 1
    tx_end, ty_end = tx0 + n_t, ty0 + n_t
    width = 1 << top
    gx = np.arange(tx0, tx_end, width)
    gy = np.arange(ty0, ty_end, width)
    A = len(angles)
    ra = np.repeat(np.arange(A), len(gx) * len(gy)).astype(np.int64)
    rtx = np.tile(np.repeat(gx, len(gy)), A).astype(np.int64)
    rty = np.tile(np.tile(gy, len(gx)), A).astype(np.int64)
    offsets = K.scan_offsets(dx, dy, pyramid.levels.shape[2])
    rb = K.root_scores(pyramid.levels, top, dx, dy, *offsets, ra, rtx, rty)
    order = np.argsort(rb, kind="stable")
    ra, rtx, rty, rb = ra[order], rtx[order], rty[order], rb[order]
    full = 255 * n_pts
    threshold = int(min_score * full)
    s0 = 0.0
    if use_s0 and len(rb):
        s0, threshold = _s0_pruning(pyramid, dx, dy, offsets, ra, rtx, rty, top, tx_end, ty_end, n_dives, full,
                                    threshold, s0_ratio)
    nms_cells = int(math.ceil(nms_m / r))
    nms_angles = int(math.ceil(math.radians(nms_deg) / step))
    cs, ca, ctx, cty, visited = K.branch_and_bound(
        pyramid.levels, dx, dy, *offsets, ra, rtx, rty, rb, top, tx_end, ty_end, threshold, top_k,
        nms_cells, nms_angles, A, wrap, 0.0)
    order = np.argsort(-cs, kind="stable")
    cands = [Candidate2D(float(ctx[i] * r), float(cty[i] * r), float(angles[ca[i]]), float(cs[i] / full))
             for i in order]
    stats = SearchStats(A, step, len(ra), int(visited), s0, time.perf_counter() - t0)
    log.debug("bnb: %d angles x %d roots, %d nodes, best %.3f, %.3f s", A, len(gx) * len(gy),
              visited, cands[0].score if cands else -1, stats.time_s)
    return cands, stats


def _window_roots(w: "Window", angles: np.ndarray, step: float, r: float, width: int):
    """Root (angle index, cell x, cell y) arrays of one window at a level of ``width`` cells."""
    A = len(angles)
    if w.yaw_window >= 2 * math.pi - 1e-9:
        a_idx = np.arange(A)
    else:
        d = (angles - w.theta + math.pi) % (2 * math.pi) - math.pi
        a_idx = np.flatnonzero(np.abs(d) <= 0.5 * w.yaw_window + 0.5 * step)
    half = int(math.ceil(0.5 * w.size_m / r))
    c0 = np.floor(np.asarray(w.center, float) / r).astype(np.int64)
    gx = np.arange(c0[0] - half, c0[0] + half + 1, width)
    gy = np.arange(c0[1] - half, c0[1] + half + 1, width)
    n = len(gx) * len(gy)
    return (np.repeat(a_idx, n).astype(np.int64), np.tile(np.repeat(gx, len(gy)), len(a_idx)).astype(np.int64),
            np.tile(np.tile(gy, len(gx)), len(a_idx)).astype(np.int64))


def _search_each_window(pyramid: Pyramid, scan_xy: np.ndarray, windows: list["Window"], angles: np.ndarray,
                        step: float, top: int, k: int, use_s0: bool, s0_ratio: float, min_score: float,
                        nms_m: float, nms_deg: float, n_dives: int, keep_ratio: float, min_leaf_score: float,
                        t0: float) -> tuple[list[Candidate2D], SearchStats]:
    """:func:`search_windows` with ``per_window_k``: the windows searched side by side (one thread
    each, ``_kernels.search_each_window``), the scan cells rotated only by the angles some window
    takes (a place window spans ~16 deg: 5% of the circle).

    ``min_leaf_score``: the best leaf of an earlier search (0: none). Each window starts at
    ``max(min_score, keep_ratio x min_leaf_score)``, and at ``keep_ratio`` x the best S0 of all
    windows (``_kernels.search_each_window``); a leaf below ``keep_ratio`` x the
    best of all windows is dropped at the end. The serial search raised each window's threshold
    to ``keep_ratio`` x the best leaf of the windows before it: that pruned only leaves this final
    filter drops, so the leaves kept are the same; the windows need not wait for each other.
    """
    from blockloc.global_init import _kernels as K

    r = pyramid.resolution
    A = len(angles)
    full = 255 * len(scan_xy)
    roots = [_window_roots(w, angles, step, r, 1 << top) for w in windows]
    starts = np.zeros(len(roots) + 1, np.int64)
    starts[1:] = np.cumsum([len(x[0]) for x in roots])
    ra = np.concatenate([x[0] for x in roots]) if roots else np.zeros(0, np.int64)
    rtx = np.concatenate([x[1] for x in roots]) if roots else np.zeros(0, np.int64)
    rty = np.concatenate([x[2] for x in roots]) if roots else np.zeros(0, np.int64)
    dx = np.zeros((A, len(scan_xy)), np.int32)
    dy = np.zeros((A, len(scan_xy)), np.int32)
    used = np.unique(ra)
    if len(used):
        cx, cy = rotated_cells(scan_xy, angles[used], r)
        dx[used] = (cx - pyramid.origin[0]).astype(np.int32)
        dy[used] = (cy - pyramid.origin[1]).astype(np.int32)
    nms_cells = int(math.ceil(nms_m / r))
    nms_angles = int(math.ceil(math.radians(nms_deg) / step))
    # just below keep_ratio x min_leaf_score: a leaf scoring that much exactly is kept at the end
    threshold0 = max(int(min_score * full), int(keep_ratio * min_leaf_score * full) - 1)
    offsets = K.scan_offsets(dx, dy, pyramid.levels.shape[2])
    cs, ca, cx_, cy_, s0, visited = K.search_each_window(
        pyramid.levels, dx, dy, *offsets, ra, rtx, rty, starts, top, threshold0, k, nms_cells, nms_angles, A,
        float(keep_ratio), n_dives, float(s0_ratio), bool(use_s0))
    cands: list[Candidate2D] = []
    for wi in range(len(windows)):
        row = cs[wi]
        for i in np.argsort(-row, kind="stable"):
            if row[i] < 0:
                continue
            cands.append(Candidate2D(float(cx_[wi, i] * r), float(cy_[wi, i] * r), float(angles[ca[wi, i]]),
                                     float(row[i] / full), wi))
    best = max([min_leaf_score] + [c.score for c in cands])
    cands = [c for c in cands if c.score >= keep_ratio * best]
    stats = SearchStats(A, step, len(ra), int(visited.sum()), float(s0.max()) / full if len(s0) and use_s0 else 0.0,
                        time.perf_counter() - t0)
    log.debug("bnb over %d windows side by side: %d roots, %d nodes, best %.3f, %.3f s", len(windows), len(ra),
              int(visited.sum()), best, stats.time_s)
    return cands, stats


def required_cells(scan_xy: np.ndarray, center_xy: np.ndarray, window_m: float,
                   resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Global cell range [lo, hi) the pyramid must cover for :func:`search` (any rotation)."""
    d = float(np.hypot(*np.asarray(scan_xy).T).max()) + 2 * resolution
    c = np.asarray(center_xy, float)
    lo = np.floor((c - 0.5 * window_m - d) / resolution).astype(np.int64) - 2
    hi = np.floor((c + 0.5 * window_m + d) / resolution).astype(np.int64) + 3
    return lo, hi


@dataclass
class Window:
    """A search window: the body within ``size_m`` x ``size_m`` around ``center`` (2,) (levelled
    frame L, metres), the levelled scan turned by ``theta`` +- ``yaw_window`` / 2 (rad)."""

    center: np.ndarray
    size_m: float
    theta: float
    yaw_window: float


def search_windows(pyramid: Pyramid, scan_xy: np.ndarray, windows: list[Window], top_k: int = 5,
                   use_s0: bool = True, s0_ratio: float = 0.9, min_score: float = 0.05,
                   nms_m: float = 1.0, nms_deg: float = 5.0, n_dives: int = 8,
                   max_range: float | None = None, keep_ratio: float = 0.0,
                   min_leaf_score: float = 0.0, top_level: int | None = None,
                   per_window_k: int = 0) -> tuple[list[Candidate2D], SearchStats]:
    """Top-K poses over the union of several windows in one branch and bound (one threshold for all,
    so a window whose bound cannot beat the best leaf found elsewhere is never expanded).

    per_window_k > 0: instead, the ``per_window_k`` best leaves of each window (``Candidate2D.window``
    says which), each window searched on its own (its own S0) and pruned below ``keep_ratio`` x the
    best leaf of the windows before it. A region where the map is occupied everywhere (woods, a
    parking lot in the height band) scores about 1 at any pose; with one top K for all windows its
    leaves would crowd out every other window's, the right one's too.

    keep_ratio: leaves below this fraction of the best leaf are pruned (they matter neither as the
    answer nor as its runner-up); min_leaf_score: prune below this score from the start (with
    ``per_window_k``: below ``keep_ratio`` x it, the best leaf of an earlier search itself; else the best
    leaf of an earlier search times keep_ratio). top_level: the level roots start at (default the
    pyramid's top); small windows prune better from a lower level, whose bounds are tighter.

    The angles are the full circle at the range-derived step; each window takes those within its
    yaw window. The pyramid must cover every window plus 2^top cells plus the scan's reach (children
    of a window's last roots may extend past it). Scores are in [0, 1].
    """
    from blockloc.global_init import _kernels as K

    t0 = time.perf_counter()
    r = pyramid.resolution
    top = pyramid.num_levels - 1 if top_level is None else min(top_level, pyramid.num_levels - 1)
    n_pts = len(scan_xy)
    d_max = max_range if max_range is not None else float(np.hypot(*scan_xy.T).max())
    step = angle_step(r, d_max)
    angles, _ = make_angles(0.0, 2 * math.pi, step)
    A = len(angles)
    width = 1 << top
    if per_window_k > 0:
        return _search_each_window(pyramid, scan_xy, windows, angles, step, top, per_window_k, use_s0, s0_ratio,
                                   min_score, nms_m, nms_deg, n_dives, keep_ratio, min_leaf_score, t0)
    ra, rtx, rty = [], [], []
    for w in windows:
        a, x, y = _window_roots(w, angles, step, r, width)
        ra.append(a)
        rtx.append(x)
        rty.append(y)
    if not ra:
        return [], SearchStats(A, step, 0, 0, 0.0, time.perf_counter() - t0)
    roots = np.unique(np.stack([np.concatenate(ra), np.concatenate(rtx), np.concatenate(rty)], axis=1), axis=0)
    cx, cy = rotated_cells(scan_xy, angles, r)
    dx = (cx - pyramid.origin[0]).astype(np.int32)
    dy = (cy - pyramid.origin[1]).astype(np.int32)
    ra = roots[:, 0].astype(np.int64)
    rtx = roots[:, 1].astype(np.int64)
    rty = roots[:, 2].astype(np.int64)
    offsets = K.scan_offsets(dx, dy, pyramid.levels.shape[2])
    rb = K.root_scores(pyramid.levels, top, dx, dy, *offsets, ra, rtx, rty)
    order = np.argsort(rb, kind="stable")
    ra, rtx, rty, rb = ra[order], rtx[order], rty[order], rb[order]
    full = 255 * n_pts
    threshold = int(max(min_score, min_leaf_score) * full)
    big = np.iinfo(np.int64).max // 4
    s0 = 0.0
    if use_s0 and len(rb):
        s0, threshold = _s0_pruning(pyramid, dx, dy, offsets, ra, rtx, rty, top, big, big, n_dives, full,
                                    threshold, s0_ratio)
    nms_cells = int(math.ceil(nms_m / r))
    nms_angles = int(math.ceil(math.radians(nms_deg) / step))
    cs, ca, ctx, cty, visited = K.branch_and_bound(
        pyramid.levels, dx, dy, *offsets, ra, rtx, rty, rb, top, big, big, threshold, top_k,
        nms_cells, nms_angles, A, True, float(keep_ratio))
    order = np.argsort(-cs, kind="stable")
    cands = [Candidate2D(float(ctx[i] * r), float(cty[i] * r), float(angles[ca[i]]), float(cs[i] / full))
             for i in order]
    stats = SearchStats(A, step, len(ra), int(visited), s0, time.perf_counter() - t0)
    log.debug("bnb over %d windows: %d roots, %d nodes, best %.3f, %.3f s", len(windows), len(ra), visited,
              cands[0].score if cands else -1, stats.time_s)
    return cands, stats
