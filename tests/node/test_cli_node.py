"""``blockloc play`` and ``blockloc node`` as a user types them, side by side over loopback DDS."""

from __future__ import annotations

import signal
import subprocess
import time

import numpy as np
import pytest

from tests.faults.conftest import Running
from tests.node.conftest import wait_until


class Proc(Running):
    """A ``blockloc`` subprocess whose stderr is collected as it comes (the fault suite's
    :class:`Running`), waited for by the text it prints."""

    def wait_for(self, text: str, timeout_s: float) -> None:
        t0 = time.monotonic()
        while text not in self.err:
            assert self.proc.poll() is None, f"exited {self.proc.returncode} before {text!r}: {self.err[-1500:]}"
            assert time.monotonic() - t0 < timeout_s, f"no {text!r} within {timeout_s} s: {self.err[-1500:]}"
            time.sleep(0.05)

    def finish(self, timeout_s: float) -> int:
        try:
            code = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
            raise AssertionError(f"still running after {timeout_s} s: {self.err[-1500:]}") from None
        self._reader.join(10)
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


def position_error(msg, truth) -> float:
    """Metres between a pose message's position and the ground truth at its stamp."""
    from blockloc.ros2.messages import time_to_stamp

    q = msg.pose.pose.position
    return float(np.linalg.norm(np.array([q.x, q.y, q.z])
                                - truth.interpolate(np.array([time_to_stamp(msg.header.stamp)]))[0][:3, 3]))


def ctrl_c(node: Proc, timeout_s: float) -> None:
    """Ctrl-C the node a second after its last pose: it must finish its run and exit with 130."""
    time.sleep(1.0)
    node.proc.send_signal(signal.SIGINT)
    assert node.finish(timeout_s) == 130, node.err


def reap(node: Proc, play: Proc | None, dds) -> None:
    """Neither process outlives the test, nor the test's own DDS participant."""
    node.kill()
    if play is not None:
        play.kill()
    dds.close()


def listen():
    """A participant of the test collecting the node's poses and the player's ground truth."""
    from blockloc.ros2 import dds as d
    from blockloc.ros2 import messages as m

    p = d.Dds()
    got = {"pose": [], "gt": [], "diag": []}
    p.reader("/blockloc/pose", m.PoseWithCovarianceStamped, got["pose"].append, d.RELIABLE)
    p.reader("/blockloc/ground_truth", m.Odometry, got["gt"].append, d.RELIABLE)
    p.reader("/diagnostics", m.DiagnosticArray, got["diag"].append, d.RELIABLE)
    return p, got


def test_play_into_node_end_to_end_and_ctrl_c_keeps_the_run(tiny_live_world, loopback_dds, tmp_path):
    w = tiny_live_world
    out = tmp_path / "run"
    dds, got = listen()
    node = Proc("node", "--map", w["map"], "--config", w["config"], "--out", out)
    play = None
    try:
        node.wait_for("listening on /points", 120)
        # a quarter of the recorded pace: the machine running the tests is shared (a node that falls
        # behind drops scans, by design)
        play = Proc("play", "--seq", w["session"], "--config", w["config"], "--rate", "0.25")
        assert play.finish(300) == 0, play.err
        assert "120 scans" in play.err and "ground-truth poses published" in play.err
        try:
            wait_until(lambda: len(got["pose"]) >= 40, 30, "poses")
        except AssertionError as exc:
            raise AssertionError(f"{exc} ({len(got['pose'])} so far); the node said: {node.err[-2000:]}") from None
        ctrl_c(node, 120)
    finally:
        reap(node, play, dds)
    assert "node stopped:" in node.err and "Traceback" not in node.err
    truth = w["seq"].ground_truth()
    assert len(got["gt"]) >= 100 and max(position_error(g, truth) for g in got["gt"]) < 1e-6  # the player's truth
    errors = [position_error(p, truth) for p in got["pose"]]
    assert len(errors) >= 40 and np.median(errors) < 0.3, (len(errors), np.round(errors, 2))
    # the run folder track writes, kept after Ctrl-C
    for name in ("poses.tum", "metrics.json", "diagnostics.csv", "run.mcap", "report.html"):
        assert (out / name).is_file(), name
    import json

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["interrupted"] is True and metrics["frames"] >= 40


