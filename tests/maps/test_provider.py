"""The map provider: policies, hysteresis, switch reporting, prefetch, LRU bound, bad tiles."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from blockloc.config import MapConfig
from blockloc.errors import MapError
from blockloc.maps.grid_tiles import tile_global_map
from blockloc.maps.policies import BlockPolicy, GridPolicy, SrtPolicy, make_policy
from blockloc.maps.provider import MapProvider as _MapProvider
from blockloc.maps.store import MapWriter

_PROVIDER_KEYS = {"prefetch", "lookahead_s", "min_lookahead_m", "cache_mb", "max_spare_regions", "retry_missing_s"}


class FakeEngine:
    """A registration engine made of target builders (the provider only builds and updates targets)."""

    def __init__(self, build=None, build_tiles=None):
        self.build, self.build_tiles = build, build_tiles
        self.incremental = build_tiles is not None

    def build_target(self, points):
        return self.build(points)

    def build_tiled_target(self, tiles):
        return self.build_tiles(tiles)

    def update_tiles(self, target, add, remove):
        for key in remove:
            target.remove_tile(key)
        for key, pts in add.items():
            target.add_tile(key, pts)
        return target


def MapProvider(store, backend, *, target_builder=None, tiles_target_builder=None, hysteresis_m=None, **kw):
    """The provider with ``backend``'s policy and an engine of the given builders."""
    policy_kw = {k: v for k, v in kw.items() if k not in _PROVIDER_KEYS}
    if hysteresis_m is not None:
        policy_kw["switch_hysteresis_m"] = hysteresis_m
    engine = None if target_builder is None and tiles_target_builder is None else FakeEngine(
        target_builder, tiles_target_builder)
    return _MapProvider(store, make_policy(backend, store, **policy_kw), engine=engine,
                        **{k: v for k, v in kw.items() if k in _PROVIDER_KEYS})


def _block_store(path, centres, n=2000, seed=0):
    rng = np.random.default_rng(seed)
    with MapWriter(path, "block", params={"block_size_m": 50.0}) as w:
        for i, c in enumerate(centres):
            pts = np.asarray(c, float) + rng.uniform(-20, 20, (n, 3)) * [1, 1, 0.1]
            w.add(f"{i:03d}", pts, centroid=np.asarray(c, float))
        return w.commit()


def _grid_store(path, extent=100.0, tile=10.0, per_tile=400, seed=0):
    rng = np.random.default_rng(seed)
    n = int((extent / tile) ** 2 * per_tile)
    pts = np.c_[rng.uniform(0, extent, (n, 2)), rng.uniform(0, 3, n)].astype(np.float32)
    return tile_global_map(pts, None, tile, path)


class CountingBuilder:
    def __init__(self):
        self.calls = 0
        self.threads = set()

    def __call__(self, points):
        self.calls += 1
        self.threads.add(threading.current_thread().name)
        return {"n": len(points), "call": self.calls}


def _drive(provider, xs, y=0.0, vx=1.0, dt=1.0, wait=True):
    out = []
    for k, x in enumerate(xs):
        out.append(provider.update(np.array([x, y, 0.0]), np.array([vx, 0.0, 0.0]), 100.0 + k * dt))
        if wait:
            provider.wait_idle()
    return out


def test_block_policy_hysteresis_no_flip_flop():
    pol = BlockPolicy(["a", "b"], np.array([[0, 0, 0], [100, 0, 0]]), hysteresis_m=6.0)
    # wander around the bisector x = 50 within +-2.9 m: never switches once on "a"
    seq = [10, 45, 52.9, 47.1, 52.9, 47.1, 52.9]
    got = [pol.select(np.array([x, 0, 0]), None, 0)[0] for x in seq]
    assert got == ["a"] * len(seq)
    assert pol.select(np.array([53.1, 0, 0]), None, 0) == ("b",)
    assert [pol.select(np.array([x, 0, 0]), None, 0)[0] for x in (50, 47.1, 52)] == ["b"] * 3
    assert pol.select(np.array([46.9, 0, 0]), None, 0) == ("a",)


