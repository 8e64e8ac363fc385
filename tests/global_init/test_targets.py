"""Refinement targets assembled from per-entry statistics equal those built from the box's points."""

import numpy as np
import pytest

from blockloc.global_init.maps import StoreMap
from blockloc.global_init.refine import Refiner
from blockloc.global_init.targets import TargetCache, axis_aligned
from blockloc.registration.engines import make_engine

from .synthetic import GRAVITY_Z_DOWN, Z_DOWN, grid_store, world_up


def _sorted_level(target, level):
    snap = target.snapshot(level)
    order = np.argsort(snap.keys)
    return snap.keys[order], snap.counts[order], snap.gauss[order]


def _footprint_cells(fp):
    return {tuple(c) for c in np.argwhere(fp._grid) + fp._lo} if fp._grid is not None else set()


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """The same world stored in 30 m tiles, z-down (levelled y reversed) and z-up."""
    root = tmp_path_factory.mktemp("targets")
    pts_up = world_up(seed=3, size=90.0).astype(np.float32).astype(np.float64)
    down = grid_store(root / "down", pts_up @ Z_DOWN.T)
    up = grid_store(root / "up", pts_up)
    return {"down": StoreMap(down, GRAVITY_Z_DOWN, cache_dir=root / "cache"),
            "up": StoreMap(up, -GRAVITY_Z_DOWN, cache_dir=root / "cache")}


# boxes (levelled frame): across tile edges, half off the map, smaller than a coarse voxel (no core),
# and edges on voxel boundaries
BOXES = [((-20.3, -31.7), (29.9, 18.4)), ((10.0, 10.0), (80.0, 80.0)), ((3.2, -4.1), (4.9, -2.6)),
         ((-30.0, -30.0), (30.0, 30.0)), ((-50.0, -50.0), (50.0, 50.0))]


@pytest.mark.parametrize("frame", ["down", "up"])
def test_assembled_targets_equal_targets_built_from_the_points(maps, frame):
    smap = maps[frame]
    assert axis_aligned(smap.R_L_map)
    engine = make_engine("ndt", resolution_m=1.0)
    cache = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=10**9)
    assert cache.usable(engine, smap, smap.R_L_map)
    for lo, hi in BOXES:
        lo, hi = np.array(lo), np.array(hi)
        pts = smap.points_in_box(lo, hi)
        want = Refiner(engine, pts, smap.R_L_map, 1.0, 0.25)
        got = cache.refiner(smap, lo, hi, min_points=1)
        for level in (0, 1):
            k0, c0, g0 = _sorted_level(want._target, level)
            k1, c1, g1 = _sorted_level(got._target, level)
            np.testing.assert_array_equal(k1, k0)  # the same voxels, the same points in each
            np.testing.assert_array_equal(c1, c0)
            np.testing.assert_allclose(g1, g0, rtol=1e-9, atol=1e-9)  # the same sums, another order
        assert _footprint_cells(got.footprint) == _footprint_cells(want.footprint) != set()
        # the same verdict inputs: inlier ratio of the map's own points at identity
        probe = pts[:: max(1, len(pts) // 2000)]
        assert got.inlier_ratio(probe, np.eye(4)) == want.inlier_ratio(probe, np.eye(4))
    assert cache.misses == len(smap.store.entries) and cache.hits > 0  # each entry built once


def test_the_cache_stays_within_its_budget_and_rebuilds_what_it_dropped(maps):
    smap = maps["down"]
    engine = make_engine("ndt", resolution_m=1.0)
    full = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=10**9)
    full.refiner(smap, np.array([-50.0, -50.0]), np.array([50.0, 50.0]))
    one = max(e.nbytes for e in full._entries.values())
    budget = int(1.5 * one)
    assert full.nbytes > budget  # the box's entries do not all fit
    small = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=budget)
    lo, hi = np.array([-50.0, -50.0]), np.array([50.0, 50.0])
    first = small.refiner(smap, lo, hi)
    assert 0 < small.nbytes <= budget
    n = len(smap.entries_in(lo, hi))
    again = small.refiner(smap, lo, hi)
    assert small.nbytes <= budget and small.misses > n  # dropped entries were built again
    np.testing.assert_array_equal(_sorted_level(again._target, 0)[1], _sorted_level(first._target, 0)[1])
    # an entry larger than a quarter of the budget is refined from its points instead, even when
    # an earlier search asked for it
    big = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=one)
    for _ in range(2):
        big.begin_search()
        assert not big.ready(smap, lo, hi)


