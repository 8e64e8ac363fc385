"""The DynamicMap Benchmark layout: scans in the world frame, the sensor pose in VIEWPOINT."""

import numpy as np
import pypcd4
import pytest
from scipy.spatial.transform import Rotation

from blockloc.datasets.dynamicmap import (DynamicMapWriter, iter_scans, pose_of_viewpoint, read_gt_cloud,
                                          scan_paths, viewpoint_of)
from blockloc.errors import DatasetError


def _pose(rng):
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-50, 50, 3)
    return T


def test_viewpoint_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        T = _pose(rng)
        v = viewpoint_of(T)
        assert v.shape == (7,) and np.isclose(np.linalg.norm(v[3:]), 1.0)
        assert np.allclose(pose_of_viewpoint(v), T, atol=1e-9)
    assert np.allclose(viewpoint_of(np.eye(4)), [0, 0, 0, 1, 0, 0, 0])


def test_writer_scans_read_back_with_pypcd4(tmp_path):
    rng = np.random.default_rng(1)
    poses = [_pose(rng) for _ in range(3)]
    pts = [rng.uniform(-20, 20, (100 + 10 * k, 3)) for k in range(3)]
    dyn = [rng.random(len(p)) < 0.2 for p in pts]
    w = DynamicMapWriter(tmp_path)
    for p, T, d in zip(pts, poses, dyn):
        w.add_scan(p, T, d)
    assert w.finish() == tmp_path / "gt_cloud.pcd"
    assert [p.name for p in scan_paths(tmp_path)] == ["000000.pcd", "000001.pcd", "000002.pcd"]
    for k, path in enumerate(scan_paths(tmp_path)):
        pc = pypcd4.PointCloud.from_path(path)  # an independent reader
        assert pc.fields == ("x", "y", "z", "intensity")
        vp = np.asarray(pc.metadata.viewpoint)
        assert np.allclose(vp[:3], poses[k][:3, 3], atol=1e-6)
        assert np.allclose(pose_of_viewpoint(vp), poses[k], atol=1e-6)
        a = pc.numpy()
        assert np.allclose(a[:, :3], pts[k], atol=1e-5)  # world frame, as given
        assert np.array_equal(a[:, 3] > 0.5, dyn[k])  # the benchmark keeps the label in intensity
    got = list(iter_scans(tmp_path))
    assert np.allclose(got[1][1], poses[1], atol=1e-6) and np.allclose(got[1][0], pts[1], atol=1e-5)
    g, d = read_gt_cloud(tmp_path)
    assert np.allclose(g, np.concatenate(pts), atol=1e-5) and np.array_equal(d, np.concatenate(dyn))


def test_unlabelled_scans_have_no_gt_cloud(tmp_path):
    w = DynamicMapWriter(tmp_path)
    w.add_scan(np.zeros((4, 3)), np.eye(4), intensity=np.arange(4.0))
    assert w.finish() is None and not (tmp_path / "gt_cloud.pcd").exists()
    with pytest.raises(DatasetError, match="gt_cloud.pcd"):
        read_gt_cloud(tmp_path)
    with pytest.raises(DatasetError, match="4 labels for 3 points"):
        w.add_scan(np.zeros((3, 3)), np.eye(4), np.zeros(4, bool))
    with pytest.raises(DatasetError, match="no scans"):
        scan_paths(tmp_path / "nothing")
