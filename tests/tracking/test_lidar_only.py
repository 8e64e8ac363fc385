"""LiDAR-only tracking on synthetic data: no IMU (or its samples ignored), a constant-velocity prior
between keyframes, deskewing with the estimated twist, and the rotated-prediction retry."""

import numpy as np
import pytest

from blockloc.geometry import inv_T, rpy_to_R, so3_log, xyzrpy_to_T
from blockloc.tracking.params import TrackerSettings
from blockloc.app.assemble import make_tracker as tracker_from_config
from blockloc.tracking.tracker import make_tracker as build_tracker
from tests.tracking.synthetic import (
    T_BODY_LIDAR,
    CircleTrajectory,
    GicpRegistration,
    ScriptedProvider,
    imu_from_trajectory,
    make_scan,
    make_scene,
)


@pytest.fixture(scope="module")
def world():
    traj = CircleTrajectory(z_up=True)
    scene = make_scene(seed=0)
    reg = GicpRegistration()
    stamps = np.round(np.arange(0.1, 7.0, 0.1), 6)
    frames = {s: make_scan(scene, traj, s, T_BODY_LIDAR, index=i, max_points=6000, seed=5)
              for i, s in enumerate(stamps)}
    imu = imu_from_trajectory(traj, 0.0, 8.0, noise=0.01, seed=1)
    return dict(traj=traj, scene=scene, reg=reg, target=reg.build_target(scene), stamps=stamps,
                frames=frames, imu=imu)


def make_tracker(world, switch_calls=(), target=None, imu=False, **params):
    prov = ScriptedProvider(world["target"] if target is None else target, switch_calls)
    return build_tracker(imu=imu, map_provider=prov, registration=world["reg"], T_body_lidar=T_BODY_LIDAR,
                         T_body_imu=np.eye(4), gravity_map=world["traj"].gravity_map,
                         settings=TrackerSettings.of(**params))


def run(world, tracker, stamps, feed_imu=False):
    imu, out, j = world["imu"], [], 0
    for s in stamps:
        while feed_imu and j < len(imu.t) and imu.t[j] <= s:
            tracker.insert_imu(imu.t[j], imu.acc[j], imu.gyro[j])
            j += 1
        out.append(tracker.insert_frame(world["frames"][s]))
    return out


def pos_errors(world, ests):
    gt = world["traj"].pose(np.array([e.stamp for e in ests]))
    return np.array([np.linalg.norm(e.T_map_body[:3, 3] - g[:3, 3]) for e, g in zip(ests, gt)])


def test_lidar_only_tracks_deskews_and_keeps_the_20_to_5_window(world):
    tr = make_tracker(world, switch_calls=(30, 55))
    s0 = world["stamps"][0]
    tr.initialize(world["traj"].pose(s0)[0], s0)  # velocity unknown: 2 m/s against a zero prior
    ests = run(world, tr, world["stamps"])
    assert tr.lidar_only
    err = pos_errors(world, ests)
    assert np.sqrt(np.mean(err[10:] ** 2)) < 0.01 and err.max() < 0.3 and err[5:].max() < 0.03
    assert all(e.diagnostics.status == "ok" for e in ests)
    # same window behaviour as with an IMU: full at 20, 5 at a switch, growing back
    sizes = [e.diagnostics.window_size for e in ests]
    assert [i for i, e in enumerate(ests) if e.diagnostics.switched] == [30, 55]
    assert sizes[29] == 20 and sizes[30] == 5 and sizes[31:46] == list(range(6, 21)) and sizes[55] == 5
    # the twist is estimated: the map velocity matches the truth once the window has a few frames
    v_true = world["traj"].velocity(np.array([e.stamp for e in ests[10:]]))
    v_est = np.array([e.velocity_map for e in ests[10:]])
    assert np.median(np.linalg.norm(v_est - v_true, axis=1)) < 0.1
    assert np.all(ests[-1].acc_bias == 0) and np.all(ests[-1].gyro_bias == 0)
    # no jump across a switch beyond 3 sigma of the reported covariance
    traj = world["traj"]
    for k in (30, 55):
        est_rel = inv_T(ests[k - 1].T_map_body) @ ests[k].T_map_body
        gt_rel = inv_T(traj.pose(ests[k - 1].stamp)[0]) @ traj.pose(ests[k].stamp)[0]
        d = inv_T(gt_rel) @ est_rel
        dev = np.r_[so3_log(d[:3, :3]), d[:3, 3]]
        assert np.all(np.abs(dev) < 3 * np.sqrt(np.diag(ests[k].covariance))), dev
    assert tr.counters["rotation_retries"] == 0 and tr.counters["imu_only"] == 0


def test_deskewing_with_the_estimated_twist_matters(world):
    """The scans are motion-distorted (2 m/s, 0.1 s sweeps): without deskewing the error is larger."""
    s0 = world["stamps"][0]
    errs = {}
    for deskew in (True, False):
        tr = make_tracker(world, deskew=deskew)
        tr.initialize(world["traj"].pose(s0)[0], s0, world["traj"].velocity(s0)[0])
        errs[deskew] = np.sqrt(np.mean(pos_errors(world, run(world, tr, world["stamps"]))[5:] ** 2))
    assert errs[True] < 0.02 and errs[False] > 1.5 * errs[True], errs


