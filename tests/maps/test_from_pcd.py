"""Maps from a global PCD and a trajectory: keyframe crops, block and grid stores."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from blockloc.datasets.pointclouds import write_point_cloud
from blockloc.errors import MapError
from blockloc.trajectory_io import write_kitti, write_tum
from blockloc.geometry import Trajectory, xyzrpy_to_T
from blockloc.maps.from_pcd import build_map_from_global_pcd, keyframes_from_global_map
from blockloc.voxels import voxel_downsample
from blockloc.maps.store import open_map

VOXEL = 0.25


def _corridor(length=60.0, width=8.0, height=3.0, step=0.25):
    """Floor and two walls of a corridor along x (map frame, metres), on a ``step`` grid."""
    xs = np.arange(0.0, length, step)
    ys = np.arange(-width / 2, width / 2, step)
    zs = np.arange(0.0, height, step)
    fx, fy = np.meshgrid(xs, ys, indexing="ij")
    floor = np.column_stack([fx.ravel(), fy.ravel(), np.zeros(fx.size)])
    wx, wz = np.meshgrid(xs, zs, indexing="ij")
    walls = [np.column_stack([wx.ravel(), np.full(wx.size, y), wz.ravel()])
             for y in (-width / 2, width / 2)]
    pts = np.concatenate([floor, *walls]) + 0.01  # off the voxel borders
    return pts, (pts[:, 0] * 10 % 255).astype(np.float32)


def _walk(n=25, length=50.0):
    x = np.linspace(2.0, length, n)
    return Trajectory(100.0 + np.arange(n), xyzrpy_to_T(x, 0.3 * np.sin(x), np.full(n, 1.2), 0 * x, 0 * x,
                                                     0.1 * np.sin(x)))


def test_crops_match_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-50, 50, (20000, 3)) * [1, 1, 0.1]
    traj = Trajectory(np.arange(6.0), xyzrpy_to_T(rng.uniform(-40, 40, 6), rng.uniform(-40, 40, 6),
                                                  *np.zeros((3, 6)), rng.uniform(-3, 3, 6)))
    T_bl = xyzrpy_to_T(0.5, 0.0, 1.0, 0, 0, 0)
    kfs = list(keyframes_from_global_map(pts, None, traj, sensor_range_m=17.0,
                                         keyframe_distance_m=0.0, keyframe_angle_deg=0.0,
                                         T_body_lidar=T_bl))
    assert [k.index for k in kfs] == list(range(6))
    tree = cKDTree(pts)
    for k, T in zip(kfs, traj.poses @ T_bl):
        np.testing.assert_allclose(k.T_map_lidar, T)
        want = np.sort(tree.query_ball_point(T[:3, 3], 17.0))
        order = np.lexsort(k.points_map.T)
        np.testing.assert_array_equal(k.points_map[order], pts[want][np.lexsort(pts[want].T)])
        assert k.intensity is None


def test_keyframe_selection_follows_distance():
    pts, inten = _corridor()
    traj = _walk(n=50)  # ~1 m apart
    kfs = list(keyframes_from_global_map(pts, inten, traj, sensor_range_m=10.0,
                                         keyframe_distance_m=4.5, keyframe_angle_deg=90.0))
    xs = np.array([k.position[0] for k in kfs])
    assert kfs[0].index == 0 and 9 <= len(kfs) <= 12
    assert np.all(np.diff(xs) > 4.0)
    for k in kfs:  # every crop within range, intensities carried
        assert np.linalg.norm(k.points_map - k.position, axis=1).max() <= 10.0
        np.testing.assert_allclose(k.intensity, (k.points_map[:, 0] * 10 % 255), atol=1e-3)


@pytest.mark.parametrize("fmt", ["tum", "kitti"])
def test_block_map_from_global_pcd(tmp_path, fmt):
    pts, inten = _corridor()
    gpath = write_point_cloud(tmp_path / "global.pcd", pts, intensity=inten,
                              encoding="binary_compressed")
    traj = _walk(n=25, length=35.0)
    tpath = tmp_path / f"poses.{fmt}"
    (write_tum if fmt == "tum" else write_kitti)(tpath, traj)
    store = build_map_from_global_pcd(gpath, tpath, "block", tmp_path / "blocks",
                                      sensor_range_m=12.0, keyframe_distance_m=2.0,
                                      block_size_m=10.0, voxel_size_m=VOXEL, frame_name="camera_init")
    assert store.kind == "block" and len(store.entries) >= 3
    assert store.params["trajectory_frame"] == "camera_init"
    assert store.params["sensor_range_m"] == 12.0
    vox = lambda p: {tuple(v) for v in np.floor(np.asarray(p, float) / VOXEL).astype(np.int64)}  # noqa: E731
    # the blocks together hold exactly the map within 12 m of the keyframes, and nothing else
    kf_pos = np.concatenate([e.keyframes for e in store.entries])
    g, _ = voxel_downsample(pts, VOXEL)
    d, _ = cKDTree(kf_pos).query(g.astype(float))
    union = set().union(*(vox(store.load(e.id)[0]) for e in store.entries))
    assert union == vox(g[d <= 12.0])
    assert (d > 12.5).any()  # the corridor reaches beyond: the crop is real
    for e in store.entries:  # each block near its keyframes (Algorithm 1 unchanged)
        p, i = store.load(e.id)
        dk, _ = cKDTree(e.keyframes).query(p.astype(float))
        assert dk.max() <= 12.0 + 1e-3 and i is not None


def test_grid_map_from_global_pcd(tmp_path):
    pts, inten = _corridor()
    gpath = write_point_cloud(tmp_path / "global.ply", pts, intensity=inten)
    traj = _walk(n=10, length=25.0)
    write_tum(tmp_path / "poses.tum", traj)
    store = build_map_from_global_pcd(gpath, tmp_path / "poses.tum", "grid", tmp_path / "grid",
                                      sensor_range_m=8.0, keyframe_distance_m=1.0, tile_size_m=10.0,
                                      voxel_size_m=VOXEL, frame_name="odom")
    assert store.kind == "grid" and store.frame == "odom"
    reopened = open_map(tmp_path / "grid")
    assert reopened.frame == "odom"
    got = np.concatenate([reopened.load(e.id)[0] for e in reopened.entries])
    g, _ = voxel_downsample(pts, VOXEL)
    d, _ = cKDTree(traj.positions).query(g.astype(float))
    assert len(got) == int((d <= 8.0).sum())
    assert got[:, 0].max() < 25.0 + 8.0 + VOXEL


def test_map_and_trajectory_in_different_frames(tmp_path):
    pts, inten = _corridor(length=20.0)
    gpath = write_point_cloud(tmp_path / "g.pcd", pts, intensity=inten)
    far = Trajectory(np.arange(3.0), xyzrpy_to_T(np.full(3, 5000.0), np.arange(3.0), *np.zeros((4, 3))))
    with pytest.raises(MapError, match="no map point within 10.0 m of the trajectory"):
        build_map_from_global_pcd(gpath, far, "block", tmp_path / "b", sensor_range_m=10.0)
    with pytest.raises(MapError, match="expected block or grid"):
        build_map_from_global_pcd(gpath, far, "srt", tmp_path / "b")
    assert not (tmp_path / "b").exists()


def test_block_build_equals_algorithm_1_on_full_crops(tmp_path):
    """The builder gets each point once per block; the blocks are those of Algorithm 1 fed the
    full crops of :func:`keyframes_from_global_map`."""
    from blockloc.maps.block_maps import build_block_map

    pts, inten = _corridor()
    gpath = write_point_cloud(tmp_path / "g.pcd", pts, intensity=inten)
    traj = _walk(n=40, length=55.0)
    kw = dict(sensor_range_m=9.0, keyframe_distance_m=1.5, keyframe_angle_deg=15.0)
    store = build_map_from_global_pcd(gpath, traj, "block", tmp_path / "fast", block_size_m=8.0,
                                      voxel_size_m=VOXEL, **kw)
    g, gi = voxel_downsample(pts, VOXEL, inten)
    ref = build_block_map(keyframes_from_global_map(g.astype(float), gi, traj, **kw),
                          block_size_m=8.0, voxel_size_m=VOXEL)
    assert len(store.entries) == len(ref.blocks) >= 4
    for e, b in zip(store.entries, ref.blocks):
        p, _ = store.load(e.id)
        assert len(p) == len(b.points)
        np.testing.assert_allclose(np.sort(p, axis=0), np.sort(b.points, axis=0), atol=1e-4)
        np.testing.assert_allclose(e.centroid, b.centroid, atol=1e-3)
