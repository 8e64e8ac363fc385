"""The error breakdown (blockloc.evaluation.breakdown) on synthetic trajectories whose error is known."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.errors import EvaluationError
from blockloc.evaluation.breakdown import breakdown_metrics, error_breakdown
from blockloc.geometry import Trajectory, make_T, so3_exp


def circle(radius=20.0, speed=5.0, rate_hz=10.0, duration_s=30.0, z=0.0):
    """A counter-clockwise circle (z up), body x along the direction of travel."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    w = speed / radius
    th = w * t
    poses = np.stack([make_T(so3_exp(np.array([0.0, 0.0, a + np.pi / 2])),
                             np.array([radius * np.cos(a), radius * np.sin(a), z])) for a in th])
    return Trajectory(t, poses)


def moved(poses, offsets_body):
    """Each pose moved by (3,) metres in its own body frame (x forward, y left)."""
    out = poses.copy()
    out[:, :3, 3] += np.einsum("nij,j->ni", poses[:, :3, :3], np.asarray(offsets_body, float))
    return out


def test_a_planted_50_ms_lag_is_recovered_as_the_time_shift():
    gt = circle(speed=5.0)
    est_poses = gt.interpolate(gt.stamps - 0.05)  # at stamp t the estimate is where gt was 50 ms ago
    inner = slice(5, -5)  # interpolate clamps at the ends
    b = error_breakdown(gt.stamps[inner], gt.poses[inner], est_poses[inner])
    assert b.time_shift_s == pytest.approx(0.05, abs=1e-3)
    m = breakdown_metrics(b)
    assert m["err_along_mean_m"] == pytest.approx(-0.25, abs=3e-3)  # 5 m/s x 50 ms behind
    # inward (left, on a counter-clockwise circle): 1.6 mm of arc over 0.25 m, 1.6 mm of the
    # interpolated 0.5 m chord
    assert 0.0 < m["err_cross_mean_m"] < 4e-3
    assert m["err_along_rms_after_shift_m"] < 3e-3
    # an estimate 50 ms ahead: the opposite sign
    ahead = error_breakdown(gt.stamps[inner], gt.poses[inner], gt.interpolate(gt.stamps + 0.05)[inner])
    assert ahead.time_shift_s == pytest.approx(-0.05, abs=1e-3)


def test_a_constant_offset_is_recovered_and_does_not_pass_for_a_time_shift():
    gt = circle()
    off = np.array([0.10, -0.05, 0.02])
    est = gt.poses.copy()
    est[:, :3, 3] += off
    b = error_breakdown(gt.stamps, gt.poses, est)
    np.testing.assert_allclose(b.offset_m, off, atol=1e-3)  # 1.5 turns: the mean over whole turns
    m = breakdown_metrics(b)
    assert m["err_vertical_mean_m"] == pytest.approx(0.02) and m["err_vertical_rms_m"] == pytest.approx(0.02)
    # turning with the heading, a fixed map-frame offset averages out along and across track
    assert abs(m["err_along_mean_m"]) < 0.02 and abs(m["err_cross_mean_m"]) < 0.02
    assert abs(b.time_shift_s) < 0.004


def test_lateral_and_along_track_errors_are_told_apart_on_a_curved_path():
    gt = circle(radius=15.0, speed=4.0)
    left = error_breakdown(gt.stamps, gt.poses, moved(gt.poses, [0.0, 0.1, 0.0]))
    m = breakdown_metrics(left)
    assert m["err_cross_mean_m"] == pytest.approx(0.1, abs=2e-3)  # z x forward = left in a z-up map
    assert abs(m["err_along_mean_m"]) < 2e-3 and abs(left.time_shift_s) < 1e-3
    ahead = breakdown_metrics(error_breakdown(gt.stamps, gt.poses, moved(gt.poses, [0.1, 0.0, 0.0])))
    assert ahead["err_along_mean_m"] == pytest.approx(0.1, abs=2e-3)
    assert ahead["err_along_rms_m"] == pytest.approx(0.1, abs=2e-3)
    assert abs(ahead["err_cross_mean_m"]) < 2e-3
    assert ahead["err_time_shift_s"] == pytest.approx(-0.1 / 4.0, abs=1e-3)  # 0.1 m ahead at 4 m/s