def test_a_tilted_levelled_frame_or_another_engine_is_not_assembled(maps):
    smap = maps["down"]
    c, s = np.cos(0.01), np.sin(0.01)
    tilted = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    assert not axis_aligned(tilted)
    assert not TargetCache.usable(make_engine("ndt"), smap, tilted)
    assert not TargetCache.usable(object(), smap, smap.R_L_map)


def test_the_localizer_refines_on_assembled_targets_and_finds_the_same_pose(maps):
    # A first search builds its targets from the points (a one-shot `blockloc init` pays no
    # statistics); the next search keeps the entries the first asked for and assembles its targets:
    # the same verdict, the same pose to rounding, as targets built from the points.
    from blockloc.geometry import xyzrpy_to_T
    from blockloc.global_init.relocalize import GlobalLocalizer, InitParams

    from .synthetic import gravity_body, scan_from

    smap = maps["down"]
    world = smap.points_in_box(*smap.bounds_L())
    T_true = xyzrpy_to_T(6.0, 4.0, -(1.9 + 0.02 * 6.0), 0.03, -0.02, 2.4)
    scan, g = scan_from(world, T_true), gravity_body(T_true)
    loc = GlobalLocalizer(smap, InitParams(use_place_index=False, target_cache_mb=64.0))
    first = loc.localize(scan, g, hint_xy=(8.0, 2.0), window_m=10.0)
    assert loc.target_cache.misses == 0 and len(loc.target_cache) == 0  # one-shot: nothing kept
    second = loc.localize(scan, g, hint_xy=(8.0, 2.0), window_m=10.0)
    assert loc.target_cache.misses > 0 and len(loc.target_cache) > 0
    off = GlobalLocalizer(smap, InitParams(use_place_index=False, target_cache_mb=0.0))
    assert off.target_cache is None
    base = off.localize(scan, g, hint_xy=(8.0, 2.0), window_m=10.0)
    for res in (first, second):
        assert res.verified and base.verified and res.ambiguous == base.ambiguous
        np.testing.assert_allclose(res.T_map_body, base.T_map_body, atol=1e-6)
        assert res.fitness == pytest.approx(base.fitness, abs=1e-9)


def test_a_precomputed_map_is_searched_on_statistics_read_from_disk_with_the_same_result(maps, tmp_path):
    # `GlobalLocalizer.precompute` leaves every entry's statistics in the cache; a later process's
    # second search reads them (builds none) and finds the pose a localizer without them finds
    from blockloc.geometry import xyzrpy_to_T
    from blockloc.global_init.relocalize import GlobalLocalizer, InitParams

    from .synthetic import gravity_body, scan_from

    smap = maps["down"]
    store = smap.store
    params = dict(use_place_index=False, target_cache_mb=64.0)
    ahead = GlobalLocalizer(StoreMap(store, smap.gravity_map, cache_dir=tmp_path), InitParams(**params))
    assert ahead.precompute() == (len(store.entries), len(store.entries))
    assert len(list(ahead.target_cache.disk_dir.glob("*.npz"))) == len(store.entries)
    assert len(ahead.target_cache) == 0  # written, not held
    # entries too big for the cache's budget are refined from their points (`ready`): none written
    tiny = GlobalLocalizer(StoreMap(store, smap.gravity_map, cache_dir=tmp_path / "tiny"),
                           InitParams(use_place_index=False, target_cache_mb=0.01))
    assert tiny.precompute() == (len(store.entries), 0)
    assert not list(tiny.target_cache.disk_dir.parent.glob("targets-*/*.npz"))

    world = smap.points_in_box(*smap.bounds_L())
    T_true = xyzrpy_to_T(-5.0, 7.0, -(1.9 + 0.02 * -5.0), 0.02, 0.03, -1.1)
    scan, g = scan_from(world, T_true), gravity_body(T_true)
    loc = GlobalLocalizer(StoreMap(store, smap.gravity_map, cache_dir=tmp_path), InitParams(**params))
    loc.target_cache._build = None  # any build would raise
    loc.localize(scan, g, hint_xy=(-3.0, 5.0), window_m=10.0)
    res = loc.localize(scan, g, hint_xy=(-3.0, 5.0), window_m=10.0)
    assert loc.target_cache.misses > 0 and loc.target_cache.loaded == loc.target_cache.misses
    base = GlobalLocalizer(smap, InitParams(use_place_index=False, target_cache_mb=0.0)).localize(
        scan, g, hint_xy=(-3.0, 5.0), window_m=10.0)
    assert res.verified and base.verified
    np.testing.assert_allclose(res.T_map_body, base.T_map_body, atol=1e-6)
    assert res.fitness == pytest.approx(base.fitness, abs=1e-9)


