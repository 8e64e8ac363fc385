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