def test_sigterm_during_global_init_ends_cleanly(tiny_live_world, loopback_dds, tmp_path):
    w = tiny_live_world
    node = Proc("-v", "node", "--map", w["map"], "--config", w["config"], "--out", tmp_path / "run")
    play = None
    try:
        node.wait_for("listening on /points", 120)
        play = Proc("play", "--seq", w["session"], "--config", w["config"], "--loop")
        node.wait_for("global init over the whole map", 120)
        node.proc.send_signal(signal.SIGTERM)
        assert node.finish(120) == 143, node.err
    finally:
        node.kill()
        if play is not None:
            play.proc.send_signal(signal.SIGINT)
            assert play.finish(60) == 130, play.err
    assert "node stopped:" in node.err and "Traceback" not in node.err
    assert "play stopped:" in play.err


def test_play_stops_after_max_frames_and_rejects_a_bad_rate(tiny_live_world, loopback_dds):
    w = tiny_live_world
    p = Proc("play", "--seq", w["session"], "--config", w["config"], "--max-frames", "5", "--rate", "4")
    assert p.finish(60) == 0, p.err
    assert "5 scans" in p.err
    bad = Proc("play", "--seq", w["session"], "--rate", "0")
    assert bad.finish(60) == 2
    assert bad.err.strip().splitlines()[-1].startswith("error: --rate 0")


def test_play_pace_file_replaces_only_its_own(tiny_live_world, loopback_dds, tmp_path):
    """``play --pace-file FILE`` over a user's file (notes, a figure) or a directory: exit 2 before
    anything is published, one line naming --pace-file, the file unchanged (play replaced any file,
    and a directory failed with IsADirectoryError once publishing had started); a pace file of its
    own is replaced."""
    import json

    w = tiny_live_world
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes")
    (tmp_path / "folder").mkdir()
    for target in (notes, tmp_path / "folder"):
        p = Proc("play", "--seq", w["session"], "--config", w["config"], "--max-frames", "3", "--pace-file", target)
        assert p.finish(60) == 2, p.err
        lines = p.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: --pace-file {target}: "), p.err
    assert notes.read_text() == "my notes" and not any((tmp_path / "folder").iterdir())
    pace = tmp_path / "pace.json"
    for _ in range(2):  # its own file, written then replaced
        p = Proc("play", "--seq", w["session"], "--config", w["config"], "--max-frames", "3", "--rate", "4",
                 "--pace-file", pace)
        assert p.finish(60) == 0, p.err
        assert json.loads(pace.read_text())["clock"] == "CLOCK_MONOTONIC"


def test_node_with_a_missing_map_is_one_error_line(loopback_dds, tmp_path):
    p = Proc("node", "--map", tmp_path / "nowhere")
    assert p.finish(60) == 2
    lines = p.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "nowhere" in lines[0]


def test_node_checks_the_map_against_its_backend_at_startup(loopback_dds, tmp_path):
    """``node --map GRID`` (the default backend 'block' needs a block map): one line at startup
    naming --map-backend, exit 2 (it listened, then failed on every scan, advising a --map-backend
    node did not have). ``--map-backend grid`` takes the grid map; Ctrl-C before any scan came says
    no "results in DIR": nothing was written there (it said so anyway)."""
    from blockloc.maps.store import MapWriter

    grid = tmp_path / "lgrid"
    with MapWriter(grid, "grid", params={"tile_size_m": 10.0}) as w:
        w.add("5.0_5.0", np.random.default_rng(0).uniform(0, 10, (100, 3)).astype(np.float32))
        w.commit()
    out = tmp_path / "runs" / "lgrid"
    p = Proc("node", "--map", grid, "--out", out)
    assert p.finish(60) == 2, p.err
    lines = p.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {grid}: the 'block' backend needs a block map"), p.err
    assert "--map-backend grid" in lines[0] and "listening" not in p.err
    node = Proc("node", "--map", grid, "--map-backend", "grid", "--gravity", "up", "--out", out)
    try:
        node.wait_for("listening on /points", 120)
        node.proc.send_signal(signal.SIGINT)
        assert node.finish(60) == 130, node.err
    finally:
        node.kill()
    assert "node stopped: 0 scans processed" in node.err and "results in" not in node.err, node.err
    assert not out.exists()


