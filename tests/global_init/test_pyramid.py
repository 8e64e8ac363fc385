"""The pyramid's bound is admissible: every node bounds its children and every leaf below it."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from blockloc.global_init import _kernels as K
from blockloc.global_init.projection import Raster
from blockloc.global_init.pyramid import assemble, build_pyramid


def _raster(seed, nx, ny, density):
    rng = np.random.default_rng(seed)
    grid = np.where(rng.random((nx, ny)) < density, rng.integers(1, 256, (nx, ny)), 0).astype(np.uint8)
    return Raster(np.array([rng.integers(-50, 50), rng.integers(-50, 50)]), grid, 0.25,
                  np.zeros(2, np.int64), np.zeros((1, 1), np.float32))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), levels=st.integers(2, 5), density=st.floats(0.01, 0.5),
       n_pts=st.integers(1, 40))
def test_every_node_bounds_its_children_and_leaves(seed, levels, density, n_pts):
    rng = np.random.default_rng(seed)
    ras = _raster(seed, int(rng.integers(8, 40)), int(rng.integers(8, 40)), density)
    pyr = build_pyramid(ras, levels)
    # Scan cells relative to the translation, crop-relative as the search uses them.
    cells = rng.integers(-12, 12, (1, n_pts, 2))
    dx = (cells[..., 0] - pyr.origin[0]).astype(np.int32)
    dy = (cells[..., 1] - pyr.origin[1]).astype(np.int32)
    top = levels - 1
    w = 1 << top
    lo = ras.origin - w - 12
    hi = ras.origin + np.array(ras.grid.shape) + 12
    for _ in range(5):
        tx, ty = (int(v) for v in rng.integers(lo, hi))
        zero = np.zeros(1, np.int64)
        node = int(K.node_scores(pyr.levels, top, dx, dy, zero, np.array([tx]), np.array([ty]))[0])
        # children at level top-1
        half = w >> 1
        for c in range(4):
            ctx, cty = tx + half * (c & 1), ty + half * (c >> 1)
            child = int(K.node_scores(pyr.levels, top - 1, dx, dy, zero, np.array([ctx]), np.array([cty]))[0])
            assert node >= child
        # every leaf (exact score on the base raster) below the node
        gx, gy = np.meshgrid(np.arange(tx, tx + w), np.arange(ty, ty + w), indexing="ij")
        leaves = K.node_scores(pyr.levels, 0, dx, dy, np.zeros(gx.size, np.int64), gx.ravel().astype(np.int64),
                               gy.ravel().astype(np.int64))
        assert node >= leaves.max()
        # and the bound is tight somewhere: level 0 equals a direct sum over the raster
        full = np.zeros((ras.grid.shape[0] + 200, ras.grid.shape[1] + 200), np.int64)
        full[100:-100, 100:-100] = ras.grid
        sx = cells[0, :, 0] + tx - ras.origin[0] + 100
        sy = cells[0, :, 1] + ty - ras.origin[1] + 100
        ok = (sx >= 0) & (sy >= 0) & (sx < full.shape[0]) & (sy < full.shape[1])
        direct = int(full[sx[ok], sy[ok]].sum())
        assert leaves[0] == direct


def test_assembled_pieces_equal_the_pyramid_of_the_union():
    a = _raster(1, 30, 20, 0.2)
    b = _raster(2, 25, 35, 0.2)
    b.origin = a.origin + np.array([10, -7])
    lo = np.minimum(a.origin, b.origin)
    hi = np.maximum(a.origin + a.grid.shape, b.origin + b.grid.shape)
    union = np.zeros(tuple(hi - lo), np.uint8)
    for r in (a, b):
        o = r.origin - lo
        sl = union[o[0]:o[0] + r.grid.shape[0], o[1]:o[1] + r.grid.shape[1]]
        np.maximum(sl, r.grid, out=sl)
    whole = build_pyramid(Raster(lo, union, 0.25, lo, union.astype(np.float32)), 4)
    q_lo, q_hi = lo - 9, hi + 2
    got = assemble([build_pyramid(a, 4), build_pyramid(b, 4)], q_lo, q_hi)
    want = assemble([whole], q_lo, q_hi)
    np.testing.assert_array_equal(got.levels, want.levels)
    assert got.levels[3].max() > 0


def test_node_scores_inside_and_across_the_crop_edge_are_the_direct_sums():
    # Nodes whose scan cells all lie in the crop are summed unchecked (``_kernels._node_score``),
    # the others cell by cell: every translation over and around the crop, both ways, must give
    # the direct sum (0 outside the crop).
    rng = np.random.default_rng(3)
    ras = _raster(3, 24, 17, 0.3)
    pyr = build_pyramid(ras, 3)
    cells = rng.integers(-6, 6, (4, 30, 2))  # 4 "angles" of 30 cells
    dx = (cells[..., 0] - pyr.origin[0]).astype(np.int32)
    dy = (cells[..., 1] - pyr.origin[1]).astype(np.int32)
    lin, box = K.scan_offsets(dx, dy, pyr.levels.shape[2])
    assert np.array_equal(box, np.stack([dx.min(1), dx.max(1), dy.min(1), dy.max(1)], 1))
    nx, ny = pyr.levels.shape[1:]
    gx, gy = np.meshgrid(np.arange(-12, nx + 12), np.arange(-12, ny + 12), indexing="ij")
    n = gx.size
    for a in range(4):
        tx = (gx.ravel() + pyr.origin[0]).astype(np.int64)
        ty = (gy.ravel() + pyr.origin[1]).astype(np.int64)
        ra = np.full(n, a, np.int64)
        for h in range(3):
            got = K.root_scores(pyr.levels, h, dx, dy, lin, box, ra, tx, ty)
            i = dx[a][None, :] + tx[:, None]
            j = dy[a][None, :] + ty[:, None]
            ok = (i >= 0) & (j >= 0) & (i < nx) & (j < ny)
            direct = np.where(ok, pyr.levels[h][np.clip(i, 0, nx - 1), np.clip(j, 0, ny - 1)], 0).sum(axis=1)
            assert np.array_equal(got, direct)
            assert np.array_equal(K.node_scores(pyr.levels, h, dx, dy, ra, tx, ty), direct)