def test_error_against_speed_and_turn_rate_lands_in_the_right_bins():
    # 10 s straight north at 1.5 m/s into a 10 m circle at 6 m/s (34 deg/s); only the circle errs
    slow_t = np.arange(0.0, 10.0, 0.1)
    yaw90 = so3_exp(np.array([0.0, 0.0, np.pi / 2]))
    slow = np.stack([make_T(yaw90, np.array([10.0, 1.5 * (t - 10.0), 0.0])) for t in slow_t])
    fast = circle(radius=10.0, speed=6.0, duration_s=10.0)
    stamps = np.r_[slow_t, 10.0 + fast.stamps]
    G = np.concatenate([slow, fast.poses])
    P = np.concatenate([slow, moved(fast.poses, [0.0, 0.2, 0.0])])
    m = breakdown_metrics(error_breakdown(stamps, G, P))
    # central differences: the first circle pose sees (0.15 + 0.6) m in 0.2 s = 3.75 m/s
    by_speed = {r["lo"]: r for r in m["err_by_speed"]}
    assert {k: r["count"] for k, r in by_speed.items()} == {1.0: 100, 2.0: 1, 4.0: 99}
    assert by_speed[1.0]["trans_rmse_m"] == pytest.approx(0.0, abs=1e-9) and by_speed[1.0]["hi"] == 2.0
    assert by_speed[4.0]["trans_rmse_m"] == pytest.approx(0.2) and by_speed[4.0]["hi"] == 8.0
    assert by_speed[4.0]["cross_rms_m"] == pytest.approx(0.2, abs=1e-3)
    assert abs(by_speed[4.0]["along_mean_m"]) < 1e-3
    # the first circle pose turns 0.06 rad in 0.2 s (17 deg/s) by central differences
    by_turn = {r["lo"]: r for r in m["err_by_turn_rate"]}
    assert {k: r["count"] for k, r in by_turn.items()} == {0.0: 100, 10.0: 1, 20.0: 99}
    assert by_turn[20.0]["trans_rmse_m"] == pytest.approx(0.2) and by_turn[0.0]["trans_rmse_m"] < 1e-9


def test_standing_still_has_no_direction_and_bad_input_is_one_error():
    t = np.arange(0.0, 5.0, 0.1)
    G = np.repeat(np.eye(4)[None], len(t), axis=0)
    P = G.copy()
    P[:, :3, 3] = [0.1, 0.0, 0.0]
    m = breakdown_metrics(error_breakdown(t, G, P))
    assert m["err_moving_poses"] == 0 and m["err_along_mean_m"] is None and m["err_time_shift_s"] is None
    assert m["err_offset_m"] == pytest.approx([0.1, 0.0, 0.0])
    with pytest.raises(EvaluationError, match="increasing stamps"):
        error_breakdown(t[:1], G[:1], P[:1])
    with pytest.raises(EvaluationError, match="expected as many of each"):
        error_breakdown(t, G, P[:3])


def test_a_body_frame_offset_and_a_lag_are_told_apart_when_the_speed_varies():
    """An estimate 2 cm behind in the body frame (a mounting error) and 30 ms late, on a path whose
    speed goes 0.5 -> 3 m/s: the fit with an intercept separates them; the body-frame offset
    holds the 2 cm; the 1-D fit alone blames it all on the lag."""
    t = np.arange(0.0, 40.0, 0.1)
    s_path = 0.5 * t + 2.5 * t**2 / 80.0  # speed 0.5 + t / 16 m/s
    th = s_path / 25.0
    gt = Trajectory(t, np.stack([make_T(so3_exp(np.array([0.0, 0.0, a + np.pi / 2])),
                                        np.array([25 * np.cos(a), 25 * np.sin(a), 0.0])) for a in th]))
    est = moved(gt.interpolate(t - 0.03), [-0.02, 0.0, 0.0])
    inner = slice(3, None)
    m = breakdown_metrics(error_breakdown(t[inner], gt.poses[inner], est[inner]))
    assert m["err_time_shift_with_offset_s"] == pytest.approx(0.03, abs=2e-3)
    assert m["err_along_offset_m"] == pytest.approx(-0.02, abs=2e-3)
    assert m["err_body_offset_m"][0] == pytest.approx(-0.02 - 0.03 * np.mean(0.5 + t[inner] / 16), abs=3e-3)
    assert m["err_time_shift_s"] > 0.035  # without the intercept the offset looks like more lag
    # at one speed the two cannot be told apart: no such fit
    still = breakdown_metrics(error_breakdown(*(lambda g: (g.stamps, g.poses, moved(g.poses, [-0.02, 0, 0])))(circle())))
    assert still["err_along_offset_m"] is None and still["err_body_offset_m"][0] == pytest.approx(-0.02)