def test_the_node_takes_gravity_from_the_option_else_the_maps_place_index(tiny_live_world, tmp_path):
    import shutil

    from blockloc.commands.node import map_gravity
    from blockloc.maps.store import open_map

    store = open_map(tiny_live_world["map"])
    assert map_gravity(store, None) == pytest.approx(tiny_live_world["seq"].info.gravity_map)
    assert map_gravity(store, "down") == pytest.approx([0.0, 0.0, 9.81])
    # no place index and a mapping sequence that cannot be opened: z up, said once
    bare = tmp_path / "bare"
    shutil.copytree(tiny_live_world["map"], bare)
    import json

    manifest = json.loads((bare / "manifest.json").read_text())
    manifest.pop("extras", None)
    manifest["parameters"]["sequence"] = "nowhere:at/all"
    (bare / "manifest.json").write_text(json.dumps(manifest))
    assert map_gravity(open_map(bare), None) == pytest.approx([0.0, 0.0, -9.81])


def test_a_wrong_initialpose_while_tracking_gives_a_verified_pose_within_3_s_and_never_a_wrong_one(
        tiny_live_world, loopback_dds, tmp_path):
    """RViz's "2D Pose Estimate" 10 m and 90 degrees off while the node tracks: the node searches
    around it and publishes the verified pose (not the hint) within 3 s; every pose it publishes
    is right. ``play --pace-file`` says when each stamp was due (checked on the ground truth)."""
    import json

    from blockloc.geometry import rpy_to_R
    from blockloc.ros2 import convert
    from blockloc.ros2 import dds as d
    from blockloc.ros2 import messages as m
    from blockloc.ros2.messages import time_to_stamp

    w = tiny_live_world
    truth = w["seq"].ground_truth()
    p = d.Dds()
    got = {"pose": [], "gt": [], "diag": []}  # (monotonic s received, message)
    for topic, kind, key in (("/blockloc/pose", m.PoseWithCovarianceStamped, "pose"),
                             ("/blockloc/ground_truth", m.Odometry, "gt"), ("/diagnostics", m.DiagnosticArray, "diag")):
        p.reader(topic, kind, lambda msg, key=key: got[key].append((time.monotonic(), msg)), d.RELIABLE)
    initialpose = p.writer("/initialpose", m.PoseWithCovarianceStamped, d.RELIABLE)
    pace = tmp_path / "pace.json"
    node = Proc("node", "--map", w["map"], "--config", w["config"])
    play = None
    try:
        node.wait_for("listening on /points", 120)
        play = Proc("play", "--seq", w["session"], "--config", w["config"], "--rate", "0.5", "--pace-file", pace)
        wait_until(lambda: len(got["pose"]) >= 10, 120, "tracking")
        T = convert.matrix_of(got["gt"][-1][1].pose.pose.position, got["gt"][-1][1].pose.pose.orientation)
        wrong = T.copy()
        wrong[:2, 3] -= 10.0 * T[:2, 3] / np.linalg.norm(T[:2, 3])  # 10 m towards the circle's centre
        wrong[:3, :3] = rpy_to_R(0.0, 0.0, np.pi / 2) @ T[:3, :3]  # and turned 90 degrees
        sent = time.monotonic()
        initialpose.write(convert.pose_with_covariance(wrong, None, 0.0, "map"))

        def reinit():
            for t, msg in list(got["diag"]):
                v = {kv.key: kv.value for kv in msg.status[0].values}
                if t > sent and int(v.get("verified_inits", 0)) >= 2 and v["state"] == "ok":
                    return float(v["stamp"])
            return None

        wait_until(lambda: reinit() is not None, 30, "a verified global init around the /initialpose")
        stamp = reinit()
        wait_until(lambda: any(abs(time_to_stamp(x.header.stamp) - stamp) < 1e-6 for _, x in got["pose"]), 10,
                   "its pose")
        first = next(t for t, x in got["pose"] if abs(time_to_stamp(x.header.stamp) - stamp) < 1e-6)
        assert play.finish(120) == 0, play.err
        ctrl_c(node, 60)
    finally:
        reap(node, play, p)
    assert first - sent < 3.0, f"verified pose {first - sent:.2f} s after the /initialpose"
    errors = np.array([position_error(x, truth) for _, x in got["pose"]])
    assert len(errors) >= 30 and errors.max() < 1.0, np.round(errors, 2)  # never the hint, 10 m off
    # Around and after the new initial pose, the robot's motion kept, the scan deskewed again and
    # registered: right from the first pose (measured: 0.004-0.006 m; before, 0.13-0.39 m). The
    # first pose after the node's start is about 0.3 m off on this 5 m/s drive: the velocity is
    # unknown there, taken as zero. From the second scan on the tracker knows it and registers the
    # first two again (Estimator._settle; `blockloc track` from a global init on this world's
    # first 16 scans: 0.29, 0.04, then <= 0.02 m; before it 0.29, 0.33, then 0.06-0.13 m for 8 scans).
    # (from the scan it searched on: a scan already being tracked when the /initialpose came may
    # publish after it, still converging from the cold start, seen 0.055 m under a load of 26)
    later = [(t, x) for t, x in got["pose"] if t > sent and time_to_stamp(x.header.stamp) >= stamp - 1e-6]
    after = np.array([position_error(x, truth) for t, x in later])
    at = [round(time_to_stamp(x.header.stamp) - stamp, 2) for t, x in later]
    assert len(after) >= 5 and after.max() < 0.05, list(zip(at, np.round(after, 3)))
    # the pace file: each ground-truth pose (published with its scan, at the sweep's end) came after it was due
    anchor = json.loads(pace.read_text())
    assert anchor["rate"] == 0.5 and anchor["clock"] == "CLOCK_MONOTONIC"
    frames = {round(f.stamp, 6): float(np.max(f.time_offsets)) for f in w["seq"].frames()}
    lag = np.array([t - (anchor["monotonic"] + (s + frames[round(s, 6)] - anchor["stamp"]) / anchor["rate"])
                    for t, x in got["gt"] for s in [time_to_stamp(x.header.stamp)]])
    assert lag.min() > -0.005 and np.median(lag) < 0.2, np.round(np.percentile(lag, [0, 50, 100]), 3)