def test_use_imu_false_ignores_the_imu_and_with_it_nothing_changes(world):
    s0 = world["stamps"][0]
    stamps = world["stamps"][:30]
    runs = {}
    for name, imu in (("forced", False), ("auto", True)):
        tr = make_tracker(world, imu=imu)
        tr.initialize(world["traj"].pose(s0)[0], s0, world["traj"].velocity(s0)[0])
        runs[name] = (tr, run(world, tr, stamps, feed_imu=True))
    forced, auto = runs["forced"], runs["auto"]
    assert forced[0].lidar_only and not auto[0].lidar_only
    assert not hasattr(forced[0], "imu") and len(auto[0].imu) > 0  # the samples were dropped
    # LiDAR-only at 10 Hz is as accurate as with the IMU here (NDT dominates); both track
    for tr, ests in (forced, auto):
        assert np.sqrt(np.mean(pos_errors(world, ests) ** 2)) < 0.03
    assert np.linalg.norm(auto[1][-1].acc_bias) > 0 and np.all(forced[1][-1].acc_bias == 0)


def test_two_hertz_keyframes(world):
    """Keyframes 0.5 s apart (as the real walk): the prior's noise scales with the gap."""
    stamps = world["stamps"][::5]
    tr = make_tracker(world)
    tr.initialize(world["traj"].pose(stamps[0])[0], stamps[0], world["traj"].velocity(stamps[0])[0])
    ests = run(world, tr, stamps)
    assert all(e.diagnostics.status == "ok" for e in ests)
    err = pos_errors(world, ests)  # measured: RMSE 0.021 m, 0.001-0.014 m from the third keyframe on
    assert np.sqrt(np.mean(err**2)) < 0.04 and err[2:].max() < 0.03


