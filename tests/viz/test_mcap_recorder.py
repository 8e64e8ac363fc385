"""The MCAP recording read back with the mcap library's ROS 2 decoder and with rosbags: every
message type against the events that made it, message counts, the TF chain, interrupted runs."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from blockloc.trajectory_io import read_tum
from blockloc.geometry import inv_T
from blockloc.viz.ros_codec import covariance_to_ros
from blockloc.viz.ros_messages import TOPICS
from tests.viz.conftest import LOST, read_mcap_ros2
from tests.viz.synthetic import make_run

REPO = Path(__file__).resolve().parents[2]


def ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def pose_T(position, orientation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([orientation.x, orientation.y, orientation.z, orientation.w]).as_matrix()
    T[:3, 3] = [position.x, position.y, position.z]
    return T


def tf_T(tr) -> np.ndarray:
    return pose_T(tr.transform.translation, tr.transform.rotation)


def cloud_xyz(msg) -> np.ndarray:
    assert [f.name for f in msg.fields] == ["x", "y", "z"] and msg.point_step == 12 and not msg.is_bigendian
    data = msg.data if isinstance(msg.data, (bytes, bytearray)) else np.asarray(msg.data, np.uint8).tobytes()
    return np.frombuffer(data, np.float32).reshape(-1, 3)


def by_stamp(run):
    return {int(round(e.stamp * 1e9)): e for e in run.events}


# ------------------------------------------------------------------ counts and stamps
def test_every_topic_with_expected_counts(recording, decoded, synthetic_run):
    path, rec = recording
    run = synthetic_run
    localized = len(run.localized)
    assert localized == len(run.events) - len(LOST)
    changes = sum(1 for i, e in enumerate(run.events) if i == 0 or e.active_entries != run.events[i - 1].active_entries)
    maps = sum(e.local_map_points is not None for e in run.events)
    kept, dropped = rec.decimator.counts["scans_kept"], rec.decimator.counts["scans_dropped"]
    assert kept + dropped == localized and kept > 0 and dropped > 0  # the budget binds in this run
    counts = {t: len(v) for t, v in decoded.items()}
    assert set(counts) == set(TOPICS)
    assert counts["/tf"] == counts["/localization/pose"] == counts["/localization/odometry"] == localized
    assert counts["/diagnostics"] == len(run.events)
    assert counts["/map/blocks"] == changes >= 4  # the circle passes all four blocks
    assert counts["/map/local"] == maps
    assert counts["/points/aligned"] == kept
    assert counts["/ground_truth/path"] == 1
    duration = run.events[-1].stamp - run.events[0].stamp
    assert math.floor(duration / 5.0) <= counts["/localization/path"] <= math.ceil(duration / 5.0) + 2
    assert rec.summary["counts"] == counts


def test_stamps_are_sensor_time(decoded, synthetic_run):
    stamps = set(by_stamp(synthetic_run))
    for topic, msgs in decoded.items():
        for t, msg in msgs:
            assert t in stamps, topic
            if topic == "/tf":
                assert all(ns(tr.header) == t for tr in msg.transforms)
            elif topic == "/map/blocks":
                assert all(ns(m.header) == t for m in msg.markers)
            elif hasattr(msg, "header"):
                assert ns(msg.header) == t, topic


def test_summary_metadata_and_rename(recording, synthetic_run):
    from mcap.reader import make_reader

    path, _ = recording
    assert path.exists() and not path.with_name(path.name + ".partial").exists()
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert header.profile == "ros2"
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    assert {s.name for s in summary.schemas.values()} == set(TOPICS.values())
    assert summary.statistics.message_start_time == int(round(synthetic_run.events[0].stamp * 1e9))
    assert meta["blockloc.run"]["sequence"] == "synthetic:circle"
    assert np.allclose(json.loads(meta["blockloc.run"]["T_body_lidar"]), synthetic_run.info.T_body_lidar)
    assert json.loads(meta["blockloc.metrics"]["json"])["note"] == "synthetic"
    assert meta["blockloc.end"]["reason"] == "finished"
    assert (path.parent / "foxglove_layout.json").exists()


# ------------------------------------------------------------------ each message type
def test_pose_and_odometry_round_trip(decoded, synthetic_run):
    events = by_stamp(synthetic_run)
    for t, msg in decoded["/localization/pose"]:
        ev = events[t]
        assert msg.header.frame_id == "map"
        T = pose_T(msg.pose.pose.position, msg.pose.pose.orientation)
        assert np.allclose(T, ev.T_map_body, atol=1e-9)
        cov = np.asarray(msg.pose.covariance, float).reshape(6, 6)
        assert np.allclose(cov, covariance_to_ros(ev.covariance, ev.T_map_body[:3, :3]), rtol=1e-12, atol=1e-15)
    prev = None
    for t, msg in decoded["/localization/odometry"]:
        ev = events[t]
        assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "base_link")
        assert np.allclose(pose_T(msg.pose.pose.position, msg.pose.pose.orientation), ev.T_map_body, atol=1e-9)
        R = ev.T_map_body[:3, :3]
        lin = msg.twist.twist.linear
        assert np.allclose([lin.x, lin.y, lin.z], R.T @ ev.velocity_map, atol=1e-9)
        ang = msg.twist.twist.angular
        if prev is not None:  # consecutive localized frames: the rotation between them over dt
            w = Rotation.from_matrix(prev.T_map_body[:3, :3].T @ R).as_rotvec() / (ev.stamp - prev.stamp)
            assert np.allclose([ang.x, ang.y, ang.z], w, atol=1e-9)
        prev = ev


def test_tf_chain_reproduces_poses_tum(recording, decoded, synthetic_run):
    """At every pose stamp map -> odom -> base_link resolves from /tf alone and gives poses.tum
    to 1e-6 m; base_link -> lidar is the calibration."""
    path, _ = recording
    tum = read_tum(path.parent / "poses.tum")
    tf_at = {}
    for t, msg in decoded["/tf"]:
        edges = {(tr.header.frame_id, tr.child_frame_id): tf_T(tr) for tr in msg.transforms}
        tf_at[t] = edges
    assert len(tf_at) == len(tum)
    for stamp, T_tum in zip(tum.stamps, tum.poses):
        edges = tf_at[int(round(stamp * 1e9))]
        assert np.allclose(edges[("map", "odom")], np.eye(4))
        T_map_base = edges[("map", "odom")] @ edges[("odom", "base_link")]
        assert np.abs(T_map_base[:3, 3] - T_tum[:3, 3]).max() < 1e-6
        assert np.abs(T_map_base[:3, :3] - T_tum[:3, :3]).max() < 1e-9
        assert np.allclose(edges[("base_link", "lidar")], synthetic_run.info.T_body_lidar, atol=1e-12)


def test_points_aligned_are_the_scan_in_the_map(decoded, synthetic_run, recording):
    _, rec = recording
    events = by_stamp(synthetic_run)
    for t, msg in decoded["/points/aligned"]:
        ev = events[t]
        assert msg.header.frame_id == "map" and msg.height == 1
        pts_map = cloud_xyz(msg)
        step = math.ceil(len(ev.scan_lidar) / rec.decimator.scan_points_max)
        expected = ev.scan_lidar[::step]
        assert msg.width == len(pts_map) == len(expected) <= rec.decimator.scan_points_max
        T_lidar_map = inv_T(ev.T_map_body @ synthetic_run.info.T_body_lidar)
        back = pts_map.astype(np.float64) @ T_lidar_map[:3, :3].T + T_lidar_map[:3, 3]
        assert np.abs(back - expected).max() < 1e-4  # float32 in a 60 m world


def test_local_map_once_per_change(decoded, synthetic_run, recording):
    _, rec = recording
    events = by_stamp(synthetic_run)
    for t, msg in decoded["/map/local"]:
        ev = events[t]
        assert ev.local_map_points is not None and msg.header.frame_id == "map"
        step = math.ceil(len(ev.local_map_points) / rec.decimator.map_points_max)
        assert np.array_equal(cloud_xyz(msg), ev.local_map_points[::step])


def test_points_budget_holds(decoded, synthetic_run):
    """Cloud payload per minute within the 12 MB/min budget (plus the 2 s burst)."""
    total = sum(len(cloud_xyz(m)) * 12 for topic in ("/points/aligned", "/map/local") for _, m in decoded[topic])
    minutes = (synthetic_run.events[-1].stamp - synthetic_run.events[0].stamp) / 60.0
    assert total <= 12e6 * minutes + 12e6 / 60 * 2.0 + 1000


def test_block_markers(decoded, synthetic_run):
    from blockloc.viz.ros_messages import outline_xy

    entries = {e["id"]: e for e in synthetic_run.info.map_entries}
    events = by_stamp(synthetic_run)
    for t, msg in decoded["/map/blocks"]:
        active = set(events[t].active_entries)
        markers = {(m.ns, m.id): m for m in msg.markers}
        assert msg.markers[0].action == 3  # DELETEALL first: each message is the whole picture
        for ns_, ids in (("active", active), ("blocks", set(entries) - active)):
            m = markers[(ns_, 0)]
            assert m.type == 5 and m.header.frame_id == "map"
            xy = np.array([[p.x, p.y] for p in m.points])
            segs = sum(len(outline_xy(entries[i])) - 1 for i in ids)
            assert len(xy) == 2 * segs
            corners = np.vstack([outline_xy(entries[i]) for i in ids])
            assert np.min(np.linalg.norm(xy[:, None] - corners[None], axis=2), axis=1).max() < 1e-9
        assert markers[("active", 0)].scale.x > markers[("blocks", 0)].scale.x
        labels = {m.text for m in msg.markers if m.ns == "labels"}
        assert labels == set(entries)
    hexagon = [m for _, msg in decoded["/map/blocks"] for m in msg.markers
               if m.ns == "active" and len(m.points) == 12]
    assert hexagon  # block_000's 6-sided footprint, not its bounding box


def test_diagnostics(decoded, synthetic_run):
    events = by_stamp(synthetic_run)
    for t, msg in decoded["/diagnostics"]:
        ev = events[t]
        (status,) = msg.status
        values = {kv.key: kv.value for kv in status.values}
        assert (status.name, status.hardware_id) == ("tracking", "blockloc")
        assert int(status.level if not isinstance(status.level, bytes) else status.level[0]) == (2 if ev.status == "lost" else 0)
        assert values["status"] == ev.status and int(values["frame_index"]) == ev.index
        for key in ("fitness", "update_ms", "registration_ms", "smoother_ms", "window_size", "num_points"):
            assert float(values[key]) == pytest.approx(ev.diagnostics[key], rel=1e-8)
        assert values["switched"] == ("true" if ev.diagnostics["switched"] else "false")
        assert values["block_id"] == ev.diagnostics["block_id"]
        assert ("switched to" in status.message) == bool(ev.diagnostics["switched"])


def test_paths(decoded, synthetic_run):
    events = by_stamp(synthetic_run)
    last_sent = None
    for t, msg in decoded["/localization/path"]:
        stamps = [ns(p.header) for p in msg.poses]
        assert stamps == sorted(stamps) and stamps[-1] <= t
        for s, p in zip(stamps, msg.poses):
            assert np.allclose(pose_T(p.pose.position, p.pose.orientation), events[s].T_map_body, atol=1e-9)
        gaps = np.linalg.norm(np.diff([[p.pose.position.x, p.pose.position.y] for p in msg.poses], axis=0), axis=1)
        assert len(gaps) == 0 or gaps.min() >= 0.5 - 1e-9
        last_sent = msg
    final = synthetic_run.localized[-1]
    end = last_sent.poses[-1].pose.position
    assert np.linalg.norm([end.x - final.T_map_body[0, 3], end.y - final.T_map_body[1, 3]]) < 0.5
    ((_, gt_msg),) = decoded["/ground_truth/path"]
    gt = synthetic_run.info.ground_truth
    xy = np.array([[p.pose.position.x, p.pose.position.y] for p in gt_msg.poses])
    assert len(xy) > 100 and np.allclose(xy[0], gt.positions[0, :2]) and np.allclose(xy[-1], gt.positions[-1, :2])


def test_path_message_stays_bounded():
    from blockloc.viz.ros_messages import RunMessages

    run = make_run(duration_s=60.0, scan_points=10, map_every_s=1e9)
    msgs = RunMessages(path_spacing_m=0.05, path_max_poses=100, path_period_s=0.0)
    msgs.start(run.info)
    sizes = [len(m.data) for ev in run.events for m in msgs.frame(ev) if m.topic == "/localization/path"]
    assert len(sizes) > 100 and max(sizes) < 100 * 90 + 200  # ~72 bytes a PoseStamped


def test_without_ground_truth_no_gt_topic(tmp_path):
    from blockloc.viz.mcap_recorder import McapRecorder

    run = make_run(duration_s=2.0, scan_points=100, with_gt=False)
    rec = McapRecorder(tmp_path / "r.mcap", background=False, write_layout=False)
    rec.start(run.info)
    for ev in run.events:
        rec.frame(ev)
    rec.finish({})
    topics = {t for t, _, _ in read_mcap_ros2(tmp_path / "r.mcap")}
    assert topics == set(TOPICS) - {"/ground_truth/path"}
    assert not (tmp_path / "foxglove_layout.json").exists()


def test_in_process_and_worker_write_the_same_messages(tmp_path):
    from blockloc.viz.mcap_recorder import McapRecorder

    run = make_run(duration_s=3.0, scan_points=3000)
    out = {}
    for bg in (False, True):
        rec = McapRecorder(tmp_path / f"{bg}.mcap", background=bg, write_layout=False)
        rec.start(run.info)
        # the worker process (what bench/recording.py measures), only when there is one
        assert (rec.worker is not None and rec.worker.proc.pid > 0) if bg else rec.worker is None
        for ev in run.events:
            rec.frame(ev)
        rec.finish({})
        out[bg] = [(t, topic) for topic, t, _ in read_mcap_ros2(tmp_path / f"{bg}.mcap")]
    assert out[False] == out[True] and len(out[True]) > 100


# ------------------------------------------------------------------ interrupted runs
def test_exception_mid_run_leaves_a_valid_file(tmp_path):
    """finish() after an exception: a complete MCAP with the frames seen, the reason recorded."""
    from mcap.reader import make_reader

    from blockloc.viz.mcap_recorder import McapRecorder

    run = make_run(duration_s=4.0, scan_points=500)
    rec = McapRecorder(tmp_path / "run.mcap")
    rec.start(run.info)
    try:
        for ev in run.events:
            if ev.index == 17:
                raise RuntimeError("tracking blew up")
            rec.frame(ev)
    except RuntimeError as exc:
        rec.finish({}, reason=f"RuntimeError: {exc}")
    rec.finish({})  # a second call is harmless
    with open(tmp_path / "run.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary().statistics.channel_message_counts
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert meta["blockloc.end"]["reason"] == "RuntimeError: tracking blew up"
    poses = [t for topic, t, _ in read_mcap_ros2(tmp_path / "run.mcap") if topic == "/localization/pose"]
    assert len(poses) == 17


_KILLED_SCRIPT = """
import os, signal, sys
sys.path.insert(0, {repo!r})
from tests.viz.synthetic import make_run
from blockloc.viz.mcap_recorder import McapRecorder
run = make_run(duration_s=6.0, scan_points=500)
rec = McapRecorder({path!r}, background={background}, flush_period_s=0.5)
rec.start(run.info)
for ev in run.events[:40]:
    rec.frame(ev)