def test_refinements_side_by_side_give_the_same_candidates_in_the_same_order(maps, monkeypatch):
    # ``refine_workers`` 2: the targets are built and the candidates refined in threads; the
    # candidates, their order and the early stop (a candidate scoring below the ratio is refined only
    # while nothing before it is verified) are those of one thread, on targets built from the points
    # (the first search) and assembled from the kept statistics (the second).
    import math
    import threading

    from blockloc.geometry import xyzrpy_to_T
    from blockloc.global_init.bnb import Candidate2D
    from blockloc.global_init.relocalize import GlobalLocalizer, InitParams

    from .synthetic import gravity_body, scan_from

    smap = maps["down"]
    world = smap.points_in_box(*smap.bounds_L())
    T_true = xyzrpy_to_T(6.0, 4.0, -(1.9 + 0.02 * 6.0), 0.03, -0.02, 2.4)
    body, g = scan_from(world, T_true), gravity_body(T_true)
    runs = {}
    for workers in (1, 2):
        loc = GlobalLocalizer(smap, InitParams(use_place_index=False, target_cache_mb=64.0, refine_workers=workers))
        threads = set()
        align = loc.engine.align

        def spy(*a, _align=align, _threads=threads):
            _threads.add(threading.current_thread().name)
            return _align(*a)

        monkeypatch.setattr(loc.engine, "align", spy)
        scan, scan_ndt = loc.prepare_scan(body, g)
        cells = loc._scan_cells(body, g)
        xy = (loc.map.R_L_map @ T_true[:3, 3])[:2]
        th = loc._theta_from_yaw(2.4, scan)
        scan_ndt0 = scan_ndt
        # the truth, two starts near it, one 40 m away (another target), one below 0.8 x the best
        c2d = [Candidate2D(xy[0] + 0.8, xy[1] - 0.5, th + 0.05, 0.85), Candidate2D(xy[0], xy[1], th, 0.9),
               Candidate2D(xy[0] - 40.0, xy[1] + 3.0, th + 1.0, 0.8), Candidate2D(xy[0] + 2.0, xy[1], th, 0.3),
               Candidate2D(xy[0] - 1.0, xy[1] + 1.0, th - 0.1, 0.75)]
        runs[workers] = []
        for _ in range(2):  # from the points, then assembled from the kept statistics
            loc.target_cache.begin_search()
            scan, scan_ndt = loc.prepare_scan(body, g)  # a new search: its own targets
            np.testing.assert_array_equal(scan_ndt, scan_ndt0)
            runs[workers].append(loc._refine(c2d, scan, scan_ndt, cells))
        assert len(loc.target_cache) > 0
        if workers == 1:
            assert threads == {threading.current_thread().name}
        else:
            assert any(n.startswith("blockloc-refine") for n in threads), threads
    for one, two in zip(runs[1], runs[2]):
        assert len(one) == len(two) == 4  # the 0.3 leaf: not refined, the best was verified
        assert one[0].verified and math.isclose(one[0].score, 0.9)
        for a, b in zip(one, two):
            assert (a.score, a.verified, a.converged) == (b.score, b.verified, b.converged)
            np.testing.assert_array_equal(a.T_map_body, b.T_map_body)
            assert (a.fitness, a.ndt_score, a.structure_fitness, a.overlap) == (b.fitness, b.ndt_score,
                                                                               b.structure_fitness, b.overlap)
            np.testing.assert_equal((a.coverage, a.see_through), (b.coverage, b.see_through))


