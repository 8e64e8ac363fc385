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


def test_the_pool_hands_frames_back_in_order_across_chunks_and_runs(tmp_path):
    from blockloc.datasets.nclt import encode_frame

    import resource
    from multiprocessing import forkserver

    p = get_preset("tiny", azimuth_steps=64)
    seq = open_sim_sequence("tiny", "loc", 2, azimuth_steps=64)
    ref_map = open_sim_sequence("tiny", "map", 2, azimuth_steps=64)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with FramePool(2) as pool:
        # 21 frames: three chunks, the last short
        got = list(pool.frames(p, "loc", 2, 3, 3 + 21))
        # two runs, the second's chunks queued behind the first's (both in the workers at once),
        # encoded there
        loc, mapped = pool.runs(p, 2, [("loc", 20, 30), ("map", 5, 5 + 11)], encode=True)
        enc_loc, enc_map = list(loc), list(mapped)
        # the same frames written by the workers into a directory: where they are comes back
        (written,) = pool.runs(p, 2, [("loc", 20, 30)], encode=True, write_to=[tmp_path])
        written = list(written)
    # the workers' fork server is stopped and reaped with the pool: its CPU and its workers' (the
    # imports, 42 frames) count as this process's children's, as spawned workers' did
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert forkserver._forkserver._forkserver_pid is None
    assert after.ru_utime - before.ru_utime > 0.5
    assert [f.index for f in got] == list(range(3, 24))
    for f in (got[0], got[9], got[-1]):
        ref = seq.frame(f.index)
        assert f.stamp == ref.stamp
        for x, y in ((f.points, ref.points), (f.intensity, ref.intensity), (f.ring, ref.ring),
                     (f.time_offsets, ref.time_offsets)):
            assert x.dtype == y.dtype and np.array_equal(x, y)
    assert [f.index for f in enc_loc] == list(range(20, 30)) and [f.index for f in enc_map] == list(range(5, 16))
    assert enc_loc[3] == encode_frame(got[-1]) and enc_map[-1] == encode_frame(ref_map.frame(15))
    assert len(enc_map[-1].hits) > len(enc_map[-1].sync) > 0
    # written there: each frame's sync file holds its bytes, the hits come back as bytes (the
    # chunks' hits files read and removed), nothing else is left
    assert [(w.index, w.stamp, w.utime, w.dropped) for w in written] == [
        (e.index, e.stamp, e.utime, e.dropped) for e in enc_loc]
    for w, e in zip(written, enc_loc):
        assert w.sync == tmp_path / f"{e.utime}.bin" and w.sync.read_bytes() == e.sync
        assert bytes(w.hits) == e.hits
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"{e.utime}.bin" for e in enc_loc)


def _encode_before(frame):
    """write_session's encoding of a frame as 2af77ae did it (a structured array filled field by
    field, then sorted by time): the reference :func:`encode_frame` is held to."""
    from blockloc.datasets.nclt import NCLT_POINT_DTYPE, NCLT_POINT_OFFSET, NCLT_POINT_SCALE, _hits_packets

    pts = np.asarray(frame.points, dtype=np.float64).reshape(-1, 3)
    q = np.rint((pts - NCLT_POINT_OFFSET) / NCLT_POINT_SCALE)
    keep = np.isfinite(q).all(axis=1) & (q >= 0).all(axis=1) & (q <= 65535).all(axis=1)
    q = q[keep].astype(np.uint16)
    raw = np.zeros(len(q), dtype=NCLT_POINT_DTYPE)
    raw["x"], raw["y"], raw["z"] = q[:, 0], q[:, 1], q[:, 2]
    if frame.intensity is not None:
        inten = np.nan_to_num(np.asarray(frame.intensity, dtype=np.float64)[keep])
        raw["intensity"] = np.clip(np.rint(inten), 0, 255).astype(np.uint8)
    if frame.ring is not None:
        raw["laser_id"] = np.clip(np.asarray(frame.ring)[keep], 0, 255).astype(np.uint8)
    utime = int(round(frame.stamp * 1e6))
    if frame.time_offsets is not None:
        t_us = utime + np.rint(np.asarray(frame.time_offsets, np.float64)[keep] * 1e6).astype(np.int64)
    else:
        t_us = np.full(len(raw), utime, dtype=np.int64)
    unsorted = raw.tobytes()  # what encode_points gave
    order = np.argsort(t_us, kind="stable")
    raw, t_us = raw[order], t_us[order]
    return utime, raw.tobytes(), _hits_packets(raw.view("<u8"), t_us), int((~keep).sum()), unsorted, keep


def test_encoding_a_frame_gives_the_bytes_write_session_wrote_before():
    """``encode_frame`` (words built at once; no sort when the times are in order) against the
    encoding it replaced: a simulated scan as it is, and drawn frames with what the format cannot
    hold (NaN, inf, out of range), intensities to clip or NaN, rings above 255, times out of order
    and tied, float32 and float64 points, no times / intensity / ring."""
    from blockloc.datasets.base import LidarFrame
    from blockloc.datasets.nclt import NCLT_POINT_DTYPE, encode_frame, encode_points

    frames = [open_sim_sequence("tiny", "loc", 2, azimuth_steps=64).frame(7)]
    rng = np.random.default_rng(3)
    for k in range(6):
        n = 3000
        pts = rng.uniform(-130, 260, (n, 3))
        pts[rng.random((n, 3)) < 0.01] = np.nan
        pts[rng.random((n, 3)) < 0.01] = np.inf
        pts[rng.random((n, 3)) < 0.01] = -np.inf
        inten = rng.uniform(-20, 300, n).astype(np.float32)
        inten[rng.random(n) < 0.02] = np.nan
        inten[rng.random(n) < 0.01] = np.inf
        ring = rng.integers(0, 300, n).astype(np.uint16)
        toff = np.sort(rng.uniform(0, 0.1, n)).astype(np.float32) if k % 2 else \
            np.round(rng.uniform(-0.01, 0.1, n), 4).astype(np.float32)  # unsorted, with ties
        frames.append(LidarFrame(k, 1e9 + k * 0.1 + 1e-7, pts.astype(np.float32) if k == 2 else pts,
                                 None if k == 3 else inten, None if k == 4 else toff, None if k == 5 else ring))
    for f in frames:
        utime, sync, hits, dropped, unsorted, keep = _encode_before(f)
        enc = encode_frame(f)
        assert (enc.utime, enc.sync, enc.hits, enc.dropped) == (utime, sync, hits, dropped)
        assert enc.index == f.index and enc.stamp == f.stamp and encode_frame(f, hits=False).hits == b""
        raw, keep_now = encode_points(f.points, f.intensity, f.ring)
        assert raw.dtype == NCLT_POINT_DTYPE and raw.tobytes() == unsorted and np.array_equal(keep_now, keep)
    assert sum(_encode_before(f)[3] for f in frames[1:]) > 100  # the drawn frames had points to drop


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