def test_block_policy_follows_the_blocks_keyframes_not_their_centroids():
    # block "a" was mapped along y = 0 from x = 0 to 100, block "b" along the parallel street
    # y = 40 but holds a big square whose points pull its centroid to (60, 10). A robot on
    # y = 0 at x = 60 is covered by "a" (its keyframes pass 0 m away) although b's centroid is
    # nearer (10 m vs 10 m from a's (50, 0)... and after the shift 60 m vs 0 m).
    centroids = np.array([[10.0, 0, 0], [60.0, 5.0, 0]])
    kf_a = np.c_[np.arange(0, 101, 5.0), np.zeros(21), np.zeros(21)]
    kf_b = np.c_[np.arange(0, 101, 5.0), np.full(21, 40.0), np.zeros(21)]
    by_centroid = BlockPolicy(["a", "b"], centroids, hysteresis_m=2.0)
    by_keyframes = BlockPolicy(["a", "b"], centroids, hysteresis_m=2.0, keyframes=[kf_a, kf_b])
    robot = np.array([60.0, 0.0, 0.0])
    assert by_centroid.select(robot, None, 0) == ("b",)
    assert by_keyframes.select(robot, None, 0) == ("a",)
    # crossing to the other street switches once past the hysteresis, and not before
    assert by_keyframes.select(np.array([60.0, 20.9, 0]), None, 0) == ("a",)
    assert by_keyframes.select(np.array([60.0, 21.5, 0]), None, 0) == ("b",)
    assert by_keyframes.select(np.array([60.0, 19.5, 0]), None, 0) == ("b",)
    # a block without keyframes falls back to its centroid
    mixed = BlockPolicy(["a", "b"], centroids, hysteresis_m=2.0, keyframes=[kf_a, None])
    assert mixed.select(np.array([60.0, 4.0, 0]), None, 0) == ("b",)


def test_block_policy_blend_serves_the_next_block_near_the_end_of_a_drive():
    # two drives along x: block a's keyframes 0..50 m, block b's 50..100 m (b starts where a ends)
    kf_a = np.c_[np.arange(0, 51, 1.0), np.zeros((51, 2))]
    kf_b = np.c_[np.arange(50, 101, 1.0), np.zeros((51, 2))]
    cents = np.array([[25.0, 0, 0], [75.0, 0, 0]])
    single = BlockPolicy(["a", "b"], cents, hysteresis_m=5.0, keyframes=[kf_a, kf_b])
    blend = BlockPolicy(["a", "b"], cents, hysteresis_m=5.0, keyframes=[kf_a, kf_b], blend_m=10.0)
    seen = {}
    for x in np.arange(0, 101, 1.0):
        p = np.array([x, 0.0, 0.0])
        seen[x] = (single.select(p, None, 0.0), blend.select(p, None, 0.0), blend.primary)
        assert seen[x][2] == single.primary  # blending never changes which block the robot is in
    assert seen[30.0][1] == ("a",) and seen[95.0][1] == ("b",)  # far from the other drive: one block
    assert seen[45.0][1] == ("a", "b") and seen[45.0][0] == ("a",)  # 5 m before a ends: both
    assert seen[58.0][1] == ("a", "b") and seen[58.0][0] == ("b",)  # past the switch, a still near
    # the blended region holds the primary block at every position, and at most two blocks
    assert all(v[2] in v[1] and len(v[1]) <= 2 for v in seen.values())
    with pytest.raises(MapError, match="blend"):
        BlockPolicy(["a"], cents[:1], blend_m=-1.0)


