"""The build plan (serial) against the in-memory Algorithm 1, and the ledger's waiting rule."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.errors import MapError
from blockloc.maps.block_maps import BlockLedger, BlockMapBuilder, VoxelAccumulator, write_block_map
from blockloc.maps.build_plan import Drive, build_map_from_drives
from blockloc.maps.grid_tiles import GridMapBuilder, tile_bounds
from blockloc.maps.mapping import mapping_keyframes
from blockloc.maps.store import open_map
from blockloc.voxels import voxel_downsample

from .synthetic import MemorySequence, route, world_points


@pytest.fixture(scope="module")
def world():
    return world_points(extent=(-40, 170), seed=8, density=0.25)


@pytest.fixture(scope="module")
def loop_seq(world):
    """Out, and back on a road 8 m away: new blocks and merges."""
    traj = route([[0, 0], [120, 0], [120, 8], [0, 8]], speed=4.0)
    return MemorySequence(world, traj, radius=22.0, name="loop")


def test_plan_blocks_equal_the_in_memory_builder(tmp_path, world, loop_seq, monkeypatch):
    """Two drives (the loop, then the loop again an hour later: its blocks are skipped) through
    the plan and through BlockMapBuilder: the same entries and manifest, byte for byte."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    again = MemorySequence(world, route([[0, 0], [120, 0], [120, 8], [0, 8]], speed=4.0, t0=3700.0),
                           radius=22.0, name="again")
    kw = dict(keyframe_distance_m=2.0, keyframe_angle_deg=15.0)
    stats: dict = {}
    plan = build_map_from_drives([Drive.of(again), Drive.of(loop_seq)], "block", tmp_path / "plan",
                                 block_size_m=30.0, voxel_size_m=0.3, stats=stats, **kw)
    ev = plan.params["events"]
    assert ev["merge"] >= 1 and ev["skip"] >= 1  # the route exercises every decision
    tasks = stats["tasks"]  # candidates read in several runs of keyframes each
    assert tasks["run"]["count"] > tasks["candidate"]["count"] >= 4
    builder = BlockMapBuilder(30.0, 0.3)
    key = 0
    for seq in (loop_seq, again):  # the plan's order: first stamp first
        for kf in mapping_keyframes(seq, **kw):
            builder.add(key, kf.position, kf.points_map, kf.intensity)
            key += 1
        builder.end_drive()
    builder.finish()
    params = {k: plan.params[k] for k in ("sequence", "keyframe_distance_m", "keyframe_angle_deg",
                                          "deskew", "drives", "mounting_source")}
    ref = write_block_map(builder, tmp_path / "memory", params=params)
    assert [(e.id, e.sha256) for e in plan.entries] == [(e.id, e.sha256) for e in ref.entries]
    assert (tmp_path / "plan" / "manifest.json").read_bytes() == (tmp_path / "memory" / "manifest.json").read_bytes()


@pytest.mark.parametrize("with_intensity", [True, False])
def test_accumulator_runs_give_the_voxel_means_of_all_points(with_intensity):
    """Summing keyframes in runs of 3 or all at once: the same voxels, in the same order, each
    the mean of all its points (voxel_downsample of the float32 points); intensity only when
    every keyframe has it."""
    rng = np.random.default_rng(3)
    clouds = [(rng.uniform(-5, 5, (400, 3)), rng.uniform(0, 1, 400)) for _ in range(10)]
    if not with_intensity:
        clouds[4] = (clouds[4][0], None)
    clouds[2][0][7] = np.nan  # dropped
    results = []
    for run in (3, 100):
        acc = VoxelAccumulator(0.5, keyframes_per_run=run)
        for pts, inten in clouds:
            acc.add(pts, inten)
        results.append(acc.result())
    pts = np.concatenate([p for p, _ in clouds]).astype(np.float32)
    inten = np.concatenate([np.zeros(len(p)) if i is None else i for p, i in clouds])
    ref, ref_i = voxel_downsample(pts, 0.5, inten)
    for p, i in results:
        assert p.dtype == np.float32 and len(p) == len(ref)
        np.testing.assert_allclose(p, ref, atol=1e-5)
        if with_intensity:
            np.testing.assert_allclose(i, ref_i, atol=1e-5)
        else:
            assert i is None


