"""The node in this process on loopback DDS: what it publishes, and each fault in one test (one
log line, the node keeps running)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.node.conftest import wait_until


def position_error(h, pose_msg) -> float:
    from blockloc.ros2.messages import time_to_stamp

    p = pose_msg.pose.pose.position
    t = time_to_stamp(pose_msg.header.stamp)
    gt = h.seq.ground_truth().interpolate(np.array([t]))[0]
    return float(np.linalg.norm(np.array([p.x, p.y, p.z]) - gt[:3, 3]))


def lines(caplog, text: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if text in r.getMessage()]


def test_tracks_and_publishes_pose_odometry_tf_diagnostics_and_the_local_map(harness, node_log):
    h = harness()
    h.publish_static()
    for i in range(25):
        h.send_scan(i)
    wait_until(lambda: len(h.poses) >= 20, 20, "poses received")
    errors = [position_error(h, p) for p in h.poses]
    assert np.median(errors) < 0.3, errors
    assert all(p.header.frame_id == "map" for p in h.poses)
    stamps = [p.header.stamp.sec + p.header.stamp.nanosec * 1e-9 for p in h.poses]
    assert set(np.round(stamps, 6)) <= set(np.round([f.stamp for f in h.frames[:25]], 6))  # scan stamps
    wait_until(lambda: len(h.odom) >= 20 and len(h.tf) >= 20, 10, "odometry and tf")
    odom = h.odom[-1]
    assert odom.child_frame_id == "base_link" and odom.pose.covariance[0] > 0  # the window's marginals
    assert h.tf[-1].transforms[0].header.frame_id == "map" and h.tf[-1].transforms[0].child_frame_id == "base_link"
    wait_until(lambda: h.local_maps, 10, "a local map")
    assert h.local_maps[0].header.frame_id == "map" and h.local_maps[0].width > 1000
    values = h.diag_values()
    assert values[0]["state"] == "initializing" or values[0]["state"] == "ok"
    assert values[-1]["state"] == "ok" and float(values[-1]["fitness"]) > 0.7
    assert {"latency_ms", "block", "dropped_scans"} <= set(values[-1])
    # the pose is published only after a verified global init
    first_ok = next(i for i, v in enumerate(values) if v["state"] == "ok")
    assert len(h.poses) == len(values) - first_ok
    assert not lines(node_log, "LiDAR-only")


def test_map_to_odom_when_the_robot_publishes_odom_to_base_link(harness):
    from blockloc.ros2 import convert
    from blockloc.ros2 import dds as d
    from blockloc.ros2 import messages as m

    h = harness()
    h.publish_static()
    tf = h.dds.writer("/tf", m.TFMessage, d.SENSOR_DATA)
    T_odom_base = np.eye(4)
    T_odom_base[:3, 3] = [5.0, 0.0, 0.0]
    for i in range(8):
        tf.write(m.TFMessage(transforms=[convert.transform_stamped(T_odom_base, h.frames[i].stamp, "odom", "base_link")]))
        h.send_scan(i)
    wait_until(lambda: any(t.transforms[0].child_frame_id == "odom" for t in h.tf), 10, "map -> odom")
    out = [t.transforms[0] for t in h.tf if t.transforms[0].child_frame_id == "odom"][-1]
    assert out.header.frame_id == "map"
    pose = next(p for p in h.poses if p.header.stamp == out.header.stamp).pose.pose
    # map -> odom composed with odom -> base_link is the published pose
    T_map_odom = convert.matrix_of(out.transform.translation, out.transform.rotation)
    T_map_base = convert.matrix_of(pose.position, pose.orientation)
    assert T_map_odom @ T_odom_base == pytest.approx(T_map_base, abs=1e-6)


def test_player_restarted_stamps_jump_back_the_tracker_starts_over(harness, node_log):
    h = harness()
    h.publish_static()
    for i in range(12):
        h.send_scan(i)
    n_before = len(h.poses)
    h._imu_next = 0
    for i in range(12):
        h.send_scan(i)
    assert h.node.stats.restarts == 1
    assert len(lines(node_log, "jumped back")) == 1
    wait_until(lambda: len(h.poses) >= n_before + 8, 20, "poses after the restart")
    assert position_error(h, h.poses[-1]) < 0.3


def test_no_scans_for_a_while_says_no_data_then_recovers(harness, node_log):
    h = harness(no_data_timeout_s=0.5)
    h.publish_static()
    for i in range(6):
        h.send_scan(i)
    wait_until(lambda: any(v["state"] == "no data" for v in h.diag_values()), 10, "a 'no data' diagnostic")
    stale = [d for d in h.diags if d.status[0].message == "no data"]
    assert stale[0].status[0].level == 3  # STALE
    assert len(lines(node_log, "no scan on /points")) == 1
    for i in range(6, 12):
        h.send_scan(i)
    wait_until(lambda: h.diag_values()[-1]["state"] == "ok", 10, "ok again")


def test_a_slower_lidar_is_judged_by_its_own_scan_period(harness, node_log):
    """Scans 0.5 s apart (a 2 Hz source, as the real walk played into the node): no gap warning,
    as ``track`` gives none on the recording (it judges against the sequence's median spacing);
    the node judged every scan against 10 Hz and warned on each. A real gap (5 s, ten periods)
    is still said once and counted."""
    h = harness()
    h.publish_static()
    for i in range(0, 55, 5):
        h.send_scan(i)
    assert not lines(node_log, "no LiDAR scan"), lines(node_log, "no LiDAR scan")
    for i in (100, 105):
        h.send_scan(i)
    assert lines(node_log, "no LiDAR scan") == ["frame 11: no LiDAR scan for 5.00 s before it"]
    assert h.node.session.counters["lidar_gaps"] == 1


def test_no_imu_at_start_tracks_lidar_only_and_says_so(harness, node_log):
    h = harness()
    h.publish_static()
    for i in range(6):
        h.send_scan(i, imu=False)
    assert h.node.session.tracker.lidar_only
    assert len(lines(node_log, "no IMU on /imu/data: LiDAR-only")) == 1
    # the tiny world has no ground to level a scan by without an accelerometer: global init says
    # why on each scan, nothing unverified is published, the node goes on
    assert len(lines(node_log, "global init failed")) == 6
    assert not h.poses and h.node.stats.failed_scans == 0
    assert {v["state"] for v in h.diag_values()} == {"initializing"}
    assert h.diag_values()[-1]["lidar_only"] == "True"


def test_imu_stopping_mid_run_falls_back_to_lidar_only(harness, node_log):
    h = harness(imu_timeout_s=0.3)
    h.publish_static()
    for i in range(10):
        h.send_scan(i)
    assert not h.node.session.tracker.lidar_only
    for i in range(10, 25):
        h.send_scan(i, imu=False)
    assert h.node.session.tracker.lidar_only
    assert len(lines(node_log, "LiDAR-only tracking from here")) == 1
    wait_until(lambda: position_error(h, h.poses[-1]) < 0.5 and len(h.poses) >= 20, 10, "poses after the IMU stopped")


def test_bad_clouds_are_skipped_with_one_line_each(harness, node_log):
    from blockloc.ros2 import convert

    h = harness()
    h.publish_static()
    for i in range(5):
        h.send_scan(i)
    f = h.frames[5]
    good = convert.cloud_from_points(f.points, f.stamp, "lidar", time_offsets=f.time_offsets)
    wrong_step = convert.cloud_from_points(f.points, f.stamp, "lidar", time_offsets=f.time_offsets)
    wrong_step.point_step = 8  # smaller than its fields
    no_x = convert.cloud_from_points(f.points, f.stamp, "lidar")
    no_x.fields[0].name = "u"
    empty = convert.cloud_from_points(np.zeros((0, 3)), f.stamp, "lidar")
    for msg in (wrong_step, no_x, empty):
        done = h.node.stats.bad_scans
        h.points.write(msg)
        wait_until(lambda: h.node.stats.bad_scans > done, 10, "a bad scan counted")
        time.sleep(0.05)
    assert h.node.stats.bad_scans == 3
    assert len(lines(node_log, "scan skipped")) == 3
    assert any("point_step" in ln for ln in lines(node_log, "scan skipped"))
    assert any("no 'x' field" in ln for ln in lines(node_log, "scan skipped"))
    assert any("empty cloud" in ln for ln in lines(node_log, "scan skipped"))
    # NaNs: dropped, counted, the scan tracked
    pts = f.points.copy()
    pts[::10] = np.nan
    with_nan = convert.cloud_from_points(pts, f.stamp, "lidar", time_offsets=f.time_offsets)
    h.send_imu_until(f.stamp + float(np.max(f.time_offsets)))
    n = h.node.stats.processed
    h.points.write(with_nan)
    wait_until(lambda: h.node.stats.processed > n, 10, "the NaN scan processed")
    assert h.node.stats.nan_points == len(pts[::10])
    assert good is not None
    for i in range(6, 10):
        h.send_scan(i)
    assert h.diag_values()[-1]["state"] == "ok"


def test_out_of_order_imu_is_dropped_with_one_line(harness, node_log):
    from blockloc.ros2 import convert

    h = harness()
    h.publish_static()
    for i in range(4):
        h.send_scan(i)
    t_last = h.all_imu.t[h._imu_next - 1]
    for dt in (0.05, 0.03):  # older than the last sample, not a restart
        h.imu.write(convert.imu_message(t_last - dt, [0, 0, 9.81], [0, 0, 0], "imu"))
    wait_until(lambda: h.node.stats.imu_out_of_order == 2, 10, "both counted")
    assert len(lines(node_log, "not after the last one")) == 1
    for i in range(4, 10):
        h.send_scan(i)
    assert h.diag_values()[-1]["state"] == "ok" and h.diag_values()[-1]["imu_out_of_order"] == "2"


def test_initialpose_in_another_frame_or_outside_the_map_is_refused(harness, node_log):
    from blockloc.ros2 import convert

    h = harness()
    h.publish_static()
    for i in range(4):
        h.send_scan(i)
    gt = h.seq.ground_truth().interpolate(np.array([h.frames[5].stamp]))[0]
    h.initialpose.write(convert.pose_with_covariance(gt, None, 0.0, "odom"))
    far = gt.copy()
    far[0, 3] += 1000.0
    h.initialpose.write(convert.pose_with_covariance(far, None, 0.0, "map"))
    wait_until(lambda: h.node.stats.refused_initialposes == 2, 10, "two refusals")
    assert len(lines(node_log, "/initialpose refused: frame 'odom'")) == 1
    assert len(lines(node_log, "outside the map")) == 1
    # a good one re-initializes around it on the next scan
    h.initialpose.write(convert.pose_with_covariance(gt, None, 0.0, "map"))
    wait_until(lambda: lines(node_log, "global init around"), 10, "accepted")
    for i in range(4, 10):
        h.send_scan(i)
    assert any("around (" in ln for ln in lines(node_log, "t="))
    assert position_error(h, h.poses[-1]) < 0.3


def test_relocalize_request_searches_the_whole_map(harness, node_log):
    from blockloc.ros2 import messages as m

    h = harness()
    h.publish_static()
    for i in range(5):
        h.send_scan(i)
    h.relocalize.write(m.Empty())
    wait_until(lambda: lines(node_log, "/blockloc/relocalize"), 10, "the request seen")
    for i in range(5, 10):
        h.send_scan(i)
    msgs = [r.getMessage() for r in node_log.records]
    asked = next(i for i, ln in enumerate(msgs) if ln.startswith("/blockloc/relocalize"))
    searched = [ln for ln in msgs[asked + 1:] if ln.startswith("t=") and "global init over the whole map" in ln]
    assert len(searched) == 1  # on the next scan, once
    assert position_error(h, h.poses[-1]) < 0.3


def test_slow_processing_drops_the_oldest_scans_never_queues_without_bound(harness):
    h = harness(queue_size=2)
    h.publish_static()
    i = 0
    while not (h.node.session is not None and h.node.session.tracker.initialized):
        h.send_scan(i)  # until tracking: scans coming during a global init may wait more (a backlog)
        i += 1
        assert i < 20, "no verified global init"
    h.node.stats.max_waiting = 0
    for i in range(i, i + 30):  # a burst far faster than the node tracks
        h.send_scan(i, wait=False)
    wait_until(lambda: h.node.stats.received >= i - 2, 10, "the burst received")
    s = h.node.stats
    wait_until(lambda: s.processed + s.dropped == s.received, 30, "every scan processed or dropped")
    assert s.dropped > 0 and s.max_waiting == 2
    assert int(h.diag_values()[-1]["dropped_scans"]) == s.dropped


def test_scans_during_the_first_global_init_wait_bounded_and_are_caught_up_on(harness):
    h = harness(queue_size=2, backlog_size=8)
    h.publish_static()
    # all at once: the node is still searching on the first when the rest come (from scan 3: the
    # global init of the scans before it finds no verified pose)
    for i in range(3, 23):
        h.send_scan(i, wait=False)
    wait_until(lambda: h.node.stats.received >= 18, 10, "the burst received")
    s = h.node.stats
    wait_until(lambda: s.processed + s.dropped + s.bad_scans + s.failed_scans == s.received, 60,
               "every scan processed or dropped")
    assert s.max_waiting <= 8 and s.dropped == s.received - s.processed
    # the scans that waited were tracked through (thinned evenly past 8), not thrown away for the newest
    assert s.caught_up >= 5 and s.processed >= 8
    values = h.diag_values()
    caught = [v for v in values if v.get("catching_up") == "True"]
    assert len(caught) == s.caught_up and all(v["state"] == "ok" for v in caught)
    wait_until(lambda: len(h.poses) >= s.caught_up, 10, "their poses")
    errors = [position_error(h, p) for p in h.poses]
    assert max(errors) < 0.5, np.round(errors, 2)
