"""Branch and bound (``global_init/bnb.py``) on a small raster: the angle step, the angle lists,
the rotated cells, and the search against an exhaustive scan of every (angle, x, y) leaf."""

from __future__ import annotations

import math

import numpy as np
import pytest

from blockloc.global_init.bnb import angle_step, make_angles, required_cells, rotated_cells, search
from blockloc.global_init.projection import Raster
from blockloc.global_init.pyramid import assemble, build_pyramid

RES = 0.5


@pytest.mark.parametrize("resolution, d", [(0.25, 30.0), (0.5, 10.0), (1.0, 80.0)])
def test_angle_step_moves_the_farthest_cell_by_one_cell(resolution, d):
    step = angle_step(resolution, d)
    assert 2.0 * d * math.sin(step / 2.0) == pytest.approx(resolution, rel=1e-9)  # chord = r
    # a range below one cell is taken as one cell: at most a 60 degree step
    assert angle_step(resolution, 0.1 * resolution) == pytest.approx(math.pi / 3)


def test_make_angles_full_circle_and_window():
    step = 0.07
    full, wrap = make_angles(0.3, 2 * math.pi, step)
    assert wrap and full[0] == 0.3
    spacing = np.diff(full)
    assert np.allclose(spacing, spacing[0]) and spacing[0] <= step
    assert (full[-1] + spacing[0]) - full[0] == pytest.approx(2 * math.pi)
    part, wrap = make_angles(1.0, 0.5, step)
    assert not wrap and len(part) % 2 == 1 and part[len(part) // 2] == pytest.approx(1.0)
    assert part[0] <= 1.0 - 0.25 and part[-1] >= 1.0 + 0.25
    np.testing.assert_allclose(np.diff(part), step)


def test_rotated_cells_are_the_floor_of_the_rotated_points():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-10, 10, (50, 2))
    angles = np.array([0.0, 0.4, -2.0])
    cx, cy = rotated_cells(xy, angles, RES)
    for a, th in enumerate(angles):
        c, s = math.cos(th), math.sin(th)
        np.testing.assert_array_equal(cx[a], np.floor((c * xy[:, 0] - s * xy[:, 1]) / RES))
        np.testing.assert_array_equal(cy[a], np.floor((s * xy[:, 0] + c * xy[:, 1]) / RES))


