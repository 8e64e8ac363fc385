"""Grid-puzzle tiles: tiling invariants (property tests), names, Autoware metadata, windows."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from blockloc.errors import MapError
from blockloc.maps.grid_tiles import (SECTOR_NAMES, cell_of, grid_window, heading_sector,
                                      name_decimals, parse_tile_name, split_into_tiles, tile_bounds,
                                      tile_global_map, tile_name, tile_pcd_file)
from blockloc.maps.pcd import write_pcd
from blockloc.maps.store import open_map

coords = st.floats(-1e4, 1e4, allow_nan=False, width=32)
tile_sizes = st.sampled_from([0.25, 1.0, 2.0, 3.0, 7.5, 20.0, 100.0])


@settings(max_examples=60, deadline=None)
@given(pts=arrays(np.float32, st.tuples(st.integers(1, 300), st.just(3)), elements=coords),
       s=tile_sizes)
def test_every_point_in_exactly_one_tile_and_names_invert(pts, s):
    groups = split_into_tiles(pts, s)
    all_idx = np.concatenate(list(groups.values()))
    assert np.array_equal(np.sort(all_idx), np.arange(len(pts)))  # a partition: no loss, no dup
    for (ix, iy), idx in groups.items():
        name = tile_name(ix, iy, s)
        assert parse_tile_name(name + ".pcd", s) == (ix, iy)
        lo, hi = tile_bounds(name, s)
        xy = pts[idx, :2].astype(np.float64)
        assert np.all(xy >= lo) and np.all(xy < hi), (name, xy, lo, hi)
        cx, cy = (float(v) for v in name.split("_"))
        assert np.allclose([cx, cy], (lo + hi) / 2)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(pts=arrays(np.float32, st.tuples(st.integers(1, 200), st.just(3)),
                  elements=st.floats(-50, 50, width=32)),
       s=st.sampled_from([2.0, 5.0, 12.5]))
def test_union_of_tiles_is_the_input(tmp_path_factory, pts, s):
    out = tmp_path_factory.mktemp("tiles") / "g"
    inten = np.arange(len(pts), dtype=np.float32)
    store = tile_global_map(pts, inten, s, out)
    got_p, got_i = [], []
    for e in store.entries:
        p, i = store.load(e.id)
        lo, hi = tile_bounds(e.id, s)
        assert np.all(p[:, :2] >= lo) and np.all(p[:, :2] < hi)
        got_p.append(p)
        got_i.append(i)
    got_p, got_i = np.concatenate(got_p), np.concatenate(got_i)
    order = np.argsort(got_i)  # intensities are the input row numbers
    np.testing.assert_array_equal(got_i[order], inten)
    np.testing.assert_array_equal(got_p[order], pts)
    # payload equal: tiles hold exactly 16 bytes per point, like the input
    assert store.total_points == len(pts)


def test_names_fixed_decimals_and_negative():
    assert tile_name(-2, 1, 2.0) == "-3.0_3.0"
    assert tile_name(0, -1, 0.25) == "0.125_-0.125"
    assert name_decimals(20.0) == 1 and name_decimals(0.5) == 2
    assert parse_tile_name("-3.0_3.0.pcd", 2.0) == (-2, 1)
    with pytest.raises(MapError, match="not the centre"):
        parse_tile_name("-2.0_3.0", 2.0)
    with pytest.raises(MapError, match="centre coordinates"):
        parse_tile_name("abc.pcd", 2.0)


def test_cell_borders_exact():
    s = 0.1
    xs = np.array([0.3, -0.3, 0.7, 1e3 * 0.1, -0.0, 2.9999999999], np.float64)
    cells = cell_of(np.c_[xs, xs], s)
    assert np.all(cells[:, 0] * s <= xs) and np.all(xs < (cells[:, 0] + 1) * s)


@pytest.mark.parametrize("bad", [0, -2.0, float("nan"), float("inf"), "x"])
def test_bad_tile_size(tmp_path, bad):
    with pytest.raises(MapError, match="tile size"):
        tile_global_map(np.zeros((3, 3)), None, bad, tmp_path / "g")
    assert not (tmp_path / "g").exists()


def test_tile_pcd_file_and_autoware_metadata(tmp_path):
    import yaml

    rng = np.random.default_rng(3)
    pts = rng.uniform(-4, 6, (1000, 3)).astype(np.float32)  # cells -2..2
    write_pcd(tmp_path / "global.pcd", pts, rng.uniform(0, 1, 1000))
    store = tile_pcd_file(tmp_path / "global.pcd", 2.0, tmp_path / "tiles")
    assert store.kind == "grid" and len(store.entries) == 25
    assert store.total_points == 1000
    meta = yaml.safe_load((tmp_path / "tiles" / "pointcloud_map_metadata.yaml").read_text())
    assert meta.pop("x_resolution") == 2.0 and meta.pop("y_resolution") == 2.0
    assert len(meta) == 25
    for fname, (x0, y0) in meta.items():
        lo, _ = tile_bounds(fname, 2.0)
        assert (x0, y0) == tuple(lo)
        assert (tmp_path / "tiles" / fname).exists()
    # payload bytes equal: every tile file is the 16-byte point payload plus its header
    again = open_map(tmp_path / "tiles")
    assert again.params["tile_size_m"] == 2.0
    (tmp_path / "empty.pcd").write_bytes(
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\nHEIGHT 1\n"
        b"POINTS 0\nDATA binary\n")
    with pytest.raises(MapError, match="no points"):
        tile_pcd_file(tmp_path / "empty.pcd", 2.0, tmp_path / "t2")


@pytest.mark.parametrize("sector", range(8))
def test_grid_window_each_sector(sector):
    n, k = 1, 2
    cells = set(grid_window(10, 20, n, k, sector))
    base = {(x, y) for x in range(9, 12) for y in range(19, 22)}
    assert base <= cells
    dx, dy = [(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1)][sector]
    xs = sorted({x for x, _ in cells})
    ys = sorted({y for _, y in cells})
    assert (xs[0], xs[-1]) == (9 - (k if dx < 0 else 0), 11 + (k if dx > 0 else 0))
    assert (ys[0], ys[-1]) == (19 - (k if dy < 0 else 0), 21 + (k if dy > 0 else 0))
    expected = (3 + k * abs(dx)) * (3 + k * abs(dy))
    assert len(cells) == expected
    # the heading that picks this sector
    a = sector * np.pi / 4 + 0.3
    assert heading_sector(np.array([np.cos(a), np.sin(a), 0.0])) == sector
    assert SECTOR_NAMES[sector]


def test_heading_sector_slow_or_missing():
    assert heading_sector(None) is None
    assert heading_sector(np.array([0.01, 0.0, 3.0])) is None
    assert set(grid_window(0, 0, 2, 3, None)) == {(x, y) for x in range(-2, 3) for y in range(-2, 3)}
    with pytest.raises(MapError):
        grid_window(0, 0, -1, 0, None)