def test_a_later_stage_reuses_the_targets_of_the_same_scan_and_a_new_scan_builds_its_own(maps, monkeypatch):
    # The place stages call ``_refine`` once each: a candidate of a later stage within half the
    # refinement range of an earlier stage's target refines on it (no second assembly of the same
    # map); ``prepare_scan`` (a new search) starts the list again.
    from blockloc.geometry import xyzrpy_to_T
    from blockloc.global_init.bnb import Candidate2D
    from blockloc.global_init.relocalize import GlobalLocalizer, InitParams

    from .synthetic import gravity_body, scan_from

    smap = maps["down"]
    world = smap.points_in_box(*smap.bounds_L())
    T_true = xyzrpy_to_T(6.0, 4.0, -(1.9 + 0.02 * 6.0), 0.03, -0.02, 2.4)
    body, g = scan_from(world, T_true), gravity_body(T_true)
    loc = GlobalLocalizer(smap, InitParams(use_place_index=False, target_cache_mb=0.0, refine_workers=1))
    built = []
    over = loc._refiner_over
    monkeypatch.setattr(loc, "_refiner_over", lambda xy, d, cached=None: built.append(xy.copy()) or over(xy, d, cached))
    scan, scan_ndt = loc.prepare_scan(body, g)
    cells = loc._scan_cells(body, g)
    xy = (loc.map.R_L_map @ T_true[:3, 3])[:2]
    th = loc._theta_from_yaw(2.4, scan)
    first = loc._refine([Candidate2D(xy[0], xy[1], th, 0.9)], scan, scan_ndt, cells)
    assert len(built) == 1 and first[0].verified
    # the next stage: one candidate 10 m off (the same target), one 40 m off (a target of its own)
    later = loc._refine([Candidate2D(xy[0] + 10.0, xy[1], th, 0.9), Candidate2D(xy[0] - 40.0, xy[1], th, 0.9)],
                        scan, scan_ndt, cells, ordered=True)
    assert len(later) == 2 and len(built) == 2
    assert later[0].refiner is first[0].refiner and later[1].refiner is not first[0].refiner
    scan, scan_ndt = loc.prepare_scan(body, g)
    again = loc._refine([Candidate2D(xy[0], xy[1], th, 0.9)], scan, scan_ndt, cells)
    assert len(built) == 3 and again[0].refiner is not first[0].refiner
    np.testing.assert_array_equal(again[0].T_map_body, first[0].T_map_body)