@pytest.mark.parametrize("pending", [10**9, 1500, 1])
def test_accumulator_adds_runs_up_to_the_same_bytes_as_one_merge_per_run(monkeypatch, pending):
    """The accumulator merges its runs in one pass (or whenever ``PENDING_RECORDS`` are held):
    the same bytes as merging each run into the block as it arrives, which maps built before
    hold (each voxel's sums are added in the same order)."""
    import blockloc.maps.block_maps as bm
    from blockloc.maps.block_maps import keyframe_run_sums
    from blockloc.maps.grid_tiles import merge_voxel_sums

    monkeypatch.setattr(bm, "PENDING_RECORDS", pending)
    rng = np.random.default_rng(5)
    runs = [keyframe_run_sums([(rng.normal(k, 2.0, (700, 3)), rng.uniform(0, 1, 700))], 0.3)[0]
            for k in range(9)]
    one_by_one = runs[0]
    for r in runs[1:]:
        one_by_one = merge_voxel_sums([one_by_one, r], 0.3)
    acc = VoxelAccumulator(0.3)
    for r in runs:
        acc.add_run(r, True)
    pts, inten = acc.result()
    n = one_by_one["count"].astype(np.float64)
    assert pts.tobytes() == (one_by_one["sum"][:, :3] / n[:, None]).astype(np.float32).tobytes()
    assert inten.tobytes() == (one_by_one["sum"][:, 3] / n).astype(np.float32).tobytes()
    assert acc._sums.tobytes() == one_by_one.tobytes()


def test_plan_grid_holds_the_voxel_filter_of_the_union(tmp_path, loop_seq):
    kw = dict(keyframe_distance_m=2.0, keyframe_angle_deg=15.0)
    plan = build_map_from_drives([Drive.of(loop_seq)], "grid", tmp_path / "plan", tile_size_m=10.0,
                                 voxel_size_m=0.3, chunk_keyframes=7, **kw)
    # the in-memory builder sums the same voxels scan by scan: same voxels, same centroids
    gb = GridMapBuilder(10.0, 0.3)
    for k in mapping_keyframes(loop_seq, **kw):
        gb.add(k.points_map, k.intensity)
    ref = gb.finish(tmp_path / "memory")
    assert plan.ids == ref.ids
    for eid in plan.ids:
        p, i = plan.load(eid)
        q, j = ref.load(eid)
        np.testing.assert_allclose(p, q, atol=1e-4)
        np.testing.assert_allclose(i, j, atol=1e-4)
        lo, hi = tile_bounds(eid, 10.0)
        assert np.all(p[:, :2] >= lo) and np.all(p[:, :2] < hi)
    # and a chunk size is a plan parameter: recorded, and the voxels do not depend on it
    other = build_map_from_drives([Drive.of(loop_seq)], "grid", tmp_path / "c32", tile_size_m=10.0,
                                  voxel_size_m=0.3, **kw)
    assert plan.params["chunk_keyframes"] == 7 and other.params["chunk_keyframes"] == 32
    assert other.total_points == plan.total_points


def test_ledger_waits_only_for_a_held_block_that_could_be_nearest():
    led = BlockLedger(100.0)
    led.decide([0], [0.0, 0.0, 0.0])
    led.decide([1], [300.0, 0.0, 0.0])
    led.decide([2], [320.0, 0.0, 0.0])  # 20 m from block 1: a merge
    assert led.events[-1].action == "merge" and led.events[-1].block == 1
    led.hold(1, np.array([290.0, -5, -5]), np.array([330.0, 5, 5]))
    waited = []

    def resolve(blocks):
        waited.extend(blocks)
        for j in blocks:
            led.renew(j, [310.0, 0.0, 0.0])

    ev = led.decide([3], [5.0, 0.0, 0.0], resolve=resolve)  # near block 0: block 1 cannot be nearest
    assert waited == [] and ev.action == "skip" and ev.block == 0
    ev = led.decide([4], [340.0, 0.0, 0.0], resolve=resolve)  # near the held box: must wait
    assert waited == [1] and ev.block == 1 and ev.distance_m == pytest.approx(30.0)
    with pytest.raises(MapError, match="block size"):
        BlockLedger(0)


