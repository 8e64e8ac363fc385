"""refine.Footprint: where the map holds data, counted on a dense grid (or sorted codes when spread far)."""

import numpy as np

from blockloc.global_init.refine import Footprint


def _reference(points_map, R_L_map, cell_m, min_share, queries_L):
    """The definition, written plainly: cells holding >= max(3, min_share x median non-empty count)."""
    xy = points_map @ R_L_map[:2].T
    cells = [tuple(c) for c in np.floor(xy / cell_m).astype(int)]
    counts: dict = {}
    for c in cells:
        counts[c] = counts.get(c, 0) + 1
    floor = max(3.0, min_share * float(np.median(list(counts.values()))))
    keep = {c for c, n in counts.items() if n >= floor}
    return np.array([tuple(c) in keep for c in np.floor(queries_L / cell_m).astype(int)])


def test_the_dense_grid_and_the_sorted_codes_give_the_definition(monkeypatch):
    rng = np.random.default_rng(3)
    dense = rng.uniform([-20, -10, -2], [25, 30, 6], (30_000, 3))
    sparse = rng.uniform([-20, -10, -2], [25, 30, 6], (300, 3))  # thin ground: below the floor
    pts = np.concatenate([dense[dense[:, 0] < 5], sparse])
    c, s = np.cos(0.3), np.sin(0.3)
    R_L_map = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    q = rng.uniform([-40, -40], [40, 40], (5000, 2))
    want = _reference(pts, R_L_map, 1.0, 0.25, q)
    assert 0.05 < want.mean() < 0.6
    for dtype in (np.float64, np.float32):
        fp = Footprint(pts.astype(dtype), R_L_map, 1.0, 0.25)  # the store's points are float32
        assert fp._grid is not None
        ref = _reference(pts.astype(dtype).astype(np.float64), R_L_map, 1.0, 0.25, q)
        np.testing.assert_array_equal(fp.contains_L(q), ref)
    monkeypatch.setattr(Footprint, "MAX_DENSE_CELLS", 0)  # points spread over more cells than a grid should hold
    fp = Footprint(pts, R_L_map, 1.0, 0.25)
    assert fp._grid is None
    np.testing.assert_array_equal(fp.contains_L(q), want)
    # map-frame queries go through the same levelling
    q3 = np.c_[q, rng.uniform(-1, 1, len(q))] @ R_L_map
    np.testing.assert_array_equal(Footprint(pts, R_L_map, 1.0, 0.25).contains(q3), want)


def test_an_empty_footprint_contains_nothing():
    fp = Footprint(np.zeros((0, 3)), np.eye(3), 1.0, 0.25)
    assert not fp.contains_L(np.zeros((4, 2))).any()


def test_block_inlier_ratios_are_each_blocks_inlier_ratio():
    """``Refiner.block_inlier_ratios`` (one kernel pass, used by ``verify.better_fit``) gives exactly
    ``inlier_ratio`` of each block's points, the footprint applied as it applies it; an engine
    without a per-group count is asked block by block."""
    from blockloc.global_init.refine import Refiner
    from blockloc.registration.engines import make_engine

    from .synthetic import world_up

    rng = np.random.default_rng(5)
    world = world_up(seed=2, size=80.0, n_boxes=30)
    ref = Refiner(make_engine("ndt", resolution_m=1.0, num_threads=1), world[world[:, 0] < 20.0], None, 1.0, 0.25)
    T = np.eye(4)
    T[:3, 3] = [3.0, -2.0, 1.5]
    c, s = np.cos(0.2), np.sin(0.2)
    T[:2, :2] = [[c, -s], [s, c]]
    scan = world[rng.choice(len(world), 20_000, replace=False)] - T[:3, 3]  # partly off the map's part
    scan = scan + rng.normal(0, 0.05, scan.shape)
    block = np.floor(scan[:, :2] / 2.0).astype(np.int64)
    _, block = np.unique(block, axis=0, return_inverse=True)
    block = block.reshape(-1)
    nb = int(block.max()) + 1
    want = np.array([ref.inlier_ratio(scan[block == k], T) for k in range(nb)])
    got = ref.block_inlier_ratios(scan, T, block, nb)
    assert (want == 0).any() and ((want > 0) & (want < 1)).any() and want.max() > 0.5  # some blocks off the map
    np.testing.assert_array_equal(got, want)
    ref.engine = type("NoGroups", (), {"evaluate": ref.engine.evaluate})()
    np.testing.assert_array_equal(ref.block_inlier_ratios(scan, T, block, nb), want)


def test_the_whole_scan_keeps_one_target_while_poses_stay_near_and_drops_it_when_told():
    from blockloc.global_init.refine import WholeScan

    built = []

    def refiner_over(xy, d):
        built.append((xy.copy(), d))
        return None  # no map there: align says None

    whole = WholeScan(np.ones((5, 3)), refiner_over, np.eye(3), 65.0, reuse_m=2.0)
    T = np.eye(4)
    assert whole.align(T) is None and len(built) == 1 and built[0][1] == 65.0
    T1 = T.copy()
    T1[:2, 3] = (1.5, -1.0)  # within 2 m of the kept target's centre
    whole.align(T1)
    assert len(built) == 1
    T1[0, 3] = 3.0
    whole.align(T1)
    assert len(built) == 2
    whole.release()
    whole.align(T1)
    assert len(built) == 3
    assert WholeScan(np.zeros((0, 3)), refiner_over, np.eye(3), 65.0).align(T) is None and len(built) == 3
