"""Change detection fed a frame at a time (:class:`ChangeDetector`, what ``track --detect-changes``
runs while tracking) against the after-the-fact :func:`detect_changes` on the same frames and
poses, on the synthetic street of ``tests/maps/lifelong_world.py`` (a wall and a car removed, a
box added, a pedestrian)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from blockloc.maps.changes.pipeline import ChangeDetector, detect_changes
from blockloc.maps.changes.runs import TrustedFrames, read_run, trusted_mask
from tests.maps import lifelong_world as W


def test_trusted_frames_one_at_a_time_is_the_run_folders_rule():
    """The streaming rule (what track and the node feed) against the rule written out: a frame is
    trusted when it and the settle_frames frames before it are all ok."""
    rng = np.random.default_rng(3)
    for settle in (0, 1, 3, 10):
        for _ in range(20):
            statuses = list(rng.choice(["ok", "ok", "ok", "ok", "lost", "rejected", "recovered", "skipped"], 60))
            rule = TrustedFrames(settle)
            expected = [k >= settle and all(x == "ok" for x in statuses[k - settle:k + 1])
                        for k in range(len(statuses))]
            assert [rule(s) for s in statuses] == expected
            assert trusted_mask(statuses, settle).tolist() == expected


class _Cached:
    """The run day's frames cast once (both detectors read the same frames)."""

    def __init__(self, seq):
        self.inner, self.info, self.cache, self.reads = seq, seq.info, {}, []

    def __len__(self):
        return len(self.inner)

    def frame(self, i):
        self.reads.append(i)
        if i not in self.cache:
            self.cache[i] = self.inner.frame(i)
        return self.cache[i]


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    d = tmp_path_factory.mktemp("live")
    T = W.drive(1.0)
    store = W.build_map(d / "map", T)
    # a loss half-way: the frames after it are not trusted until 2 ok frames came again
    statuses = ["ok"] * len(T)
    statuses[20:23] = ["rejected", "lost", "recovered"]
    run = W.write_run(d / "run", d / "seq", T, statuses)
    return store, T, statuses, run, _Cached(W.ArraySequence("run", T))


def test_fed_frame_by_frame_it_finds_what_the_finished_run_shows(street):
    store, T, statuses, run, seq = street
    opts = dict(max_range_m=12.0, stride=2)
    reads = len(seq.reads)
    after = detect_changes(store, seq, read_run(run, settle_frames=2), **opts)
    # the after-the-fact loop reads only the frames it uses
    assert len(seq.reads) - reads == after.scans_used + after.scans_rejected == (after.frames_trusted + 1) // 2
    det = ChangeDetector(store, np.eye(4), seq.info.gravity_map, **opts)
    rule = TrustedFrames(2)
    loaded = []
    stamps = 1000.0 + 0.1 * np.arange(len(T))
    for i, (T_i, status) in enumerate(zip(T, statuses)):
        trusted = rule(status)
        det.add(stamps[i], T_i, trusted, seq.frame(i) if trusted else None)
        loaded.append(sorted(det.blocks))
    live = det.result()
    # the same document and the same voxels, new points and all
    assert json.dumps(live.to_json(), sort_keys=True) == json.dumps(after.to_json(), sort_keys=True)
    for k in ("removed", "added", "dynamic"):
        np.testing.assert_array_equal(getattr(live.voxels, k), getattr(after.voxels, k))
    np.testing.assert_array_equal(live.offmap_points, after.offmap_points)
    assert len(live.voxels.removed) > 0 and len(live.voxels.added) > 0
    assert live.frames_trusted == int(trusted_mask(statuses, 2).sum()) and live.scans_used == (live.frames_trusted + 1) // 2
    # blocks joined as the drive came within range (x from -24 m: the x >= 0 block 22 m away at
    # the first trusted frame, x = -22 m)
    assert loaded[1] == [] and loaded[2] == ["000"] and loaded[-1] == ["000", "001"]
    assert loaded.index(["000", "001"]) > 10
    # a used frame waits for the pose after it: processed by the next add, the last one possibly by result()
    last_used_last = (live.frames_trusted - 1) % 2 == 0
    assert sum(c[2] for c in det.costs) == live.scans_used + live.scans_rejected - last_used_last
    assert all(c[1] >= 0 and c[0] >= 0 for c in det.costs) and len(det.costs) == len(T)


def test_an_interrupted_feed_gives_what_its_frames_show(street):
    """result() at any time: the frames fed so far, the pending one processed with the poses it has."""
    store, T, statuses, run, seq = street
    opts = dict(max_range_m=12.0, stride=1)
    n = 10  # x up to -15 m: the x >= 0 block stays out of range
    det = ChangeDetector(store, np.eye(4), seq.info.gravity_map, **opts)
    for i in range(n):
        det.add(1000.0 + 0.1 * i, T[i], True, seq.frame(i))
    part = det.result(interrupted=True)
    rp = read_run(run, settle_frames=0)
    keep = rp.index < n
    rp.index, rp.stamps, rp.T_map_body = rp.index[keep], rp.stamps[keep], rp.T_map_body[keep]
    after = detect_changes(store, seq, rp, **opts)
    assert part.params["interrupted"] is True and part.scans_used == n
    assert part.blocks == after.blocks and part.to_json()["totals"] == after.to_json()["totals"]
    assert [b["block"] for b in part.blocks] == ["000"]  # the far side never came within range


