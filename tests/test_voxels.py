"""blockloc.voxels: the one voxel filter (centroids) and the one voxel selection (first real point)."""

import numpy as np
import pytest

from blockloc.errors import BlocklocError
from blockloc.voxels import voxel_downsample, voxel_groups, voxel_select


def test_downsample_keeps_centroids_and_mean_intensity_and_drops_non_finite():
    pts = np.array([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05], [1.05, 0, 0], [np.nan, 0, 0]])
    p, i = voxel_downsample(pts, 1.0, np.array([1.0, 3.0, 5.0, 7.0]))
    np.testing.assert_allclose(p, [[0.1, 0.05, 0.05], [1.05, 0, 0]], atol=1e-12)  # ascending key order
    np.testing.assert_allclose(i, [2.0, 5.0])
    assert i.dtype == np.float32
    q, none = voxel_downsample(pts, 1.0)
    np.testing.assert_allclose(q, p)
    assert none is None


def test_downsample_negative_coordinates_and_no_filter():
    pts = np.array([[-0.5, -0.5, 0.2], [-0.4, -0.6, 0.3], [0.5, 0.5, 0.2]])
    p, _ = voxel_downsample(pts, 1.0)
    assert len(p) == 2  # -0.5 and 0.5 fall in different voxels (floor, not truncation)
    same, _ = voxel_downsample(pts, 0.0)
    np.testing.assert_array_equal(same, pts)
    empty, ei = voxel_downsample(np.zeros((0, 3)), 0.5, np.zeros(0))
    assert empty.shape == (0, 3) and len(ei) == 0


def test_select_keeps_the_first_real_point_per_voxel_in_input_order():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-5, 5, size=(20000, 3))
    idx = voxel_select(pts, 1.0)
    keys = np.floor(pts[idx]).astype(int)
    assert len(np.unique(keys, axis=0)) == len(idx) == 1000  # every voxel once
    assert np.all(np.diff(idx) > 0)
    all_keys = np.floor(pts).astype(int)
    for k in idx[:50]:  # no earlier point shares its voxel
        assert not np.any(np.all(all_keys[:k] == all_keys[k], axis=1))
    np.testing.assert_array_equal(voxel_select(pts, 0.0), np.arange(len(pts)))


def test_groups_and_bad_size():
    inverse, first, counts = voxel_groups(np.array([[0.1, 0, 0], [2.5, 0, 0], [0.2, 0, 0]]), 1.0)
    np.testing.assert_array_equal(inverse, [0, 1, 0])
    np.testing.assert_array_equal(first, [0, 1])
    np.testing.assert_array_equal(counts, [2, 1])
    with pytest.raises(BlocklocError, match="voxel size"):
        voxel_groups(np.zeros((3, 3)), -1.0)
