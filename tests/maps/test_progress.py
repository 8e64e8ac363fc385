"""The core map builders report progress through a ``(done, total)`` callback (the commands draw
the bar): one call per item handled, counting up to the number of items the build produced."""

from __future__ import annotations

import numpy as np

from blockloc.datasets.pointclouds import write_point_cloud
from blockloc.trajectory_io import write_tum
from blockloc.geometry import Trajectory, xyzrpy_to_T
from blockloc.maps.from_pcd import build_map_from_global_pcd, keyframes_from_global_map
from blockloc.maps.grid_tiles import tile_global_map
from blockloc.maps.mapping import mapping_keyframes

from .synthetic import MemorySequence, route, world_points


class Calls(list):
    def __call__(self, done: int, total: int) -> None:
        self.append((done, total))


def assert_counts_up(calls: Calls, n: int) -> None:
    """Calls (1, n), (2, n), ..., (n, n): increasing by one, to the total, which is ``n``."""
    assert n > 1
    assert calls == [(k, n) for k in range(1, n + 1)]


def test_mapping_keyframes_counts_each_keyframe_once_handled():
    seq = MemorySequence(world_points(extent=(-10, 40), seed=1, density=0.05),
                         route([[0, 0], [30, 0]], speed=5.0), radius=10.0)
    calls = Calls()
    seen = []
    for kf in mapping_keyframes(seq, keyframe_distance_m=3.0, keyframe_angle_deg=90.0, progress=calls):
        seen.append(len(calls))  # the keyframe being handled is not counted yet
        assert len(kf.points_map) > 0
    assert seen == list(range(len(seen)))
    assert_counts_up(calls, len(seen))


def test_tile_global_map_counts_tiles(tmp_path):
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 6, (600, 2)), rng.uniform(0, 1, 600)]
    calls = Calls()
    store = tile_global_map(pts, None, 2.0, tmp_path / "g", progress=calls)
    assert_counts_up(calls, len(store.entries))
    assert len(store.entries) == 9


def _corridor_and_walk(tmp_path):
    xs, ys = np.meshgrid(np.arange(0.0, 30.0, 0.5), np.arange(-3.0, 3.0, 0.5), indexing="ij")
    pts = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)] + 0.01
    gpath = write_point_cloud(tmp_path / "g.pcd", pts)
    x = np.linspace(1.0, 25.0, 13)
    traj = Trajectory(np.arange(13.0), xyzrpy_to_T(x, 0 * x, 0 * x + 1.0, 0 * x, 0 * x, 0 * x))
    write_tum(tmp_path / "poses.tum", traj)
    return pts, gpath, traj


def test_from_pcd_counts_keyframes(tmp_path):
    pts, gpath, traj = _corridor_and_walk(tmp_path)
    kw = dict(sensor_range_m=6.0, keyframe_distance_m=3.9, keyframe_angle_deg=90.0)
    n = len(list(keyframes_from_global_map(pts, None, traj, **kw)))
    for kind in ("block", "grid"):
        calls = Calls()
        build_map_from_global_pcd(gpath, tmp_path / "poses.tum", kind, tmp_path / kind, block_size_m=8.0,
                                  tile_size_m=5.0, voxel_size_m=0.5, progress=calls, **kw)
        assert_counts_up(calls, n)


def test_a_build_shows_all_tasks_done_only_at_its_end(tmp_path):
    """A build plans each stage's tasks from the last one's results, so its total grows; the bar
    must not read ``done == total`` (100%) until the build has finished."""
    from blockloc.maps.build_plan import Drive, build_map_from_drives

    seq = MemorySequence(world_points(extent=(-30, 110), seed=6, density=0.2),
                         route([[0, 0], [80, 0], [80, 30]], speed=4.0), radius=20.0)
    calls = Calls()
    store = build_map_from_drives([Drive.of(seq)], "block", tmp_path / "m", block_size_m=30.0,
                                  voxel_size_m=0.3, keyframe_distance_m=2.0, progress=calls)
    assert len(store.entries) > 1
    totals = sorted({t for _, t in calls})
    assert len(totals) > 1  # the plan did grow while the build ran
    assert calls[-1][0] == calls[-1][1]  # the end: every task that ran is done
    assert all(d < t for d, t in calls[:-1]), calls
