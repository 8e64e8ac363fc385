"""The place index: descriptors, yaw from the column shift, storage in the map store, retrieval."""

import math

import numpy as np
import pytest

from blockloc.errors import MapError
from blockloc.geometry import T_to_xyzrpy, xyzrpy_to_T
from blockloc.global_init.maps import ArrayMap
from blockloc.global_init.place_index import (PLACE_INDEX_NAME, PlaceIndex, PlaceIndexParams,
                                              build_place_index_from_source, load_place_index, pack,
                                              scan_descriptor, unpack, write_place_index)
from blockloc.maps.store import MapWriter, open_map

from .synthetic import GRAVITY_Z_DOWN, Z_DOWN, box_outline, gravity_body, scan_from

PARAMS = PlaceIndexParams(spacing_m=2.0)


def tall_world_up(seed=11, size=120.0, n_boxes=40):
    """(N, 3) z-up points: flat ground and box outlines 2.5-8 m tall (the index's band is 2-4 m)."""
    rng = np.random.default_rng(seed)
    n_g = int(8.0 * size * size)
    g = rng.uniform(-size / 2, size / 2, (n_g, 2))
    parts = [np.c_[g, rng.normal(0, 0.02, n_g)]]
    for _ in range(n_boxes):
        cx, cy = rng.uniform(-size / 2, size / 2, 2)
        if math.hypot(cx, cy) < 6.0:
            continue  # keep the middle free to stand in
        w, d = rng.uniform(1, 7, 2)
        parts.append(box_outline(rng, cx, cy, w, d, rng.uniform(2.5, 8.0), rng.uniform(0, np.pi), 0.0, per_m=40))
    return np.concatenate(parts)


@pytest.fixture(scope="module")
def world():
    m = tall_world_up() @ Z_DOWN.T
    return m, build_place_index_from_source(ArrayMap(m, GRAVITY_Z_DOWN, PARAMS.projection_params), GRAVITY_Z_DOWN,
                                            PARAMS)


def test_bits_pack_and_unpack():
    rng = np.random.default_rng(0)
    occ = rng.random((3, 20, 64)) < 0.3
    assert np.array_equal(unpack(pack(occ), 64), occ)
    occ = rng.random((20, 100)) < 0.3
    assert np.array_equal(unpack(pack(occ), 100), occ)


def test_places_cover_the_free_middle_and_skip_the_inside_of_boxes(world):
    m, index = world
    assert len(index) > 500 and np.all(index.source == 1)  # no keyframes: grid places only
    d = np.hypot(*index.xy_L.T)
    assert d.min() < 2.0  # a place near the free middle
    occ_bits = np.array([unpack(b, index.params.num_sectors).sum() for b in index.bits])
    assert occ_bits.min() >= index.params.min_bits


def test_yaw_from_the_column_shift_on_rotated_copies_of_a_scan(world):
    m, index = world
    S = index.params.num_sectors
    for yaw in np.radians([0.0, 37.0, 90.0, 155.0, -100.0, -20.0]):
        T = xyzrpy_to_T(1.0, -1.0, -1.8, 0.0, 0.0, yaw)  # z-down body, as in the simulator
        cands = index.query(scan_from(m, T, radius=60.0), gravity_body(T), k=3)
        best = cands[0]
        assert math.hypot(best.x - 1.0, best.y + 1.0) <= 2.0, (best.x, best.y)
        err = (best.yaw - T_to_xyzrpy(T)[5] + math.pi) % (2 * math.pi) - math.pi
        assert abs(err) <= 2 * math.pi / S, math.degrees(err)  # within one sector (5.6 deg)


