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


def _scan_like(rng, n=30000, dtype=np.float32):
    """A LiDAR-like cloud: rings of points out to ~120 m, a few NaN / inf rows, a few at 0."""
    az = rng.uniform(-np.pi, np.pi, n)
    el = rng.uniform(-0.5, 0.2, n)
    r = rng.uniform(0.0, 120.0, n)
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    pts[rng.integers(0, n, 20)] = np.nan
    pts[rng.integers(0, n, 5), 1] = np.inf
    pts[rng.integers(0, n, 5)] = 0.0
    return pts.astype(dtype)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("size", [0.5, 0.3, 2.0])
def test_select_kernel_equals_the_numpy_reference(dtype, size):
    from blockloc.voxels import voxel_select_numpy

    rng = np.random.default_rng(7)
    pts = _scan_like(rng, dtype=dtype)
    # in range: the scan's range filter in the same pass; non-finite rows are skipped
    got = voxel_select(pts, size, range_m=(2.0, 100.0))
    want = voxel_select_numpy(pts, size, range_m=(2.0, 100.0))
    assert len(got) > 1000
    np.testing.assert_array_equal(got, want)
    r = np.linalg.norm(pts[got].astype(np.float64), axis=1)
    assert np.all((r >= 2.0) & (r <= 100.0))
    finite = np.isfinite(pts).all(axis=1)
    clean = pts[finite]
    np.testing.assert_array_equal(voxel_select(clean, size), voxel_select_numpy(clean, size))
    # extra columns are ignored, a strided view gives the same
    wide = np.hstack([clean, np.ones((len(clean), 2), dtype)])
    np.testing.assert_array_equal(voxel_select(wide, size), voxel_select_numpy(clean, size))
    np.testing.assert_array_equal(voxel_select(wide[:, :3], size), voxel_select_numpy(clean, size))


def test_select_points_on_voxel_borders_and_far_clouds_fall_back_exactly():
    from blockloc.voxels import voxel_select_numpy

    # exact multiples of the size and their float neighbours: floor of the same quotient
    v = np.array([-1.0, -0.5, 0.0, 0.5, 1.0, 1.5])
    grid = np.stack(np.meshgrid(v, v, v), -1).reshape(-1, 3)
    pts = np.concatenate([grid, np.nextafter(grid, -np.inf), np.nextafter(grid, np.inf)])
    np.testing.assert_array_equal(voxel_select(pts, 0.5), voxel_select_numpy(pts, 0.5))
    # more than 2**20 voxels from the origin: the numpy reference answers (same indices)
    far = np.array([[0.0, 0, 0], [3e6, 0, 0], [3e6 + 0.1, 0, 0], [0.05, 0, 0]])
    np.testing.assert_array_equal(voxel_select(far, 1.0), [0, 1])
    np.testing.assert_array_equal(voxel_select(far, 1.0, range_m=(1.0, 1e7)), [1])
    # no filter, range only
    np.testing.assert_array_equal(voxel_select(far, 0.0, range_m=(1.0, 1e7)), [1, 2])