def test_blended_block_provider_reports_one_switch_per_border(tmp_path):
    store = _block_store(tmp_path / "m", [[0, 0, 0], [60, 0, 0], [120, 0, 0]])
    with MapProvider(store, "block", target_builder=CountingBuilder(), hysteresis_m=4.0,
                     block_blend_m=0.0) as prov:
        single = _drive(prov, np.arange(0, 125, 1.0))
    # centroid-only blocks: blending adds the other block while its centroid is within blend_m
    with MapProvider(store, "block", target_builder=CountingBuilder(), hysteresis_m=4.0,
                     block_blend_m=35.0) as prov:
        maps = _drive(prov, np.arange(0, 125, 1.0))
    assert [m.block_id for m in maps] == [m.block_id for m in single]
    regions = [m.entry_ids for m in maps]
    assert ("000", "001") in regions and ("001", "002") in regions
    # ('000',) -> ('000','001') only adds map: no switch; ('000','001') -> ('001',) or -> ('001','002') is one
    flips = [i for i in range(1, len(maps)) if regions[i] != regions[i - 1]]
    assert len(flips) > 2
    assert [i for i, m in enumerate(maps) if m.switched] == [
        i for i in flips if not set(regions[i]) >= set(regions[i - 1])]
    assert sum(m.switched for m in maps) == 2


def test_block_provider_switch_reported_once_and_in_background(tmp_path):
    store = _block_store(tmp_path / "m", [[0, 0, 0], [60, 0, 0], [120, 0, 0]])
    builder = CountingBuilder()
    with MapProvider(store, "block", target_builder=builder, hysteresis_m=4.0) as prov:
        maps = _drive(prov, np.arange(0, 125, 1.0))
        st = prov.stats()
    ids = [m.block_id for m in maps]
    changes = [i for i in range(1, len(ids)) if ids[i] != ids[i - 1]]
    assert [m.switched for m in maps].count(True) == len(changes) == 2 == st["switches"]
    assert all(maps[i].switched for i in changes) and not maps[0].switched
    assert ids[0] == "000" and ids[-1] == "002"
    # switch happens past the bisector by at least half the hysteresis
    assert 32.0 <= changes[0] <= 33.0
    assert maps[changes[0]].version == maps[changes[0] - 1].version + 1
    assert builder.threads == {"blockloc-map-provider"}
    assert maps[0].target["n"] == maps[0].num_points == 2000
    assert st["late_frames"] == 0 and st["prefetch_hits"] == 2  # prefetch made every switch ready


def test_prefetch_loads_ahead_and_without_it_switches_are_late(tmp_path):
    store = _block_store(tmp_path / "m", [[0, 0, 0], [60, 0, 0]])
    gate = threading.Event()

    def slow_builder(points):
        gate.wait(10)
        return len(points)

    # with prefetch: the block ahead is built before the robot needs it
    gate.set()
    with MapProvider(store, "block", target_builder=slow_builder, lookahead_s=10.0) as prov:
        prov.update(np.array([20.0, 0, 0]), np.array([2.0, 0, 0]), 0.0)
        assert prov.wait_idle()
        assert prov.stats()["prefetch_builds"] == 1 and prov.stats()["loads"] == 2
        m = prov.update(np.array([40.0, 0, 0]), np.array([2.0, 0, 0]), 10.0)
        assert m.switched and m.block_id == "001"
    # without: the first frame that wants block 1 still gets block 0, and update does not wait
    gate.clear()
    with MapProvider(store, "block", target_builder=slow_builder, prefetch=False) as prov:
        gate.set()
        prov.update(np.array([20.0, 0, 0]), np.array([2.0, 0, 0]), 0.0)
        gate.clear()  # the next build blocks until released
        m = prov.update(np.array([40.0, 0, 0]), np.array([2.0, 0, 0]), 10.0)
        assert not m.switched and m.block_id == "000"  # returned while the builder is blocked
        m = prov.update(np.array([41.0, 0, 0]), np.array([2.0, 0, 0]), 10.1)
        assert m.block_id == "000"
        gate.set()
        assert prov.wait_idle()
        m = prov.update(np.array([42.0, 0, 0]), np.array([2.0, 0, 0]), 10.2)
        assert m.switched and m.block_id == "001"
        st = prov.stats()
        assert st["late_frames"] == 2 and st["prefetch_builds"] == 0


