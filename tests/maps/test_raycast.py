"""blockloc.maps.raycast: the compiled ray walk gives exactly the sorting path's voxels
(``detect.ray_free_keys`` with the grid refused), with and without a map."""

import numpy as np
import pytest

from blockloc.maps import raycast
from blockloc.maps.changes.detect import ray_free_keys, ray_margins, voxel_keys


def _scan(rng, n=3000):
    """A sensor 1.7 m up among a ground plane, a wall and scattered points up to 60 m (z up)."""
    az = rng.uniform(0, 2 * np.pi, n)
    r = rng.uniform(2, 60, n)
    pts = np.c_[r * np.cos(az), r * np.sin(az), rng.uniform(-1.8, 4.0, n)]
    pts[: n // 3, 2] = rng.normal(0.0, 0.02, n // 3)  # the ground
    return np.array([0.3, -0.2, 1.7]), pts


@pytest.mark.parametrize("variant", ["plain", "map", "map+hits", "map+hits+only", "only"])
def test_same_keys_as_the_sorting_path(monkeypatch, variant):
    rng = np.random.default_rng(7)
    origin, pts = _scan(rng)
    _, other = _scan(np.random.default_rng(8))
    margin = ray_margins(origin, pts, np.array([0.0, 0.0, 1.0]), 0.5)
    kw = {}
    if "map" in variant:
        kw["fine"] = (np.unique(voxel_keys(other, 0.4)), 0.16, np.unique(voxel_keys(other, 0.16)))
    if "hits" in variant:
        kw["hit_fine"] = np.unique(voxel_keys(pts, 0.16))
    if "only" in variant:
        kw["only"] = np.unique(voxel_keys(other, 0.4))[::2]
    fast = ray_free_keys(origin, pts, 0.4, margin, **kw)
    assert len(fast) > 10
    monkeypatch.setattr(raycast, "MAX_GRID_CELLS", 0)  # every scan takes the sorting path
    assert raycast.free_voxels(origin, pts, 0.4, margin, fine=kw.get("fine"), hit_fine=kw.get("hit_fine")) is None
    slow = ray_free_keys(origin, pts, 0.4, margin, **kw)
    assert np.array_equal(fast, slow)
    assert np.all(np.diff(fast) > 0)


def test_rays_shorter_than_the_margin_mark_nothing():
    origin = np.zeros(3)
    assert raycast.free_voxels(origin, np.array([[0.3, 0.0, 0.0]]), 0.4, 0.5).shape == (0, 3)
