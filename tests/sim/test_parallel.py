"""Frames rendered in worker processes (``blockloc.sim.parallel``) are the frames rendered in
the calling process, byte for byte, in order; the dataset written either way is the same."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from blockloc.sim import generate_dataset
from blockloc.sim.parallel import MIN_FRAMES_FOR_WORKERS, FramePool, default_workers
from blockloc.sim.presets import get_preset
from blockloc.sim.stream import open_sim_sequence


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_a_dataset_written_by_workers_has_the_bytes_of_one_written_in_process(tmp_path):
    here = generate_dataset("tiny", 5, tmp_path / "here", max_frames=20, azimuth_steps=120, workers=0)
    pooled = generate_dataset("tiny", 5, tmp_path / "pooled", max_frames=20, azimuth_steps=120, workers=2)
    a, b = _digest(here), _digest(pooled)
    assert len(a) > 20 and a == b


def test_the_pool_hands_frames_back_in_order_across_chunks():
    p = get_preset("tiny", azimuth_steps=64)
    seq = open_sim_sequence("tiny", "loc", 2, azimuth_steps=64)
    with FramePool(2) as pool:
        got = list(pool.frames(p, "loc", 2, 3, 3 + 21))  # 21 frames: three chunks, the last short
    assert [f.index for f in got] == list(range(3, 24))
    for f in (got[0], got[9], got[-1]):
        ref = seq.frame(f.index)
        assert f.stamp == ref.stamp
        for x, y in ((f.points, ref.points), (f.intensity, ref.intensity), (f.ring, ref.ring),
                     (f.time_offsets, ref.time_offsets)):
            assert x.dtype == y.dtype and np.array_equal(x, y)


def test_short_runs_render_in_process():
    assert default_workers(MIN_FRAMES_FOR_WORKERS - 1) == 0
    assert default_workers(10_000) in (0, 2, 3, 4)  # 0 only on a single core


def test_actor_meshes_at_once_are_the_meshes_built_one_actor_at_a_time():
    """``actor_meshes`` (a scan's actors at once) gives the vertices, triangles and order that
    ``movable_mesh`` per actor gathered in a MeshBuilder gave, bit for bit (walkers mid-stride,
    rigid walkers, vehicles): the scans stay the same."""
    from blockloc.sim.movables import actor_meshes
    from blockloc.sim.world import MeshBuilder, movable_mesh

    scene = open_sim_sequence("small", "loc", 1).scene
    actors = scene.actors
    rng = np.random.default_rng(4)
    kind = np.concatenate([actors.kind, ["pedestrian", "vehicle"]])
    for t in (0.0, 17.3, 123.45):
        xy, yaw = actors.poses(t)
        gait = actors.gait(t)
        xy = np.vstack([xy, rng.uniform(-60, 60, (2, 2))])
        yaw, gait = np.append(yaw, [0.3, -2.0]), np.append(gait, [np.nan, np.nan])
        assert np.isfinite(gait).any() and np.isnan(gait).any()
        b = MeshBuilder()
        owner = []
        for k in range(len(kind)):
            g = None if not np.isfinite(gait[k]) else float(gait[k])
            for V, F in movable_mesh(str(kind[k]), xy[k, 0], xy[k, 1], yaw[k], scene.world.terrain, gait=g):
                b.add(V, F)
                owner.append(np.full(len(F), k))
        V0, F0 = b.build()
        V1, F1, own1 = actor_meshes(kind, xy[:, 0], xy[:, 1], yaw, gait, scene.world.terrain)
        assert V0.tobytes() == V1.tobytes() and np.array_equal(F0, F1)
        assert np.array_equal(np.concatenate(owner), own1)