def test_grid_window_served_and_recomputed_after_half_tile(tmp_path):
    store = _grid_store(tmp_path / "g")
    with MapProvider(store, "grid", grid_n=1, grid_k=1) as prov:
        m = prov.update(np.array([55.0, 55.0, 0]), np.array([1.0, 0, 0]), 0.0)
        # cell (5, 5), heading east: x cells 4..7, y cells 4..6
        want = sorted(f"{(ix + 0.5) * 10:.1f}_{(iy + 0.5) * 10:.1f}" for ix in range(4, 8)
                      for iy in range(4, 7))
        assert list(m.entry_ids) == want and m.num_points == sum(
            store.entry(i).num_points for i in want)
        assert m.region_id == "55.0_55.0/E"
        # 4.9 m later (< s/2) the window is not recomputed even though the cell changed
        m2 = prov.update(np.array([59.9, 55.0, 0]), np.array([1.0, 0, 0]), 1.0)
        assert m2.entry_ids == m.entry_ids and not m2.switched
        prov.wait_idle()
        m3 = prov.update(np.array([60.1, 55.0, 0]), np.array([1.0, 0, 0]), 2.0)
        assert m3.switched and "85.0_55.0" in m3.entry_ids and "45.0_55.0" not in m3.entry_ids


def test_srt_radius_and_rebuild_triggers():
    ids = [f"{(ix + 0.5) * 10:.1f}_{(iy + 0.5) * 10:.1f}" for ix in range(10) for iy in range(10)]
    pol = SrtPolicy(ids, 10.0, radius_m=12.0, rebuild_period_s=5.0)
    r0 = pol.select(np.array([55.0, 55.0, 0]), None, 0.0)
    # tiles whose square comes within 12 m: the own cell and its 8 neighbours (axis cells 10 m on
    # start 15 m away)
    assert r0 == tuple(sorted(f"{x:.1f}_{y:.1f}" for x in (45, 55, 65) for y in (45, 55, 65)))
    # same cell, before T: unchanged even though the disk moved
    assert pol.select(np.array([58.0, 55.0, 0]), None, 4.0) == r0
    # after T: recomputed at the new position (the cell 70..80 m is now 12 m away)
    r1 = pol.select(np.array([58.0, 55.0, 0]), None, 5.0)
    assert set(r1) - set(r0) == {"75.0_55.0"}  # its diagonal neighbours are 13 m away
    # entering a new cell recomputes immediately, before T
    pol.select(np.array([69.0, 55.0, 0]), None, 5.5)
    assert pol.built_at == 5.5 and "85.0_55.0" in pol.region and "45.0_55.0" not in pol.region


def test_grid_policy_ahead_predicts_next_window():
    ids = [f"{(ix + 0.5) * 10:.1f}_{(iy + 0.5) * 10:.1f}" for ix in range(10) for iy in range(10)]
    pol = GridPolicy(ids, 10.0, n=1, k=1)
    pol.select(np.array([55.0, 55.0, 0]), np.array([1.0, 0, 0]), 0)
    nxt = pol.ahead(np.array([57.0, 55.0, 0]), np.array([1.0, 0, 0]), 10.0)
    assert nxt == pol.peek(np.array([60.05, 55.0, 0]), np.array([1.0, 0, 0]))
    assert pol.ahead(np.array([57.0, 55.0, 0]), np.array([1.0, 0, 0]), 1.0) is None  # too far


def test_lru_bound_respected_and_evicts(tmp_path):
    store = _grid_store(tmp_path / "g", extent=200.0, tile=10.0, per_tile=3000)
    tile_mb = 3000 * 12 / 2**20
    budget = 40 * tile_mb  # a 3x4 window is 12 tiles (+ a spare region): about 40 tiles fit
    with MapProvider(store, "grid", grid_n=1, grid_k=1, target_builder=CountingBuilder(),
                     cache_mb=budget) as prov:
        peak = 0.0
        for k, x in enumerate(np.arange(5, 195, 2.0)):
            prov.update(np.array([x, 100.0, 0]), np.array([2.0, 0, 0]), float(k))
            prov.wait_idle()
            peak = max(peak, prov.stats()["resident_mb"])
        st = prov.stats()
    assert st["evictions"] > 0
    assert peak <= budget * 1.0001
    assert st["loads"] > 40  # the route needed more tiles than fit