def test_poses_the_tracker_rejects_are_withheld_from_pose_odom_and_tf(tiny_live_world, loopback_dds):
    """A pose that is not verified never goes out as one: with an acceptance test no scan can pass
    (``tracking.min_fitness=1``), the node still initializes (a verified global init) and says
    "degraded" on /diagnostics for every scan, but publishes nothing on /blockloc/pose,
    /blockloc/odom or /tf."""
    from blockloc.ros2 import dds as d
    from blockloc.ros2 import messages as m

    w = tiny_live_world
    p = d.Dds()
    got = {"pose": [], "odom": [], "tf": [], "diag": []}
    for topic, kind, key in (("/blockloc/pose", m.PoseWithCovarianceStamped, "pose"),
                             ("/blockloc/odom", m.Odometry, "odom"), ("/tf", m.TFMessage, "tf"),
                             ("/diagnostics", m.DiagnosticArray, "diag")):
        p.reader(topic, kind, got[key].append, d.RELIABLE)
    node = Proc("node", "--map", w["map"], "--config", w["config"], "--set", "tracking.min_fitness=1.0",
                "--set", "tracking.max_bad_frames=1000")
    play = None
    try:
        node.wait_for("listening on /points", 120)
        play = Proc("play", "--seq", w["session"], "--config", w["config"], "--rate", "0.5", "--max-frames", "20")
        assert play.finish(120) == 0, play.err

        def values():
            return [{kv.key: kv.value for kv in x.status[0].values} for x in list(got["diag"])]

        try:
            wait_until(lambda: sum(v.get("state") == "degraded" for v in values()) >= 5, 120, "degraded scans")
        except AssertionError as exc:
            raise AssertionError(f"{exc}: {[x.get('status') for x in values()]}; {node.err[-1500:]}") from None
        node.proc.send_signal(signal.SIGINT)
        assert node.finish(60) == 130, node.err
    finally:
        node.kill()
        if play is not None:
            play.kill()
        p.close()
    v = values()
    degraded = [x for x in v if x.get("state") == "degraded"]
    assert int(v[-1]["verified_inits"]) >= 1  # it did initialize: those poses would have gone out before
    assert all(x["status"] == "rejected" and x["pose_published"] == "False" for x in degraded)
    assert int(v[-1]["poses_withheld"]) >= len(degraded) and int(v[-1]["poses_published"]) == 0
    assert not got["pose"] and not got["odom"] and not got["tf"]
    assert "0 poses published" in node.err