class StepTrajectory:
    """Stands at T0 until ``t_turn``, then at T1 (a sudden turn no motion model predicts)."""

    def __init__(self, T0, T1, t_turn):
        self.T0, self.T1, self.t_turn = T0, T1, t_turn

    def pose(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return np.where((t >= self.t_turn)[:, None, None], self.T1[None], self.T0[None])


@pytest.mark.parametrize("yaw_deg", [40.0, -40.0])
def test_rotated_prediction_recovers_a_scan_40_degrees_off_in_yaw(world, yaw_deg):
    T0 = xyzrpy_to_T(20.0, 0.0, 1.0, 0.0, 0.0, np.pi / 2)
    T1 = T0.copy()
    T1[:3, :3] = rpy_to_R(0.0, 0.0, np.deg2rad(yaw_deg)) @ T0[:3, :3]
    T1[:3, 3] += [0.1, 0.2, 0.0]
    step = StepTrajectory(T0, T1, 0.25)
    frame = make_scan(world["scene"], step, 0.5, T_BODY_LIDAR, index=1, max_points=6000, seed=7)
    frame.time_offsets = None  # a keyframe without per-point times, as the real walk's
    results = {}
    for retries in (True, False):
        extra = {} if retries else dict(rotation_retry_yaw_deg=(), rotation_retry_tilt_deg=())
        tr = make_tracker(world, **extra)
        tr.initialize(T0, 0.0)  # at rest: the prediction for 0.5 s later is T0, 40 deg off
        est = tr.insert_frame(frame)
        err = np.linalg.norm(est.T_map_body[:3, 3] - T1[:3, 3])
        rot = np.rad2deg(np.linalg.norm(so3_log(est.T_map_body[:3, :3].T @ T1[:3, :3])))
        results[retries] = (est.diagnostics, err, rot, dict(tr.counters))
    d, err, rot, counters = results[True]
    assert d.status == "ok" and d.rotation_retries >= 1 and d.rotation_retry.startswith("yaw")
    assert np.sign(float(d.rotation_retry[3:])) == np.sign(yaw_deg)
    assert err < 0.05 and rot < 1.0
    assert d.innovation_deg == pytest.approx(40.0, abs=2.0)  # measured against the real prediction
    assert counters["rotation_retries"] == 1 and counters["rotation_recoveries"] == 1
    # without the retry the same scan fails
    d0, err0, rot0, counters0 = results[False]
    assert d0.status == "rejected" and d0.rotation_retries == 0 and counters0["rejected"] == 1
    assert rot0 > 10.0


def test_a_turn_beyond_the_retries_falls_back_to_relocalization(world):
    """150 deg in 0.3 s: no rotated prediction reaches it. Those that converge somewhere near the
    prediction fit far worse than the scans before (ground returns are left out: this scene's
    gently sloped ground alone gives any nearby pose a fitness of 0.8 with the stand-in), so after
    max_bad_frames rejected scans the relocalizer is asked, around the last good pose, with
    gravity from the map and that pose."""
    T0 = xyzrpy_to_T(20.0, 0.0, 1.0, 0.0, 0.0, np.pi / 2)
    T1 = T0.copy()
    T1[:3, :3] = rpy_to_R(0.0, 0.0, np.deg2rad(150.0)) @ T0[:3, :3]
    step = StepTrajectory(T0, T1, 0.25)
    calls = []

    def relocalize(points, hint, gravity_body, stamp):
        calls.append((hint.copy(), gravity_body.copy()))
        return T1.copy()  # as a branch-and-bound search around the hint would find it

    prov = ScriptedProvider(world["target"])
    tr = build_tracker(imu=False, map_provider=prov, registration=world["reg"], T_body_lidar=T_BODY_LIDAR,
                       T_body_imu=np.eye(4), gravity_map=world["traj"].gravity_map, relocalize=relocalize)
    tr.initialize(T0, 0.0)
    ests = []
    for i, t in enumerate((0.0, 0.1, 0.2, 0.5, 1.0, 1.5, 2.0)):
        frame = make_scan(world["scene"], step, t, T_BODY_LIDAR, index=i, max_points=6000, seed=7)
        frame.time_offsets = None
        T = step.pose(t)[0] @ T_BODY_LIDAR
        z_map = (frame.points @ T[:3, :3].T + T[:3, 3])[:, 2]
        ests.append(tr.insert_frame(frame.select(z_map > 0.4 + 0.5)))  # ground near (20, 0): 0.4 m
    status = [e.diagnostics.status for e in ests]
    assert status == ["ok"] * 3 + ["rejected", "rejected", "recovered", "ok"]
    assert [e.diagnostics.rotation_retries for e in ests[3:6]] == [10] * 3  # 6 yaw + 2 x (roll, pitch)
    assert tr.counters["rotation_retries"] == 3 and tr.counters["rotation_recoveries"] == 0
    assert tr.counters["failures"] == 1 and tr.counters["recoveries"] == 1 and len(calls) == 1
    hint, gravity = calls[0]
    assert np.allclose(hint[:3, 3], T0[:3, 3], atol=0.05)  # the last good pose
    # gravity in the body frame of the last estimate (the map's vertical; no accelerometer)
    g_hint = hint[:3, :3].T @ world["traj"].gravity_map
    assert np.linalg.norm(gravity) == pytest.approx(9.81)
    assert np.degrees(np.arccos(gravity @ g_hint / 9.81**2)) < 5.0
    assert np.linalg.norm(ests[-1].T_map_body[:3, 3] - T1[:3, 3]) < 0.05


def test_mode_from_config_and_explicit_choice(world):
    from blockloc.config import Config
    from blockloc.datasets.base import SequenceInfo

    cfg, info = Config(), SequenceInfo("x")
    prov = ScriptedProvider(world["target"])

    def mode(**kw):
        return tracker_from_config(cfg, info, map_provider=prov, registration=world["reg"], **kw).lidar_only

    assert mode() is False  # tracking.use_imu true: the IMU (the caller says when there is none)
    assert mode(use_imu=True) is False and mode(use_imu=False) is True
    cfg.tracking.use_imu = False  # --no-imu
    assert mode() is True
    tr = tracker_from_config(cfg, info, map_provider=prov, registration=world["reg"])
    assert tr.params is cfg.tracking  # the section itself, not a copy of some of its fields
    assert tr.motion_noise.sigma_rot == cfg.tracking.motion_sigma_acc_rad_s2
    # told there is an IMU, the tracker keeps preintegration even before the first sample
    tr = make_tracker(world, imu=True)
    s0 = world["stamps"][0]
    tr.initialize(world["traj"].pose(s0)[0], s0)
    tr.insert_frame(world["frames"][s0])
    assert tr.lidar_only is False


def test_a_stop_after_fast_motion_is_found_from_the_last_estimate(world):
    """Constant velocity predicts the robot 1.5 m on, but it stopped: no rotation of the prediction
    fits, the last estimate does (the walk turned 43 deg, then 9 deg: scans 66-67)."""
    T0 = xyzrpy_to_T(20.0, 0.0, 1.0, 0.0, 0.0, np.pi / 2)
    still = StepTrajectory(T0, T0, 0.25)
    frame = make_scan(world["scene"], still, 0.5, T_BODY_LIDAR, index=1, max_points=6000, seed=11)
    frame.time_offsets = None
    tr = make_tracker(world)
    v = T0[:3, :3] @ np.array([3.0, 0.0, 0.0])  # it was driving at 3 m/s
    tr.initialize(T0, 0.0, velocity_map=v, sigma_vel_m_s=1.5)  # a velocity estimate, not a certainty
    est = tr.insert_frame(frame)
    d = est.diagnostics
    assert d.status == "ok" and d.rotation_retry == "stop", (d.status, d.rotation_retry, d.innovation_m)
    assert np.linalg.norm(est.T_map_body[:3, 3] - T0[:3, 3]) < 0.05
    assert d.innovation_m < 0.2  # measured against the stop hypothesis itself