def test_missing_and_corrupt_tiles_do_not_stop_tracking(tmp_path, caplog):
    store = _block_store(tmp_path / "m", [[0, 0, 0], [60, 0, 0], [120, 0, 0]])
    (tmp_path / "m" / "001.pcd").write_bytes(b"garbage")
    (tmp_path / "m" / "002.pcd").unlink()
    with MapProvider(store, "block", target_builder=CountingBuilder()) as prov:
        maps = _drive(prov, np.arange(0, 125, 2.0))
        st = prov.stats()
    assert maps[-1].block_id == "002" and maps[-1].num_points == 0 and maps[-1].target is None
    assert maps[-1].missing == ("002",)
    assert any(m.block_id == "001" and m.missing == ("001",) for m in maps)
    assert st["failed_loads"] >= 2
    assert "checksum mismatch" in caplog.text and "missing map file" in caplog.text


def test_missing_entry_is_retried_and_swapped_in_when_it_loads_again(tmp_path):
    store = _block_store(tmp_path / "m", [[0, 0, 0], [60, 0, 0]])
    good = (tmp_path / "m" / "000.pcd").read_bytes()
    (tmp_path / "m" / "000.pcd").write_bytes(b"garbage")  # e.g. a server that went away
    with MapProvider(store, "block", target_builder=CountingBuilder(), retry_missing_s=2.0) as prov:
        first = _drive(prov, [0.0, 0.5])
        assert first[-1].missing == ("000",) and first[-1].target is None
        (tmp_path / "m" / "000.pcd").write_bytes(good)  # the file is back
        later = _drive(prov, [1.0, 1.5, 2.0, 2.5, 3.0, 3.5], dt=1.0)
    healed = [m for m in later if not m.missing]
    assert healed, "the region was never rebuilt after its entry became loadable"
    assert healed[-1].block_id == "000" and healed[-1].num_points == 2000
    assert healed[-1].target is not None and not healed[-1].switched
    assert healed[-1].version > first[-1].version


def test_incremental_tile_targets(tmp_path):
    store = _grid_store(tmp_path / "g", extent=100.0)

    class TileTarget:
        built = 0

        def __init__(self, tiles):
            TileTarget.built += 1
            self.tiles = dict(tiles)
            self.adds = self.removes = 0

        def add_tile(self, key, pts):
            self.tiles[key] = pts
            self.adds += 1

        def remove_tile(self, key):
            del self.tiles[key]
            self.removes += 1

    maps = []
    with MapProvider(store, "srt", tiles_target_builder=TileTarget, srt_radius_m=15.0) as prov:
        for k, x in enumerate(np.arange(5, 95, 3.0)):
            m = prov.update(np.array([x, 50.0, 0]), np.array([3.0, 0, 0]), float(k))
            # valid until the next update: the served target holds exactly the region's tiles
            assert set(m.target.tiles) == set(m.entry_ids)
            assert sum(len(p) for p in m.target.tiles.values()) == m.num_points
            prov.wait_idle()
            assert set(m.target.tiles) == set(m.entry_ids)  # the worker never touches it
            maps.append(m)
    assert TileTarget.built <= 3  # the rest were add/remove updates of a spare buffer
    assert sum(m.switched for m in maps) >= 5


def test_global_backend_and_config(tmp_path):
    store = _grid_store(tmp_path / "g", extent=30.0)
    import dataclasses

    cfg = MapConfig(backend="global", cache_mb=64.0)
    with _MapProvider(store, make_policy(cfg.backend, store, **dataclasses.asdict(cfg)),
                      engine=FakeEngine(CountingBuilder()), cache_mb=cfg.cache_mb) as prov:
        maps = _drive(prov, np.arange(0, 30, 5.0))
    assert all(m.entry_ids == tuple(sorted(store.ids)) for m in maps)
    assert maps[0].num_points == store.total_points and not any(m.switched for m in maps)