def test_entry_statistics_kept_on_disk_are_read_back_by_a_later_process_and_give_the_same_targets(
        maps, tmp_path, caplog):
    smap = maps["up"]
    assert all(smap.entry_sha256(i) for i in range(len(smap.store.entries)))
    engine = make_engine("ndt", resolution_m=1.0)
    lo, hi = np.array([-20.3, -31.7]), np.array([29.9, 18.4])
    n = len(smap.entries_in(lo, hi))
    first = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=10**9, disk_dir=tmp_path)
    built = first.refiner(smap, lo, hi)
    first.flush()  # written by the background writer
    files = sorted(first.disk_dir.glob("*.npz"))
    assert first.loaded == 0 and len(files) == n  # built, then written once each

    # a later process: reads every entry, builds none, and assembles the same target and footprint
    later = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=10**9, disk_dir=tmp_path)
    calls = []
    later._build = lambda pts: calls.append(len(pts))  # noqa: E731 - any build is a failure here
    read = later.refiner(smap, lo, hi)
    assert later.loaded == n and calls == []
    for level in (0, 1):
        for a, b in zip(_sorted_level(read._target, level), _sorted_level(built._target, level)):
            np.testing.assert_array_equal(a, b)
    assert _footprint_cells(read.footprint) == _footprint_cells(built.footprint) != set()

    # another footprint cell or another voxel size keys other files: nothing of these is read
    other = TargetCache(make_engine("ndt", resolution_m=2.0), smap.R_L_map, 1.0, 0.25, max_bytes=10**9,
                        disk_dir=tmp_path)
    other.refiner(smap, lo, hi)
    other.flush()
    assert other.loaded == 0 and other.disk_dir != first.disk_dir

    # a damaged file is rebuilt (one warning naming it) and replaced
    files[0].write_bytes(files[0].read_bytes()[:1000])
    again = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=10**9, disk_dir=tmp_path)
    with caplog.at_level("WARNING"):
        again.refiner(smap, lo, hi)
        again.flush()
    assert again.loaded == n - 1 and any(files[0].name in r.getMessage() for r in caplog.records)
    assert TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=10**9, disk_dir=tmp_path)._read(files[0]).nbytes > 0

    # a file whose arrays do not make one entry (here: the statistics left out) is not read
    import io

    from blockloc.fileio import load_arrays

    arrays = {k: v for k, v in load_arrays(files[1]).items() if not k.startswith("stats_")}
    buf = io.BytesIO()
    np.savez(buf, **dict(arrays, has_stats=np.array(False)))
    files[1].write_bytes(buf.getvalue())
    with pytest.raises(ValueError, match="not one entry"):
        again._read(files[1])

    # the files of other code with the same settings, not written to for a day, are removed when new
    # ones are written, with temp files a killed writer left; a newer one, or another file, is kept
    import os
    import time

    stale = first.disk_dir.parent / f"targets-{first._settings_key}-0000000000"
    recent = first.disk_dir.parent / f"targets-{first._settings_key}-1111111111"
    for d in (stale, recent):
        d.mkdir()
        (d / "x.npz").write_bytes(b"old")
    left = first.disk_dir / ".x.npz.abc.tmp"
    left.write_bytes(b"part")
    day_ago = time.time() - 2 * 86400
    for p in (stale, left):
        os.utime(p, (day_ago, day_ago))
    unrelated = tmp_path / "points-b25-mm-gx"
    unrelated.mkdir()
    for f in first.disk_dir.glob("*.npz"):
        f.unlink()
    last = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=10**9, disk_dir=tmp_path)
    last.refiner(smap, lo, hi)
    last.flush()
    assert not stale.exists() and not left.exists()
    assert recent.exists() and unrelated.exists() and other.disk_dir.exists()


def test_tile_statistics_of_the_wrong_shape_are_refused():
    from blockloc.registration.ndt import TileStats

    engine = make_engine("ndt", resolution_m=1.0)
    pts = world_up(seed=1, size=20.0)
    arrays = engine.tile_stats(pts).to_arrays()
    back = engine.tile_stats_from_arrays(arrays)
    assert back.num_points == len(pts) and len(back.levels) == 2
    with pytest.raises(ValueError, match="levels"):
        TileStats.from_arrays(arrays, 1)  # a file of a coarser pyramid
    bad = dict(arrays, l0_icov=arrays["l0_icov"][:, :3])
    with pytest.raises(ValueError, match="icov"):
        engine.tile_stats_from_arrays(bad)
    with pytest.raises(KeyError):
        engine.tile_stats_from_arrays({k: v for k, v in arrays.items() if k != "l1_means"})


def test_a_cache_that_cannot_be_written_costs_time_and_one_warning(maps, tmp_path, caplog):
    smap = maps["up"]
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    engine = make_engine("ndt", resolution_m=1.0)
    cache = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=10**9, disk_dir=blocked)
    lo, hi = np.array([-50.0, -50.0]), np.array([50.0, 50.0])
    with caplog.at_level("WARNING"):
        got = cache.refiner(smap, lo, hi)
        cache.flush()
    want = TargetCache(engine, smap.R_L_map, 1.0, 0.25, max_bytes=10**9).refiner(smap, lo, hi)
    np.testing.assert_array_equal(_sorted_level(got._target, 0)[1], _sorted_level(want._target, 0)[1])
    assert cache.misses > 1 and [r.getMessage().startswith("cannot write") for r in caplog.records] == [True]