if {background}:
    assert rec._host.proxy.drain()  # every frame in the worker's pipe: what a kill must not lose
print("killing", flush=True)
os.kill(os.getpid(), signal.SIGKILL)
"""


def _run_killed(tmp_path: Path, background: bool) -> Path:
    path = tmp_path / "run.mcap"
    script = _KILLED_SCRIPT.format(repo=str(REPO), path=str(path), background=background)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    return path


def test_sigkill_of_the_tracking_process_the_worker_finishes_the_file(tmp_path):
    from mcap.reader import make_reader

    from blockloc.viz.worker import ENDED_WITHOUT_FINISH

    path = _run_killed(tmp_path, background=True)
    for _ in range(300):  # the orphaned worker finishes on its own
        if path.exists():
            break
        import time
        time.sleep(0.1)
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert meta["blockloc.end"]["reason"] == ENDED_WITHOUT_FINISH
    poses = [t for topic, t, _ in read_mcap_ros2(path) if topic == "/localization/pose"]
    assert len(poses) == 40


def test_sigkill_of_everything_leaves_a_readable_partial(tmp_path):
    """In-process recording killed: the .partial holds every chunk flushed (0.5 s of sensor time)
    and the mcap stream reader reads it up to the cut."""
    from mcap.exceptions import McapError
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    path = _run_killed(tmp_path, background=False)
    partial = path.with_name(path.name + ".partial")
    assert partial.exists() and not path.exists()
    n = 0
    with open(partial, "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False).records:
                n += isinstance(record, Message)
        except (McapError, EOFError, ValueError):
            pass  # the cut: a record or chunk half written, or the missing footer
    assert n >= 5 * 35  # frames up to the last 0.5 s flush, ~5 messages each


# ------------------------------------------------------------------ the math
def test_covariance_to_ros_is_the_first_order_error_map(synthetic_run):
    """A tangent perturbation xi of T = T_hat Exp(xi) moves the ROS error vector
    (position error in map, rotation vector in map) by J xi: the covariance is J P J^T."""
    from tests.viz.synthetic import perturb

    rng = np.random.default_rng(0)
    for ev in synthetic_run.localized[::37]:
        T = ev.T_map_body
        J = covariance_to_ros(np.eye(6), T[:3, :3])  # J J^T; J orthogonal so this is I
        assert np.allclose(J, np.eye(6))
        for _ in range(5):
            xi = rng.normal(size=6) * 1e-7
            Tp = perturb(T, xi)
            e = np.r_[Tp[:3, 3] - T[:3, 3], Rotation.from_matrix(Tp[:3, :3] @ T[:3, :3].T).as_rotvec()]
            P = np.outer(xi, xi)
            assert np.allclose(covariance_to_ros(P, T[:3, :3]), np.outer(e, e), rtol=1e-5, atol=1e-25)


def test_quaternion_matches_scipy():
    from blockloc.viz.ros_codec import _quat_one, rotation_vector

    rng = np.random.default_rng(1)
    Rs = list(Rotation.random(200, random_state=2).as_matrix())
    Rs += [Rotation.from_rotvec(a * np.pi * v / np.linalg.norm(v)).as_matrix()
           for a in (1.0, 0.999999, 1e-9) for v in rng.normal(size=(5, 3))]
    for R in Rs:
        q = _quat_one(R)
        ref = Rotation.from_matrix(R).as_quat()
        assert min(np.abs(q - ref).max(), np.abs(q + ref).max()) < 1e-9
        assert np.allclose(Rotation.from_rotvec(rotation_vector(R)).as_matrix(), R, atol=1e-9)


def test_decimator_drops_scans_never_delays():
    from blockloc.viz.ros_messages import Decimator

    run = make_run(duration_s=30.0, scan_points=20_000, map_points=200_000, map_every_s=10.0)
    dec = Decimator(points_budget_mb_per_min=10.0, scan_points_max=8000, map_points_max=60_000)
    kept = [dec.thin(ev) for ev in run.events]
    assert [k.index for k in kept] == [e.index for e in run.events]  # one out per frame in
    sizes = [len(k.scan_lidar) for k in kept if k.scan_lidar is not None]
    assert sizes and max(sizes) <= 8000 and dec.counts["scans_dropped"] > 0
    maps = [len(k.local_map_points) for k in kept if k.local_map_points is not None]
    assert len(maps) == sum(e.local_map_points is not None for e in run.events) and max(maps) <= 60_000
    assert dec.counts["points_bytes"] <= 10e6 / 60 * (30.0 + 2.0) + 1000
    assert all(e.scan_lidar.shape == (20_000, 3) for e in run.events)  # inputs untouched


def test_a_frame_the_worker_cannot_encode_ends_the_file_cleanly(tmp_path):
    """A bad frame (a stamp before the epoch) fails in the worker: the file is closed with the
    frames before it and finish() says what happened."""
    import dataclasses

    from mcap.reader import make_reader

    from blockloc.viz.events import VizError
    from blockloc.viz.mcap_recorder import McapRecorder

    run = make_run(duration_s=2.0, scan_points=100)
    rec = McapRecorder(tmp_path / "run.mcap", write_layout=False)
    rec.start(run.info)
    for ev in run.events[:8]:
        rec.frame(ev)
    rec.frame(dataclasses.replace(run.events[8], stamp=-1.0))
    for ev in run.events[9:]:
        rec.frame(ev)
    with pytest.raises(VizError, match=r"recording .*run.mcap: viz worker failed: VizError: stamp -1.0 s"):
        rec.finish({})
    with open(tmp_path / "run.mcap", "rb") as f:
        assert make_reader(f).get_summary() is not None
    poses = [t for topic, t, _ in read_mcap_ros2(tmp_path / "run.mcap") if topic == "/localization/pose"]
    assert len(poses) == 8


def test_observer_group_isolates_a_failing_member():
    from blockloc.viz.events import ObserverGroup, RunObserver

    class Log:
        def __init__(self, fail_at=None):
            self.calls, self.fail_at = [], fail_at

        def start(self, info):
            self.calls.append("start")

        def frame(self, ev):
            if ev.index == self.fail_at:
                raise RuntimeError("viewer broke")
            self.calls.append(ev.index)

        def finish(self, metrics):
            self.calls.append("finish")

    run = make_run(duration_s=0.5, scan_points=10)
    good, bad = Log(), Log(fail_at=2)
    assert isinstance(good, RunObserver)
    group = ObserverGroup([bad, good])
    group.start(run.info)
    for ev in run.events:
        group.frame(ev)
    group.finish({})
    assert good.calls == ["start", 0, 1, 2, 3, 4, "finish"]
    assert bad.calls == ["start", 0, 1, "finish"]
