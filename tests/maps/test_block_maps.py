"""Block maps (Algorithm 1) on synthetic routes: coverage, merges, skips, the released code's bugs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from blockloc.errors import MapError
from blockloc.geometry import xyzrpy_to_T
from blockloc.maps.block_maps import BlockMapBuilder, build_block_map
from blockloc.maps.build_plan import build_block_map_from_sequence, build_grid_map_from_sequence
from blockloc.maps.grid_tiles import tile_bounds
from blockloc.maps.mapping import scan_to_map, select_keyframes
from blockloc.maps.store import open_map

from .synthetic import MemorySequence, route, world_points


def _kf(x, y=0.0, z=0.0, n=20, seed=0):
    """A keyframe at (x, y, z) with a small blob of points around it (map frame)."""
    rng = np.random.default_rng(seed)
    pts = np.array([x, y, z]) + rng.normal(0, 1.0, (n, 3))
    return xyzrpy_to_T(x, y, z, 0, 0, 0), pts


def test_closing_keyframe_kept_in_both_blocks():
    b = BlockMapBuilder(block_size_m=10.0, voxel_size_m=0.0)
    for i, x in enumerate(np.arange(0, 25.0, 1.0)):
        T, pts = _kf(x, seed=i)
        b.add(i, T[:3, 3], pts)
    blocks = b.finish()
    # keyframe 11 (x=11 > 10 from x=0) closes block 0 and opens block 1
    assert blocks[0].keyframes[-1] == 11 and blocks[1].keyframes[0] == 11
    covered = set().union(*(blk.keyframes for blk in blocks))
    assert covered == set(range(25))


def test_second_block_checked_against_first():
    """Out and back on the same road: the return block repeats block 0 and must not be a new block
    (the released code adds the second block without the KD-tree check)."""
    b = BlockMapBuilder(block_size_m=50.0, voxel_size_m=0.0)
    xs = list(np.arange(0, 56.0, 1.0)) + list(np.arange(54.0, -1.0, -1.0))
    for i, x in enumerate(xs):
        b.add(i, [x, 0, 0], _kf(x, seed=i)[1])
    b.finish()
    assert len(b.blocks) == 1
    # the return's centroid is 3.7 m (< 0.1 S = 5 m) from block 0's: a skip
    assert [e.action for e in b.events] == ["new", "skip"]
    assert b.events[1].block == 0 and b.events[1].distance_m < 0.1 * 50.0


def test_distance_is_3d():
    """A ramp: 30 m horizontally but 60 m up must close a 50 m block (2D distance would not)."""
    b = BlockMapBuilder(block_size_m=50.0, voxel_size_m=0.0)
    ramp = np.linspace(0, 1, 61)
    for i, s in enumerate(ramp):
        b.add(i, [30 * s, 0, 60 * s], _kf(30 * s, 0, 60 * s, seed=i)[1])
    b.finish()
    first_far = int(np.argmax(np.hypot(30 * ramp, 60 * ramp) > 50.0))
    assert b.events[0].action == "new" and b.events[0].keyframes[-1] == first_far
    assert b.blocks[0].keyframes[-1] == 60  # the short rest is appended, nothing dropped


def test_merge_and_new_by_centroid_distance():
    S = 40.0
    b = BlockMapBuilder(block_size_m=S, voxel_size_m=0.0)
    xs = np.arange(0, 121.0, 1.0)
    k = 0
    for x in xs:  # outbound along y=0
        b.add(k, [x, 0, 0], _kf(x, 0, seed=k)[1]); k += 1
    for x in xs[::-1]:  # back along a parallel road 10 m away: 0.1 S < d < 0.5 S -> merges
        b.add(k, [x, 10, 0], _kf(x, 10, seed=k)[1]); k += 1
    b.finish()
    actions = [e.action for e in b.events]
    # out: blocks at x 0..41 and 41..82; the third (82 -> 120 -> back to 42 on the parallel road)
    # is 27 m from its nearest centroid -> new; the return 42 -> 0 lies 10 m from block 0 -> merge;
    # the two last keyframes are a short tail appended to block 0
    assert actions == ["new", "new", "new", "merge", "tail"]
    assert b.events[3].block == 0 and b.events[4].block == 0
    for e in b.events:
        if e.action == "merge":
            assert 0.1 * S < e.distance_m < 0.5 * S
    # merged centroids moved toward the parallel road
    assert any(blk.centroid[1] > 1.0 for blk in b.blocks)


def test_empty_and_bad_input():
    with pytest.raises(MapError, match="no keyframes"):
        build_block_map([])
    with pytest.raises(MapError, match="block size"):
        BlockMapBuilder(block_size_m=0)


def test_select_keyframes_distance_and_angle():
    T = xyzrpy_to_T(np.array([0, 0.5, 1.2, 1.3, 1.3]), 0, 0, 0, 0, np.deg2rad([0, 0, 0, 0, 20]))
    assert select_keyframes(T, 1.0, 15.0).tolist() == [0, 2, 4]


def test_deskew_uses_per_point_times():
    """A point seen at the end of the sweep is placed with the pose at that time."""
    traj = route([[0, 0], [100, 0]], speed=10.0, rate=10.0)
    pts = np.array([[5.0, 0, 0], [5.0, 0, 0]])
    out = scan_to_map(pts, np.array([0.0, 0.1]), traj.stamps[3], traj, np.eye(4))
    x0 = traj.poses[3, 0, 3]
    np.testing.assert_allclose(out[:, 0], [x0 + 5.0, x0 + 6.0], atol=0.05)


def test_block_map_from_sequence_covers_every_keyframe(tmp_path):
    world = world_points(extent=(-40, 200), seed=1, density=0.3)
    traj = route([[0, 0], [160, 0], [160, 8], [0, 8]], speed=4.0, rate=10.0)
    T_body_lidar = xyzrpy_to_T(0.1, 0, 0.5, 0, 0, 0.02)
    seq = MemorySequence(world, traj, radius=25.0, T_body_lidar=T_body_lidar)
    store = build_block_map_from_sequence(seq, block_size_m=50.0, keyframe_distance_m=4.0,
                                          keyframe_angle_deg=30.0, voxel_size_m=0.3,
                                          out=tmp_path / "bm")
    assert store.kind == "block" and len(store.entries) >= 3
    ev = store.params["events"]
    assert ev["new"] == len(store.entries) and ev["merge"] + ev["skip"] >= 1  # the route revisits
    # every keyframe's points end up in some block (within a voxel)
    tree = cKDTree(store.load_points(store.ids))
    kf_idx = select_keyframes(traj.poses @ T_body_lidar, 4.0, 30.0)
    for i in kf_idx[::5]:
        f = seq.frame(int(i))
        pm = scan_to_map(f.points, None, f.stamp, traj, T_body_lidar)
        d, _ = tree.query(pm)
        assert np.mean(d < 0.6) > 0.99, i
    # every keyframe position is recorded with the block that was built from it or covers it
    # (a closing keyframe belongs to two blocks)
    kf_pos = np.concatenate([e.keyframes for e in open_map(tmp_path / "bm").entries])
    assert len(np.unique(kf_pos, axis=0)) == store.params["num_keyframes"]
    # the released layout is there too
    assert (tmp_path / "bm" / "CentroidCloud.pcd").exists()
    assert (tmp_path / "bm" / "000.pcd").exists()


def test_grid_map_from_sequence(tmp_path):
    world = world_points(extent=(-40, 80), seed=2, density=0.3)
    traj = route([[0, 0], [40, 0]], speed=4.0)
    seq = MemorySequence(world, traj, radius=20.0)
    store = build_grid_map_from_sequence(seq, tile_size_m=10.0, keyframe_distance_m=3.0,
                                         voxel_size_m=0.5, out=tmp_path / "g")
    assert store.kind == "grid" and len(store.entries) > 10
    for e in store.entries[:5]:
        lo, hi = tile_bounds(e.id, 10.0)
        p, _ = store.load(e.id)
        assert np.all(p[:, :2] >= lo) and np.all(p[:, :2] < hi)


def test_sequence_without_poses_or_frames(tmp_path):
    world = world_points(extent=(0, 20), seed=0, density=0.1)
    traj = route([[0, 0], [10, 0]])
    with pytest.raises(MapError, match="no mapping poses"):
        build_block_map_from_sequence(MemorySequence(world, traj, with_poses=False), out=tmp_path / "a")
    empty = MemorySequence(world, traj)
    empty.traj = type(traj)(np.zeros(0), np.zeros((0, 4, 4)))
    with pytest.raises(MapError, match="empty session"):
        build_grid_map_from_sequence(empty, out=tmp_path / "b")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    with pytest.raises(MapError, match="tile size"):
        build_grid_map_from_sequence(MemorySequence(world, traj), tile_size_m=-1, out=tmp_path / "c")


def test_open_written_block_map(tmp_path):
    kfs = [_kf(x, seed=int(x)) for x in np.arange(0, 30.0, 1.0)]
    store = build_block_map(kfs, block_size_m=10.0, voxel_size_m=0.0, out=tmp_path / "m")
    again = open_map(tmp_path / "m")
    assert again.ids == store.ids and len(again.ids) == 3
    np.testing.assert_allclose(again.centroids(), store.centroids())


def test_scan_to_map_matches_per_point_poses_on_a_long_trajectory():
    """Windowed, binned deskew == every point moved with its own interpolated pose (to < 1 cm)."""
    traj = route([[0, 0], [300, 0], [300, 300]], speed=2.0, rate=100.0)  # 30k poses
    rng = np.random.default_rng(0)
    pts = rng.uniform(-30, 30, (500, 3))
    dt = rng.uniform(-0.05, 0.05, 500)
    T_bl = xyzrpy_to_T(0.2, 0.1, 0.4, 0.01, -0.02, 0.3)
    # (not at the corner, where this synthetic route turns 90 degrees between two poses)
    for stamp in (traj.stamps[10], traj.stamps[7000], traj.stamps[22000], traj.stamps[-10]):
        got = scan_to_map(pts, dt, stamp, traj, T_bl)
        Ts = traj.interpolate(stamp + dt) @ T_bl
        want = np.einsum("nij,nj->ni", Ts[:, :3, :3], pts) + Ts[:, :3, 3]
        assert np.abs(got - want).max() < 0.01


@pytest.mark.parametrize("kind", ["block", "grid"])
def test_build_interrupted_half_way_leaves_no_map(tmp_path, kind):
    """A scan read that fails half way through the session: no output directory, no temp dir."""
    world = world_points(extent=(-30, 90), seed=4, density=0.2)
    traj = route([[0, 0], [60, 0]], speed=5.0)
    seq = MemorySequence(world, traj, radius=20.0)
    good_frame = seq.frame

    def failing(i):
        if i > len(traj) // 2:
            raise OSError("disk unplugged")
        return good_frame(i)

    seq.frame = failing
    build = build_block_map_from_sequence if kind == "block" else build_grid_map_from_sequence
    with pytest.raises(OSError, match="unplugged"):
        build(seq, keyframe_distance_m=2.0, out=tmp_path / "m")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(MapError):
        open_map(tmp_path / "m")


@pytest.mark.parametrize("fraction, action", [
    (0.0, "skip"), (0.09, "skip"), (0.11, "merge"), (0.25, "merge"), (0.49, "merge"), (0.51, "new"),
    (0.9, "new"),
])
def test_centroid_distance_boundaries(fraction, action):
    """Block 0's centroid is the origin; the closed candidate block's centroid lies exactly
    ``fraction`` x S from it: d <= 0.1 S skip, 0.1 S < d < 0.5 S merge, d >= 0.5 S new."""
    S = 10.0
    b = BlockMapBuilder(block_size_m=S, voxel_size_m=0.0)
    cube = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    none = np.zeros((0, 3))
    b.add(0, [0, 0, 0], cube)  # block 0: these points only, centroid (0, 0, 0)
    b.add(1, [S + 1, 0, 0], none)  # closes block 0 (no points of its own) and opens block 1
    b.add(2, [S + 1, 0, 0], cube * 0.5 + [fraction * S, 0, 0])  # block 1's only points
    b.add(3, [2 * S + 2, 0, 0], none)  # closes block 1
    assert [e.action for e in b.events[:1]] == ["new"]
    ev = b.events[1]
    assert ev.keyframes == [1, 2, 3]
    assert ev.distance_m == pytest.approx(fraction * S, abs=1e-5)
    assert ev.action == action and ev.block == (1 if action == "new" else 0)
    if action == "merge":  # the merged block's centroid is renewed from all its points
        np.testing.assert_allclose(b.blocks[0].centroid, [fraction * S / 2, 0, 0], atol=1e-5)
    if action == "skip":
        assert len(b.blocks) == 1 and len(b.blocks[0].points) == 8