def _world():
    """Raster (global cells over [-30, 30) m) of random wall segments, 255 on the walls."""
    rng = np.random.default_rng(4)
    n = int(60 / RES)
    grid = np.zeros((n, n), np.uint8)
    for _ in range(25):
        p0 = rng.uniform(0, n, 2)
        d = rng.normal(size=2)
        d /= np.linalg.norm(d)
        for s in np.arange(0, rng.uniform(5, 30), 0.5):
            i, j = (p0 + s * d).astype(int)
            if 0 <= i < n and 0 <= j < n:
                grid[i, j] = 255
    origin = np.array([-n // 2, -n // 2], np.int64)
    return Raster(origin, grid, RES, np.zeros(2, np.int64), np.zeros((1, 1), np.float32))


def _scan_of(raster, x, y, th):
    """The scan (N, 2), body frame: the raster's wall cells within 9 m of the pose (x, y, th)."""
    occ = np.argwhere(raster.grid > 0)
    centres = (occ + raster.origin + 0.5) * RES
    near = centres[np.linalg.norm(centres - [x, y], axis=1) < 9.0]
    c, s = math.cos(th), math.sin(th)
    rel = near - [x, y]
    return np.c_[c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]]


def _brute_force(pyramid, scan_xy, center_xy, window_m, angles):
    """Every leaf's score (mean level-0 value under the scan cells), as search() defines them."""
    base = pyramid.levels[0].astype(np.int64)
    cx, cy = rotated_cells(scan_xy, angles, RES)
    half = int(math.ceil(0.5 * window_m / RES))
    c0 = np.floor(np.asarray(center_xy) / RES).astype(np.int64)
    ts = np.arange(-half, half + 1)
    scores = np.zeros((len(angles), len(ts), len(ts)))
    for a in range(len(angles)):
        for i, tx in enumerate(c0[0] + ts):
            for j, ty in enumerate(c0[1] + ts):
                gx = cx[a] + tx - pyramid.origin[0]
                gy = cy[a] + ty - pyramid.origin[1]
                ok = (gx >= 0) & (gy >= 0) & (gx < base.shape[0]) & (gy < base.shape[1])
                scores[a, i, j] = base[gx[ok], gy[ok]].sum() / (255.0 * len(scan_xy))
    return scores, c0[0] + ts, c0[1] + ts


@pytest.mark.parametrize("use_s0", [True, False])
def test_search_finds_the_exhaustive_best_leaf(use_s0):
    raster = _world()
    x_true, y_true, th_true = 3.2, -1.7, 0.8
    scan_xy = _scan_of(raster, x_true, y_true, th_true)
    center, window = np.array([x_true + 1.6, y_true - 1.3]), 6.0
    lo, hi = required_cells(scan_xy, center, window, RES)
    pyramid = assemble([build_pyramid(raster, 4)], lo, hi)
    cands, stats = search(pyramid, scan_xy, center, window, top_k=3, use_s0=use_s0)
    angles, _ = make_angles(0.0, 2 * math.pi, stats.angle_step_rad)
    assert stats.num_angles == len(angles)
    scores, txs, tys = _brute_force(pyramid, scan_xy, center, window, angles)
    best = scores.max()
    assert cands and cands[0].score == pytest.approx(best, abs=1e-12)
    a, i, j = np.unravel_index(np.argmax(scores), scores.shape)
    assert (cands[0].x, cands[0].y) == (txs[i] * RES, tys[j] * RES)
    assert cands[0].theta == pytest.approx(angles[a])
    # and it is the truth, to a cell and an angle step
    assert abs(cands[0].x - x_true) <= RES and abs(cands[0].y - y_true) <= RES
    dth = (cands[0].theta - th_true + math.pi) % (2 * math.pi) - math.pi
    assert abs(dth) <= stats.angle_step_rad
    assert best > 0.6  # cell centres rotated off the lattice: not all land on their cell
    # scores are in order and no candidate beats the exhaustive best
    got = [cd.score for cd in cands]
    assert got == sorted(got, reverse=True) and max(got) <= best + 1e-12
    if use_s0:
        assert 0.9 * best - 1e-9 <= stats.s0 <= best + 1e-12


def test_a_saturated_window_cannot_crowd_out_the_others_with_per_window_leaves():
    # Right of x = 30 m the map is occupied everywhere (woods in the height band): any pose there
    # scores 1. One top K over both windows returns only leaves there; per-window leaves keep the
    # true window's best leaf, which is its exhaustive best.
    from blockloc.global_init.bnb import Window, search_windows

    world = _world()
    n = world.grid.shape[0]
    grid = np.full((2 * n, n), 255, np.uint8)
    grid[:n] = world.grid
    raster = Raster(world.origin, grid, RES, np.zeros(2, np.int64), np.zeros((1, 1), np.float32))
    x_true, y_true, th_true = 3.2, -1.7, 0.8
    scan_xy = _scan_of(world, x_true, y_true, th_true)
    true_w = Window(np.array([x_true + 1.1, y_true - 0.9]), 6.0, th_true, math.radians(20))
    sat_w = Window(np.array([60.0, 0.0]), 6.0, 0.0, math.radians(20))
    lo, hi = required_cells(scan_xy, np.array([32.0, 0.0]), 70.0, RES)
    pyramid = assemble([build_pyramid(raster, 4)], lo, hi)
    shared, _ = search_windows(pyramid, scan_xy, [sat_w, true_w], top_k=2, top_level=3)
    assert shared and all(cd.x > 50 for cd in shared)  # the failure the quota prevents
    each, _ = search_windows(pyramid, scan_xy, [sat_w, true_w], top_k=2, top_level=3, per_window_k=2)
    mine = [cd for cd in each if cd.window == 1]
    assert mine and {cd.window for cd in each} == {0, 1}
    assert abs(mine[0].x - x_true) <= RES and abs(mine[0].y - y_true) <= RES
    alone, _ = search_windows(pyramid, scan_xy, [true_w], top_k=1, top_level=3)
    assert mine[0].score == pytest.approx(alone[0].score, abs=1e-12)


def test_windows_below_the_keep_ratio_of_the_best_s0_are_pruned_and_the_kept_leaves_stay_the_same():
    # Per-window leaves: a window whose leaves all fall below keep_ratio x the best leaf of all is
    # dropped at the end; each window's threshold starts just below keep_ratio x the best S0 of all
    # windows (an S0 is a leaf's score), so such a window is hardly expanded, and the leaves kept
    # are those of each window searched alone.
    from blockloc.global_init.bnb import Window, search_windows

    world = _world()
    raster = Raster(world.origin, world.grid, RES, np.zeros(2, np.int64), np.zeros((1, 1), np.float32))
    x_true, y_true, th_true = 3.2, -1.7, 0.8
    scan_xy = _scan_of(world, x_true, y_true, th_true)
    true_w = Window(np.array([x_true + 1.1, y_true - 0.9]), 6.0, th_true, math.radians(20))
    wrong_w = Window(np.array([-12.0, 9.0]), 6.0, th_true + 2.0, math.radians(20))
    lo, hi = required_cells(scan_xy, np.zeros(2), 40.0, RES)
    pyramid = assemble([build_pyramid(raster, 4)], lo, hi)
    kw = dict(top_k=1, top_level=3, per_window_k=1, keep_ratio=0.8)
    alone_true, st_true = search_windows(pyramid, scan_xy, [true_w], **kw)
    alone_wrong, st_wrong = search_windows(pyramid, scan_xy, [wrong_w], **kw)
    assert alone_true and alone_wrong
    assert alone_wrong[0].score < 0.8 * alone_true[0].score  # the wrong window cannot be kept
    both, st = search_windows(pyramid, scan_xy, [wrong_w, true_w], **kw)
    assert [(c.x, c.y, c.theta, c.score, c.window) for c in both] == \
        [(c.x, c.y, c.theta, c.score, 1) for c in alone_true]
    assert st.nodes_visited < st_true.nodes_visited + st_wrong.nodes_visited