def test_a_detector_that_fails_stops_alone_and_the_command_says_why(tmp_path, caplog):
    """A failure inside the detector (a block file it cannot read, ...) never stops tracking: it is
    logged in one line, later frames are not fed, and ``track`` ends with an error naming it and
    writes no changes.json."""
    from types import SimpleNamespace

    from blockloc.app.runs import LiveChanges
    from blockloc.commands.track import write_detected_changes
    from blockloc.errors import MapError, TrackingError
    from blockloc.viz.events import FrameEvent

    class Broken:
        calls = 0

        def add(self, *a):
            Broken.calls += 1
            raise MapError("block 003: cannot read 003.pcd")

    live = LiveChanges(stride=1, settle_frames=0)
    live.detector, live._trusted = Broken(), TrustedFrames(0)
    live._tap = SimpleNamespace(last=SimpleNamespace(index=3))
    for i in (3, 4):
        live.frame(FrameEvent(i, 1.0 + 0.1 * i, np.eye(4), None, np.zeros(3), "ok", {}))  # no exception
    assert isinstance(live.error, MapError) and Broken.calls == 1
    assert "change detection stopped on frame 3: block 003: cannot read 003.pcd" in caplog.text
    with pytest.raises(TrackingError, match=r"--detect-changes: change detection stopped on an error \(block 003"):
        write_detected_changes(live, None, tmp_path)
    assert not (tmp_path / "changes.json").exists()


def _swept(frame, stamp: float):
    """The frame at ``stamp`` with per-point times (a 0.1 s sweep), so its scan is deskewed."""
    import dataclasses

    offsets = np.linspace(-0.05, 0.05, len(frame.points)).astype(np.float32)
    return dataclasses.replace(frame, stamp=stamp, time_offsets=offsets)


def test_a_restarted_source_never_deskews_a_scan_with_the_new_streams_poses(street):
    """Stamps jump back (the node's source restarted): the scan waiting for the pose after it is
    processed with the poses before it, as across a long gap, whether the restart is said
    (ChangeDetector.restart, the node's hook) or only seen in the stamps."""
    store, T, statuses, run, seq = street
    opts = dict(max_range_m=12.0, stride=1)
    half = 12

    def feed(det, second_start: float, say_restart: bool, gap_frame: bool):
        for i in range(half):
            det.add(1000.0 + 0.1 * i, T[i], True, _swept(seq.frame(i), 1000.0 + 0.1 * i))
        if say_restart:
            assert det.restart() == 1  # the waiting scan, processed now
        if gap_frame:  # the reference: an untrusted frame long after (no pose can be a neighbour)
            det.add(1000.0 + 0.1 * half + 1.0, None, False, None)
        for i in range(half, 2 * half):
            s = second_start + 0.1 * (i - half)
            det.add(s, T[i], True, _swept(seq.frame(i), s))
        return det.result()

    told = ChangeDetector(store, np.eye(4), seq.info.gravity_map, **opts)
    said = feed(told, 500.0, True, False)
    seen = feed(ChangeDetector(store, np.eye(4), seq.info.gravity_map, **opts), 500.0, False, False)
    ref = feed(ChangeDetector(store, np.eye(4), seq.info.gravity_map, **opts), 2000.0, False, True)
    assert told.restarts == 1 and told.scans_flushed_on_restart == 1
    assert said.params["source_restarts"] == 1 and said.params["scans_flushed_on_restart"] == 1
    assert "source_restarts" not in ref.params
    doc = lambda r: {k: v for k, v in r.to_json().items() if k != "params"}  # noqa: E731
    assert said.scans_used == ref.scans_used == 2 * half
    assert json.dumps(doc(said), sort_keys=True) == json.dumps(doc(ref), sort_keys=True)
    assert json.dumps(said.to_json(), sort_keys=True) == json.dumps(seen.to_json(), sort_keys=True)
    np.testing.assert_array_equal(said.offmap_points, ref.offmap_points)


@pytest.mark.parametrize("threaded", [False, True])
def test_the_nodes_restart_hook_starts_trust_over_in_order(street, threaded):
    """NodeChanges.restart (the node's on_restart) between the frames around it, on the worker
    thread too: trust starts over (settle_frames ok frames again), the waiting scan is flushed."""
    from types import SimpleNamespace

    from blockloc.app.runs import LiveChanges
    from blockloc.node.changes import NodeChanges

    store, T, statuses, run, seq = street
    info = SimpleNamespace(T_body_lidar=np.eye(4), gravity_map=seq.info.gravity_map)
    node = NodeChanges(LiveChanges(stride=1, settle_frames=3), threaded=threaded)
    node.begin(SimpleNamespace(store=store, seq=SimpleNamespace(info=info)))
    est = lambda i: SimpleNamespace(T_map_body=T[i], diagnostics=SimpleNamespace(status="ok"))  # noqa: E731
    for i in range(10):
        node(_swept(seq.frame(i), 1000.0 + 0.1 * i), est(i))
    node.restart()
    for i in range(10, 20):
        node(_swept(seq.frame(i), 500.0 + 0.1 * (i - 10)), est(i))
    node.close()
    det = node.live.detector
    assert node.live.error is None
    # 7 trusted frames on each side of the restart (3 to settle), not 7 + 10
    assert det.frames_trusted == 14 and det.restarts == 1 and det.scans_flushed_on_restart == 1
    assert node.cost()["source_restarts"] == 1