def test_the_scan_descriptor_turns_with_the_scan(world):
    m, index = world
    p = index.params
    T0 = xyzrpy_to_T(1.0, -1.0, -1.8, 0.0, 0.0, 0.0)
    cells0 = index.scan_cells(scan_from(m, T0, radius=60.0), gravity_body(T0))
    T1 = xyzrpy_to_T(1.0, -1.0, -1.8, 0.0, 0.0, math.radians(90.0))
    cells1 = index.scan_cells(scan_from(m, T1, radius=60.0), gravity_body(T1))
    a = unpack(scan_descriptor(cells0.band, p).occupied, p.num_sectors)
    b = unpack(scan_descriptor(cells1.band, p).occupied, p.num_sectors)
    # 90 deg = 16 of 64 sectors; the body turned left, so the world turns right in the scan
    # (z-down body: the levelled frame's y is the body's -y).
    overlap = [np.mean(np.roll(b, s, axis=1)[a]) for s in range(p.num_sectors)]
    assert int(np.argmax(overlap)) in (15, 16, 17, 47, 48, 49)
    assert max(overlap) > 0.8


def test_index_round_trips_through_the_store_and_a_corrupt_file_is_named(world, tmp_path):
    m, _ = world
    keys = np.floor(m[:, :2] / 40.0).astype(int)
    with MapWriter(tmp_path / "map", "grid", params={"tile_size_m": 40.0}) as w:
        for k in np.unique(keys, axis=0):
            w.add(f"{k[0] * 40 + 20.0:.1f}_{k[1] * 40 + 20.0:.1f}", m[np.all(keys == k, axis=1)].astype(np.float32))
        w.commit()
    store, index = write_place_index(tmp_path / "map", GRAVITY_Z_DOWN, PARAMS, cache_dir=tmp_path / "cache")
    assert store.has_extra(PLACE_INDEX_NAME)
    extra = store.extras[PLACE_INDEX_NAME]
    assert extra.bytes == (tmp_path / "map" / extra.file).stat().st_size
    again = load_place_index(open_map(tmp_path / "map"), GRAVITY_Z_DOWN, PARAMS, build_missing=False)
    assert again.params == index.params and len(again) == len(index)
    assert np.array_equal(again.xy_L, index.xy_L) and np.array_equal(again.bits, index.bits)
    assert np.array_equal(again.grown, index.grown)
    # the same index gives the same bytes (serial and Dask builds of a map are compared byte for byte)
    assert again.to_bytes() == index.to_bytes() == (tmp_path / "map" / extra.file).read_bytes()
    # writing it again replaces it atomically: a new file name, then the old file is removed
    store2, _ = write_place_index(tmp_path / "map", GRAVITY_Z_DOWN, PlaceIndexParams(spacing_m=3.0),
                                  cache_dir=tmp_path / "cache")
    new = store2.extras[PLACE_INDEX_NAME]
    assert new.sha256 != extra.sha256 and new.file != extra.file
    assert not (tmp_path / "map" / extra.file).exists() and (tmp_path / "map" / new.file).exists()
    # a flipped byte: the error names the file
    f = tmp_path / "map" / new.file
    good = f.read_bytes()
    bad = bytearray(good)
    bad[len(bad) // 2] ^= 0xFF
    f.write_bytes(bytes(bad))
    with pytest.raises(MapError, match=rf"{new.file}: checksum mismatch"):
        load_place_index(open_map(tmp_path / "map"), GRAVITY_Z_DOWN, build_missing=False)
    # the index of a map with other gravity is refused, naming the file
    f.write_bytes(good)
    with pytest.raises(MapError, match=rf"{PLACE_INDEX_NAME}: built for gravity"):
        load_place_index(open_map(tmp_path / "map"), np.array([0.0, 0.0, -9.81]), build_missing=False)


def test_bad_index_bytes_raise_a_map_error_naming_them():
    with pytest.raises(MapError, match="somewhere.npz: not a place index"):
        PlaceIndex.from_bytes(b"not an npz", "somewhere.npz")


def test_retrieval_recall_on_the_small_world(small_world, tmp_path):
    from blockloc.app.catalog import open_sequence

    from .conftest import prepared_scans

    paths, cfg = small_world
    seq = open_sequence(paths.loc, dataset_cfg=cfg.dataset)
    index = load_place_index(open_map(paths.block_map), seq.info.gravity_map, cache_dir=tmp_path)
    assert index.stats["keyframe_places"] > 0 and index.stats["grid_places"] > 0
    ranks = []
    for scan, T in prepared_scans(seq, np.linspace(20, len(seq) - 1, 25).astype(int)):
        cands = index.query(scan.points_body, scan.gravity_body, k=10)
        near = [k for k, c in enumerate(cands) if math.hypot(c.x - T[0, 3], c.y - T[1, 3]) < 5.0]
        ranks.append(near[0] if near else 99)
    ranks = np.array(ranks)
    assert np.mean(ranks < 5) >= 0.95, ranks  # recall@5
    assert np.mean(ranks < 1) >= 0.8, ranks  # recall@1


def low_world_up(seed=5, size=120.0, n_boxes=70):
    """(N, 3) z-up points: flat ground and box outlines 0.9-1.8 m tall (fences, hedges, cars: nothing
    in the static band 2-4 m)."""
    rng = np.random.default_rng(seed)
    n_g = int(15.0 * size * size)
    g = rng.uniform(-size / 2, size / 2, (n_g, 2))
    parts = [np.c_[g, rng.normal(0, 0.02, n_g)]]
    for _ in range(n_boxes):
        cx, cy = rng.uniform(-size / 2, size / 2, 2)
        if math.hypot(cx, cy) < 6.0:
            continue  # keep the middle free to stand in
        w, d = rng.uniform(1, 7, 2)
        parts.append(box_outline(rng, cx, cy, w, d, rng.uniform(0.9, 1.8), rng.uniform(0, np.pi), 0.0, per_m=40))
    return np.concatenate(parts)


def test_an_open_stretch_gets_open_places_and_is_relocalized_without_a_hint():
    """Where the static band is empty, the places are described in the open band, and a scan there
    is found by them, verified at the right pose; without open places, the index holds none."""
    from blockloc.global_init.relocalize import GlobalLocalizer, InitParams, pose_error

    m = low_world_up() @ Z_DOWN.T
    source = ArrayMap(m, GRAVITY_Z_DOWN, PARAMS.projection_params)
    index = build_place_index_from_source(source, GRAVITY_Z_DOWN, PARAMS)
    assert len(index) > 300 and np.all(index.band == 1), index.stats
    assert index.stats["open_places"] == len(index)
    static_only = build_place_index_from_source(
        source, GRAVITY_Z_DOWN, PlaceIndexParams(spacing_m=2.0, open_band_m=None))
    assert len(static_only) == 0  # the static band alone leaves the stretch unindexed
    # round trip keeps the bands
    again = PlaceIndex.from_bytes(index.to_bytes())
    assert np.array_equal(again.band, index.band) and again.params == index.params
    loc = GlobalLocalizer.for_points(m, GRAVITY_Z_DOWN, InitParams(whole_map_fallback=False))
    loc._place_index = index
    found = 0
    for x, y, yaw in ((1.0, -1.0, 30.0), (20.0, 15.0, -120.0), (-25.0, 10.0, 80.0)):
        T = xyzrpy_to_T(x, y, -1.8, 0.0, 0.0, math.radians(yaw))
        scan = scan_from(m, T, radius=40.0)
        cands = index.query(scan, gravity_body(T), k=8)
        assert any(math.hypot(c.x - x, c.y - y) < 3.0 for c in cands), [(c.x, c.y) for c in cands]
        res = loc.localize(scan, gravity_body(T))
        e_t, e_r = pose_error(res.T_map_body, T) if res.T_map_body is not None else (math.inf, math.inf)
        assert not res.verified or (e_t < 0.3 and e_r < 2.0), (e_t, e_r)  # never verified and wrong
        found += bool(res.verified)
    assert found == 3


def test_a_version_2_index_still_loads_without_open_places(world):
    import io
    import json

    _, index = world
    with np.load(io.BytesIO(index.to_bytes())) as z:
        arrays = {k: z[k] for k in z.files if k != "band"}
    meta = json.loads(bytes(arrays["meta"]).decode())
    meta["version"] = 2
    del meta["params"]["open_band_m"]
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    old = PlaceIndex.from_bytes(buf.getvalue(), "old.npz")
    assert len(old) == len(index) and np.all(old.band == 0) and old.params.open_band_m is None
    meta["version"] = 1
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    with pytest.raises(MapError, match="old.npz: place index version 1.*rebuild it with 'blockloc map index'"):
        PlaceIndex.from_bytes(buf.getvalue(), "old.npz")


def test_a_scan_with_too_few_static_bits_ranks_the_static_and_the_open_places_side_by_side():
    """A scan whose static band holds fewer than ``min_bits`` bits (what makes a place open): its
    static places' scores (chance, from a handful of bits: campus 20 bits scored 1.2 per bit and
    buried the true open place at rank 8342) and its open places' alternate in the ranking; with
    enough static bits the ranking is by score alone."""
    from blockloc.global_init.place_descriptors import ScanCells
    from blockloc.global_init.place_index import best_shift

    p = PlaceIndexParams()
    rng = np.random.default_rng(0)
    S, R = p.num_sectors, p.num_rings

    def ring_cells(n, r_m):
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return np.unique(np.floor(np.c_[r_m * np.cos(a), r_m * np.sin(a)] / p.resolution_m).astype(np.int64), axis=0)

    few_band = ring_cells(6, 12.0)
    open_cells = np.concatenate([ring_cells(200, r) for r in (8.0, 20.0, 35.0)])
    # static places that hold the scan's few bits (and little else: they score high per bit), open
    # places with dense random bits
    hit = scan_descriptor(few_band, p).occupied
    static_bits = [hit | pack(rng.random((R, S)) < 0.02) for _ in range(3)]
    open_bits = [pack(rng.random((R, S)) < 0.4) for _ in range(3)]
    xy = np.array([[0, 0], [30, 0], [60, 0], [0, 30], [30, 30], [60, 30]], np.float32)
    index = PlaceIndex(p, np.array([0.0, 0.0, 9.81]), xy, np.ones(6, np.uint8), np.stack(static_bits + open_bits),
                       np.stack(static_bits + open_bits), band=np.array([0, 0, 0, 1, 1, 1], np.uint8))
    few = ScanCells(few_band, open_cells, np.eye(3), 7.0, None, open_cells)
    assert scan_descriptor(few.band, p, few.obstacles, 7.0).counts(S)[0].sum() < p.min_bits
    best, _ = best_shift(index.scores(few))
    assert set(np.argsort(-best)[:3]) == {0, 1, 2}  # by score alone: the static places first
    assert index.thin_static(few)
    ranked = [index.band[c.index] for c in index.query_cells(few, k=6)]
    assert ranked[:4] == [0, 1, 0, 1]
    many_band = np.concatenate([ring_cells(200, r) for r in (10.0, 25.0, 40.0)])
    many = ScanCells(many_band, open_cells, np.eye(3), 7.0, None, open_cells)
    assert not index.thin_static(many)
    best, _ = best_shift(index.scores(many))
    assert [c.index for c in index.query_cells(many, k=6)] == list(np.argsort(-best, kind="stable"))


def test_the_compiled_greedy_suppression_keeps_what_the_cell_lookup_kept():
    # query_cells keeps the best places at least nms_m apart (global_init._kernels.greedy_nms); the
    # reference is the dictionary of accepted places by nms_m cell it replaced.
    from blockloc.global_init import _kernels as K

    rng = np.random.default_rng(3)
    xy = np.round(rng.uniform(-40, 40, (3000, 2)) / 0.5) * 0.5  # lattice corners: exact ties at nms_m
    order = rng.permutation(len(xy)).astype(np.int64)
    for nms_m, k in ((4.0, 256), (4.0, 10), (2.5, 5000)):
        kept_ref, cells = [], {}
        for o in order:
            ci, cj = (int(v) for v in np.floor(xy[o] / nms_m))
            if any(np.hypot(*(q - xy[o])) < nms_m for di in (-1, 0, 1) for dj in (-1, 0, 1)
                   for q in cells.get((ci + di, cj + dj), ())):
                continue
            cells.setdefault((ci, cj), []).append(xy[o])
            kept_ref.append(o)
            if len(kept_ref) >= k:
                break
        kept = K.greedy_nms(xy, order, nms_m, k)
        assert kept.tolist() == kept_ref
        assert len(kept) == min(k, len(kept_ref))


def test_a_subsets_scores_are_its_rows_of_the_whole_index_with_the_weights_kept_or_not(world):
    # The hinted search scores the places of its window (PlaceIndex.subset); the log-likelihood
    # weights are kept per index (llr_weights) and a subset takes its rows of them.
    m, whole_index = world
    index = PlaceIndex(whole_index.params, whole_index.gravity_map, whole_index.xy_L, whole_index.source,
                       whole_index.bits, whole_index.grown, {}, whole_index.band)  # nothing kept yet
    T = xyzrpy_to_T(1.0, -1.0, -1.8, 0.0, 0.0, 0.7)
    cells = index.scan_cells(scan_from(m, T, radius=60.0), gravity_body(T))
    rows = np.arange(0, len(index), 3)
    before = index.subset(rows).scores(cells)  # weights not kept yet: the subset computes its own
    assert index._llr_weights is None
    whole = index.scores(cells)
    assert index._llr_weights is not None
    after = index.subset(rows).scores(cells)  # the whole index's weights, its rows
    assert np.isfinite(whole).all() and whole.std() > 0
    np.testing.assert_array_equal(after, before)  # kept weights change nothing
    # the whole index's rows, to float32 rounding (the ring sums' matrix product by another shape)
    np.testing.assert_allclose(after, whole[rows], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("places, rings, words, shifts", [(300, 20, 1, 64), (7, 3, 2, 128), (0, 4, 1, 8)])
def test_polar_llr_is_the_ring_by_ring_float32_sum(places, rings, words, shifts):
    # every shift of a place at once (_kernels.polar_llr): the same float32 sums, in the same
    # order, as one shift at a time
    from blockloc.global_init import _kernels as K

    rng = np.random.default_rng(places)

    def bits(*shape):
        return (rng.integers(0, 2**63, shape, dtype=np.int64).astype(np.uint64) << np.uint64(1)) \
            | rng.integers(0, 2, shape).astype(np.uint64)

    grown, raw = bits(places, rings, words), bits(places, rings, words)
    occ, free = bits(shifts, rings, words), bits(shifts, rings, words)
    occ_w = rng.normal(0, 1, (places, rings)).astype(np.float32)
    free_w = rng.normal(0, 1, (places, rings)).astype(np.float32)

    def common(a, b):  # (P, S) set bits of a (S, W) & b (P, W)
        x = a[None, :, :] & b[:, None, :]
        return np.unpackbits(x.view(np.uint8), axis=-1).reshape(len(b), len(a), 64 * a.shape[-1]).sum(axis=-1)

    want = np.zeros((places, shifts), np.float32)
    for r in range(rings):
        c1 = common(occ[:, r], grown[:, r]).astype(np.float32)
        c2 = common(free[:, r], raw[:, r]).astype(np.float32)
        want = want + (occ_w[:, r, None] * c1 + free_w[:, r, None] * c2)
    got = K.polar_llr(occ, grown, occ_w, free, raw, free_w)
    assert got.dtype == np.float32 and np.array_equal(got, want)