def test_plan_rejects_bad_input_before_writing(tmp_path, loop_seq):
    with pytest.raises(MapError, match="no mapping drive"):
        build_map_from_drives([], "block", tmp_path / "m")
    with pytest.raises(MapError, match="kind"):
        build_map_from_drives([Drive.of(loop_seq)], "tiles", tmp_path / "m")
    with pytest.raises(MapError, match="frame range|no LiDAR frame"):
        build_map_from_drives([Drive.of(loop_seq, start=10_000)], "block", tmp_path / "m")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(MapError):
        open_map(tmp_path / "m")


def test_open_drive_task_prepares_a_simulated_drive():
    """A worker opening a drive ahead of its scan tasks builds the simulated scene then, not in
    its first scan task."""
    from blockloc.maps.build_tasks import forget_drives, open_drive_task
    from blockloc.sim.stream import open_sim_sequence

    seq = open_sim_sequence("small", "map", 1)
    drive = Drive.of(seq, stop=20)
    assert seq._scene is None
    try:
        open_drive_task(drive)
        assert seq._scene is not None
    finally:
        forget_drives([drive])


def test_a_worker_keeps_a_remounted_drive_and_its_inner_one_as_one(loop_seq, monkeypatch):
    """The opened-drive cache counts a drive read with an estimated mounting and the drive it wraps
    as one: alternating between two remounted drives reopens neither (with a cap of two)."""
    import blockloc.maps.build_tasks as bt

    opens = []

    class Opener:
        def __init__(self, name):
            self.name = name

        def __call__(self):
            opens.append(self.name)
            return loop_seq

    monkeypatch.setattr(bt, "_OPENED", type(bt._OPENED)())
    monkeypatch.setattr(bt, "_OPENED_MAX", 2)
    a, b, c = (Drive(n, Opener(n), f"key-{n}") for n in "abc")
    ra, rb = bt.remounted(a, np.eye(4)), bt.remounted(b, np.eye(4))
    for _ in range(3):
        bt._opened(ra)
        bt._opened(rb)
    assert opens == ["a", "b"]
    bt._opened(a)  # the inner drive: already open
    assert opens == ["a", "b"]
    bt._opened(c)  # a third drive drops the least recently read one, with its remounted reading
    assert opens == ["a", "b", "c"] and set(bt._OPENED) == {"key-a", "key-a|" + ra.key.split("|")[1], "key-c"}
    bt._opened(rb)
    assert opens[-1] == "b"


def test_each_worker_opens_the_drive_its_share_starts_in(tmp_path, world, loop_seq):
    """The warm-up opens one drive a worker, spread over the drives in the order given (every
    drive on every worker kept each drive's poses and scene data in every worker), and the
    build is the serial one byte for byte."""
    from blockloc.maps.build_plan import InlineExecutor

    class TwoWorkers(InlineExecutor):
        opened: list = []

        def on_each_worker(self, fn, args_of, *, key):
            self.opened = [args_of(i, 2)[0] for i in range(2)]
            return [self.submit(fn, *args) for args in (args_of(i, 2) for i in range(2))]

    drives = [Drive.of(loop_seq, stop=n, name=f"d{n}") for n in (40, 60, 80, 100, 120)]
    ex = TwoWorkers()
    warmed = build_map_from_drives(drives, "block", tmp_path / "w", block_size_m=30.0, executor=ex)
    assert [d.name for d in ex.opened] == ["d40", "d80"]
    serial = build_map_from_drives(drives, "block", tmp_path / "s", block_size_m=30.0)
    assert [e.sha256 for e in warmed.entries] == [e.sha256 for e in serial.entries]