def test_node_detect_changes_writes_what_map_changes_finds_in_its_run(tiny_live_world, loopback_dds, tmp_path):
    """``blockloc node --detect-changes --out DIR`` as a user types it, fed by ``blockloc play``:
    at Ctrl-C it writes DIR/changes.json (exit 130 as always) from the scans it tracked, with the
    detector's cost and what it cost the node; its blocks are what ``blockloc map changes`` finds
    after the fact in the run folder the node wrote (same trusted frames, same stride)."""
    import json
    import shutil

    w = tiny_live_world
    out = tmp_path / "run"
    dds, got = listen()
    node = Proc("node", "--map", w["map"], "--config", w["config"], "--out", out, "--detect-changes",
                "--changes-stride", "2")
    play = None

    def processed() -> int:
        return max([int(kv.value) for x in list(got["diag"]) for kv in x.status[0].values
                    if kv.key == "scans_processed"], default=0)

    try:
        node.wait_for("listening on /points", 120)
        play = Proc("play", "--seq", w["session"], "--config", w["config"], "--rate", "0.5", "--max-frames", "36")
        assert play.finish(120) == 0, play.err
        wait_until(lambda: processed() >= 36, 120, f"36 scans processed ({processed()}): {node.err[-1500:]}")
        ctrl_c(node, 60)
    finally:
        reap(node, play, dds)
    assert "changes.json written:" in node.err and "Traceback" not in node.err, node.err[-2000:]
    assert "36 scans processed" in node.err and ", 0 dropped" in node.err, node.err[-800:]  # same frames as the session
    live = json.loads((out / "changes.json").read_text())
    assert live["during"] == "node --detect-changes" and live["frames_trusted"] >= 15
    cost = live["cost"]
    assert cost["frames_tracked"] == 36 and cost["scans_dropped"] == 0 and cost["node_thread"].startswith("worker")
    assert 0 < cost["per_scan_cpu_ms"]["p50"] <= cost["per_scan_cpu_ms"]["max"]
    copy = shutil.copytree(out, tmp_path / "copy")
    r = subprocess.run(["blockloc", "map", "changes", "--map", str(w["map"]), "--run", str(copy), "--seq",
                        str(w["session"]), "--out", str(tmp_path / "after.json"), "--stride", "2"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    after = json.loads((tmp_path / "after.json").read_text())
    for k in ("frames_trusted", "scans_used", "scans_rejected", "totals", "blocks"):
        assert live[k] == after[k], k
    assert live["scans_used"] == (live["frames_trusted"] + 1) // 2 and live["blocks"]


def test_node_detect_changes_needs_out(tiny_live_world, loopback_dds):
    p = Proc("node", "--map", tiny_live_world["map"], "--detect-changes")
    assert p.finish(60) == 2
    lines = p.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --detect-changes") and "--out" in lines[0], p.err