def test_bad_backend_and_kinds(tmp_path):
    grid = _grid_store(tmp_path / "g", extent=20.0)
    block = _block_store(tmp_path / "b", [[0, 0, 0]])
    with pytest.raises(MapError, match="needs a block map"):
        MapProvider(grid, "block")
    with pytest.raises(MapError, match="needs a grid map"):
        MapProvider(block, "srt")
    with pytest.raises(MapError, match="backend 'nope'"):
        MapProvider(block, "nope")
    with pytest.raises(MapError, match="cache"):
        MapProvider(block, "block", cache_mb=0)


def test_target_builder_failure_is_unmapped_not_fatal(tmp_path):
    store = _block_store(tmp_path / "m", [[0, 0, 0], [60, 0, 0]])

    def picky(points):
        raise ValueError("too few points")

    with MapProvider(store, "block", target_builder=picky) as prov:
        m = prov.update(np.zeros(3), None, 0.0)
        assert m.target is None and m.num_points == 2000
        assert prov.stats()["target_failures"] == 1


def test_bound_smaller_than_a_region_still_serves_and_switches(tmp_path, caplog):
    store = _block_store(tmp_path / "m", [[0, 0, 0], [60, 0, 0], [120, 0, 0]])
    with MapProvider(store, "block", cache_mb=0.001) as prov:  # one block is ~23 kB
        maps = _drive(prov, np.arange(0, 125, 2.0))
        st = prov.stats()
    assert [m.block_id for m in maps][-1] == "002" and st["switches"] == 2
    assert all(m.num_points == 2000 for m in maps)
    assert st["evictions"] >= 1 and "smaller than the regions in use" in caplog.text
    assert st["resident_mb"] <= 2 * 2000 * 12 / 2**20 + 1e-9  # active + the wanted/prefetched one


def test_srt_ahead_predicts_cell_entry_and_period_expiry():
    ids = [f"{(ix + 0.5) * 10:.1f}_{(iy + 0.5) * 10:.1f}" for ix in range(10) for iy in range(10)]
    pol = SrtPolicy(ids, 10.0, radius_m=12.0, rebuild_period_s=5.0)
    v = np.array([1.0, 0, 0])
    pol.select(np.array([51.0, 55.0, 0]), v, 0.0)
    # at 1 m/s the period runs out (x = 56) before the next cell (x = 60)
    assert pol.ahead(np.array([51.0, 55.0, 0]), v, 20.0) == pol.peek(np.array([56.0, 55.0, 0]), v)
    # moving fast, the cell border comes first
    fast = np.array([4.0, 0, 0])
    assert pol.ahead(np.array([51.0, 55.0, 0]), fast, 40.0) == pol.peek(np.array([60.05, 55.0, 0]), fast)
    assert pol.ahead(np.array([51.0, 55.0, 0]), v, 2.0) is None  # neither within the horizon


def test_relocate_serves_the_map_where_the_robot_jumped_to_and_waits_for_it(tmp_path):
    # A jump (a relocalization): update() would serve the old block while the new one loads;
    # relocate() waits for it, and ignores the hysteresis toward the block the robot left.
    store = _block_store(tmp_path / "m", [[0, 0, 0], [60, 0, 0]])
    gate = threading.Event()
    built = []

    def slow_builder(points):
        gate.wait(10)
        built.append(len(points))
        return len(points)

    with MapProvider(store, "block", target_builder=slow_builder, prefetch=False, hysteresis_m=100.0) as prov:
        gate.set()
        assert prov.update(np.array([0.0, 0, 0]), None, 0.0).block_id == "000"
        gate.clear()
        threading.Timer(0.3, gate.set).start()  # the next build finishes later
        m = prov.relocate(np.array([60.0, 0, 0]), None, 1.0)
        assert m.block_id == "001" and len(built) == 2
        assert prov.update(np.array([60.5, 0, 0]), None, 1.1).block_id == "001"
        assert prov.stats()["late_frames"] == 0
