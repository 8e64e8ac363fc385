"""Per-entry pyramids are cached on disk (keyed by the entry's sha256) and assemble like one raster."""

import numpy as np

from blockloc.global_init.maps import ArrayMap, ProjectionParams, StoreMap
from blockloc.maps.store import open_map

from .synthetic import GRAVITY_Z_DOWN, Z_DOWN, grid_store, world_up


def test_cached_pyramids_are_reused_and_match_the_whole_map(tmp_path, monkeypatch):
    pts = (world_up(seed=21, size=80.0) @ Z_DOWN.T).astype(np.float32).astype(np.float64)
    store = grid_store(tmp_path / "map", pts)
    params = ProjectionParams()
    first = StoreMap(store, GRAVITY_Z_DOWN, params, cache_dir=tmp_path / "cache")
    assert first.precompute() == len(store.entries) > 1
    files = sorted((tmp_path / "cache").rglob("*.npz"))
    assert len(files) == len(store.entries)
    # a second map object reads the cache: it never loads points to build pyramids
    second = StoreMap(open_map(tmp_path / "map"), GRAVITY_Z_DOWN, params, cache_dir=tmp_path / "cache")
    monkeypatch.setattr(second.store, "load", lambda *a, **k: (_ for _ in ()).throw(AssertionError("loaded")))
    lo, hi = np.array([-60, -60]), np.array([60, 60])
    got = second.pyramid(lo, hi)
    assert got.levels[0].max() == 255
    # Tiles compose into the same base raster as the whole map, away from tile edges where each
    # tile's local ground is estimated from its own points.
    whole = ArrayMap(pts, GRAVITY_Z_DOWN, params).pyramid(lo, hi)
    agree = np.mean(got.levels[0] == whole.levels[0])
    assert agree > 0.97, agree
    top = params.num_levels - 1
    assert np.all(got.levels[top] >= got.levels[top - 1])
    # the lowest levels alone (a search whose roots start lower): the same arrays
    for m in (second, ArrayMap(pts, GRAVITY_Z_DOWN, params)):
        low = m.pyramid(lo, hi, 3)
        full = m.pyramid(lo, hi)
        assert low.num_levels == 3 and np.array_equal(low.levels, full.levels[:3])
        assert np.array_equal(low.origin, full.origin)


def test_box_queries_return_exactly_the_points_in_the_box():
    # Buckets wholly inside the box skip the point test; the result must equal a brute-force mask,
    # for boxes on and off bucket edges, in a levelled frame turned against the map frame.
    from blockloc.global_init.maps import BUCKET_M, _BucketedPoints

    rng = np.random.default_rng(5)
    pts = rng.uniform([-130, -90, -3], [170, 110, 8], (60_000, 3)).astype(np.float32)
    c, s = np.cos(0.4), np.sin(0.4)
    R_L_map = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    b = _BucketedPoints(pts, R_L_map)
    xy = pts.astype(np.float64) @ R_L_map[:2].T
    boxes = [(np.array([-40.0, -20.0]), np.array([60.0, 80.0])), (np.array([0.0, 0.0]), np.array([2 * BUCKET_M] * 2)),
             (np.array([-3.0, 7.0]), np.array([4.0, 9.0])), (np.array([-500.0, -500.0]), np.array([500.0, 500.0])),
             (np.array([300.0, 300.0]), np.array([400.0, 400.0]))]
    for lo, hi in boxes:
        want = pts[np.all((xy >= lo) & (xy <= hi), axis=1)]
        got = b.in_box(lo, hi)
        assert len(got) == len(want)
        key = lambda a: a[np.lexsort(a.T)]
        np.testing.assert_array_equal(key(got), key(want))


def test_entry_points_are_memory_mapped_from_the_cache_and_box_queries_match(tmp_path, monkeypatch):
    # The first map object writes each entry's sorted points; a second maps them (no PCD decode,
    # nothing held in memory) and its box queries return exactly the points of a fresh decode.
    pts = (world_up(seed=22, size=80.0) @ Z_DOWN.T).astype(np.float32).astype(np.float64)
    store = grid_store(tmp_path / "map", pts)
    first = StoreMap(store, GRAVITY_Z_DOWN, ProjectionParams(), cache_dir=tmp_path / "cache")
    first.precompute(points=True)
    second = StoreMap(open_map(tmp_path / "map"), GRAVITY_Z_DOWN, ProjectionParams(), cache_dir=tmp_path / "cache")
    monkeypatch.setattr(second.store, "load", lambda *a, **k: (_ for _ in ()).throw(AssertionError("loaded")))
    lo, hi = np.array([-25.0, -12.0]), np.array([18.0, 30.0])
    got = second.points_in_box(lo, hi)
    assert all(isinstance(e.points, np.memmap) and e.resident == 0 for e in second._points.values())
    xy = pts @ second.R_L_map[:2].T
    want = pts[np.all((xy >= lo) & (xy <= hi), axis=1)]
    assert len(got) == len(want) > 100
    key = lambda a: a[np.lexsort(a.T)]
    np.testing.assert_array_equal(key(got), key(want))
    # a points file cut short is not trusted: the entry is decoded again
    victim = next((tmp_path / "cache").rglob("*.points.npy"))
    victim.write_bytes(victim.read_bytes()[:-120])
    third = StoreMap(open_map(tmp_path / "map"), GRAVITY_Z_DOWN, ProjectionParams(), cache_dir=tmp_path / "cache")
    np.testing.assert_array_equal(key(third.points_in_box(lo, hi)), key(want))


def test_a_cut_short_or_empty_cache_file_is_rebuilt_not_raised(tmp_path, caplog):
    # an npz cut short (a full disk, a copy stopped) is not a zip archive, and an empty file (a
    # power loss after the rename) ends too soon: raised as zipfile.BadZipFile or EOFError past the
    # callers' `except ValueError`, they stopped the search
    pts = world_up(seed=21, size=60.0).astype(np.float32).astype(np.float64)
    store = grid_store(tmp_path / "map", pts)
    first = StoreMap(store, -GRAVITY_Z_DOWN, ProjectionParams(), cache_dir=tmp_path / "cache")
    first.precompute(points=True)
    files = sorted((tmp_path / "cache").rglob("*.np[yz]"))
    lo, hi = np.array([-200, -200]), np.array([200, 200])  # cells: the whole map
    box = (np.array([-100.0, -100.0]), np.array([100.0, 100.0]))
    want, want_points = first.pyramid(lo, hi).levels, first.points_in_box(*box)
    assert len(files) > 4 and len(want_points) == len(pts)
    for k, f in enumerate(files):
        f.write_bytes(f.read_bytes()[: len(f.read_bytes()) // 2] if k % 2 else b"")
    second = StoreMap(open_map(tmp_path / "map"), -GRAVITY_Z_DOWN, ProjectionParams(), cache_dir=tmp_path / "cache")
    with caplog.at_level("WARNING"):
        got, got_points = second.pyramid(lo, hi).levels, second.points_in_box(*box)
    assert np.array_equal(got, want)
    assert sorted(map(tuple, got_points)) == sorted(map(tuple, want_points))
    assert sum("ignoring unreadable cache" in r.getMessage() for r in caplog.records) >= len(files) // 2
    third = StoreMap(open_map(tmp_path / "map"), -GRAVITY_Z_DOWN, ProjectionParams(), cache_dir=tmp_path / "cache")
    caplog.clear()
    assert np.array_equal(third.pyramid(lo, hi).levels, want) and len(third.points_in_box(*box)) == len(pts)
    assert not caplog.records  # the rebuilt files replaced the damaged ones
