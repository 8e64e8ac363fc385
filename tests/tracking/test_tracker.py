"""The tracker on synthetic data: exact IMU from an analytic trajectory, motion-distorted scans of a
point-cloud scene, small_gicp standing in for NDT (same H convention)."""

import numpy as np
import pytest

from blockloc.errors import TrackingError
from blockloc.geometry import inv_T, so3_log, xyzrpy_to_T
from blockloc.tracking.imu import ImuNoise
from blockloc.tracking.params import TrackerSettings
from blockloc.tracking.tracker import make_tracker as build_tracker
from tests.tracking.synthetic import (T_BODY_LIDAR, CircleTrajectory, GicpRegistration, ScriptedProvider,
                                      imu_from_trajectory, make_scan, make_scene)

T_BODY_IMU = xyzrpy_to_T(0.2, 0.0, -0.1, 0.0, 0.0, 0.5)
ACC_BIAS, GYRO_BIAS = np.array([0.05, -0.03, 0.02]), np.array([0.002, -0.001, 0.001])


@pytest.fixture(scope="module")
def world():
    traj = CircleTrajectory(z_up=False)  # NCLT-like z-down map
    scene = make_scene(seed=0) * np.array([1.0, -1.0, -1.0])
    reg = GicpRegistration()
    target = reg.build_target(scene)
    imu = imu_from_trajectory(traj, 0.0, 10.0, T_body_imu=T_BODY_IMU, acc_bias=ACC_BIAS, gyro_bias=GYRO_BIAS,
                              noise=0.01, seed=1)
    stamps = np.round(np.arange(0.1, 7.0, 0.1), 6)
    frames = {s: make_scan(scene, traj, s, T_BODY_LIDAR, index=i, max_points=6000, seed=5)
              for i, s in enumerate(stamps)}
    return dict(traj=traj, reg=reg, target=target, imu=imu, stamps=stamps, frames=frames)


def make_tracker(world, switch_calls=(), relocalize=None, **params):
    prov = ScriptedProvider(world["target"], switch_calls)
    return build_tracker(imu=True, map_provider=prov, registration=world["reg"], T_body_lidar=T_BODY_LIDAR,
                         T_body_imu=T_BODY_IMU,
                   gravity_map=world["traj"].gravity_map, imu_noise=ImuNoise(0.01, 0.001, 0.001, 0.0001),
                   settings=TrackerSettings.of(**params), relocalize=relocalize)


def run(world, tracker, skip=lambda s: False, imu_keep=lambda t: True, empty=lambda s: False):
    imu, out = world["imu"], []
    j = 0
    for s in world["stamps"]:
        while j < len(imu.t) and imu.t[j] <= s:
            if imu_keep(imu.t[j]):
                tracker.insert_imu(imu.t[j], imu.acc[j], imu.gyro[j])
            j += 1
        if skip(s):
            continue
        frame = world["frames"][s]
        if empty(s):
            frame = frame.select(np.zeros(len(frame), bool))
        out.append(tracker.insert_frame(frame))
    return out


def errors(world, ests):
    gt = world["traj"].pose(np.array([e.stamp for e in ests]))
    return np.array([np.linalg.norm(e.T_map_body[:3, 3] - g[:3, 3]) for e, g in zip(ests, gt)])


def start(world, tracker, offset=np.zeros(3)):
    s0 = world["stamps"][0]
    T0 = world["traj"].pose(s0)[0].copy()
    T0[:3, 3] += offset
    tracker.initialize(T0, s0, world["traj"].velocity(s0)[0])


def test_tracks_and_shrinks_the_window_at_switches(world):
    tr = make_tracker(world, switch_calls=(30, 55))
    start(world, tr)
    ests = run(world, tr)
    err = errors(world, ests)
    assert np.sqrt(np.mean(err**2)) < 0.03
    sizes = [e.diagnostics.window_size for e in ests]
    sw = [i for i, e in enumerate(ests) if e.diagnostics.switched]
    assert sw == [30, 55]
    assert max(sizes) == 20 and sizes[29] == 20
    assert sizes[30] == 5 and sizes[31:46] == list(range(6, 21)) and sizes[46] == 20
    assert sizes[55] == 5 and tr.counters["switches"] == 2
    # No jump across a switch larger than 3 sigma: the estimated motion into the switch frame
    # matches the true motion within 3 standard deviations per axis.
    traj = world["traj"]
    for k in sw:
        est_rel = inv_T(ests[k - 1].T_map_body) @ ests[k].T_map_body
        gt_rel = inv_T(traj.pose(ests[k - 1].stamp)[0]) @ traj.pose(ests[k].stamp)[0]
        d = inv_T(gt_rel) @ est_rel
        dev = np.r_[so3_log(d[:3, :3]), d[:3, 3]]
        sigma = np.sqrt(np.diag(ests[k].covariance))
        assert np.all(np.abs(dev) < 3 * sigma), (dev, sigma)
    # biases are estimated (the IMU has a real bias)
    assert np.linalg.norm(ests[-1].acc_bias - ACC_BIAS) < 0.02
    assert np.linalg.norm(ests[-1].gyro_bias - GYRO_BIAS) < 5e-4
    assert all(e.diagnostics.status == "ok" for e in ests)


def test_lidar_dropout_of_one_second_is_bridged_by_the_imu(world):
    tr = make_tracker(world)
    start(world, tr)
    ests = run(world, tr, skip=lambda s: 3.0 <= s < 4.0)
    err = errors(world, ests)
    after = [i for i, e in enumerate(ests) if e.stamp >= 4.0][0]
    assert ests[after].diagnostics.innovation_m < 0.3  # the IMU alone carried the pose across 1 s
    assert ests[after].diagnostics.status == "ok"
    # the first estimate follows the first scan's registration, 5.7 cm off in this world (its
    # factor, 2 cm floor, outweighs the 0.1 m initial prior); the claim is on the frames after it
    assert err[0] < 0.07 and err[1:].max() < 0.05
    # frames that arrive empty are IMU-only keyframes, and tracking goes on
    tr2 = make_tracker(world)
    start(world, tr2)
    ests2 = run(world, tr2, empty=lambda s: 3.0 <= s < 4.0)
    statuses = [e.diagnostics.status for e in ests2 if 3.0 <= e.stamp < 4.0]
    assert statuses and set(statuses) == {"imu_only"}
    assert errors(world, ests2).max() < 0.2 and tr2.counters["recoveries"] == 0


def test_imu_gap_is_handled(world):
    tr = make_tracker(world)
    start(world, tr)
    ests = run(world, tr, imu_keep=lambda t: not (2.0 <= t < 2.3))
    gaps = [e.diagnostics.imu_gap_s for e in ests]
    assert max(gaps) > 0.25
    err = errors(world, ests)
    # the first estimate follows the first scan's registration, 5.7 cm off in this world (its
    # factor, 2 cm floor, outweighs the 0.1 m initial prior); the claim is on the frames after it
    assert err[0] < 0.07 and err[1:].max() < 0.05
    assert all(e.diagnostics.status == "ok" for e in ests)


class FakeGlobalInit:
    """Answers the true pose when the hint is within its search window (as BBS would), else None."""

    def __init__(self, traj, window_m=40.0):
        self.traj, self.window_m, self.calls = traj, window_m, []

    def __call__(self, points, hint, gravity_body, stamp):
        self.calls.append((None if hint is None else hint.copy(), gravity_body, stamp))
        T = self.traj.pose(stamp)[0]
        if hint is not None and np.abs(hint[:2, 3] - T[:2, 3]).max() > self.window_m / 2:
            return None
        return T


def test_kidnapped_start_is_detected_and_recovered(world):
    reloc = FakeGlobalInit(world["traj"])
    tr = make_tracker(world, relocalize=reloc)
    start(world, tr, offset=np.array([6.0, -4.0, 0.0]))
    ests = run(world, tr)
    assert tr.counters["failures"] == 1 and tr.counters["recoveries"] == 1
    hint = reloc.calls[0][0]
    assert np.linalg.norm(hint[:2, 3] - (world["traj"].pose(world["stamps"][0])[0][:2, 3] + [6, -4])) < 1.0
    # gravity handed to global init is the body-frame gravity (z down map: +z in body when level)
    g = reloc.calls[0][1]
    assert g[2] > 9.0
    rec = [i for i, e in enumerate(ests) if e.diagnostics.status == "recovered"][0]
    assert rec <= 4
    err = errors(world, ests)
    # velocity and biases restart from their priors (zero velocity while moving at 2 m/s):
    # a short transient (8 frames: 0.039 m at frames 5-6 after the recovery), then the window has them back
    assert err[rec:].max() < 0.15 and err[rec + 8:].max() < 0.03


def test_start_without_pose_uses_global_localization(world):
    reloc = FakeGlobalInit(world["traj"])
    tr = make_tracker(world, relocalize=reloc)
    ests = run(world, tr)
    assert reloc.calls[0][0] is None  # whole map, no hint
    err = errors(world, ests)  # the velocity is unknown at the start (2 m/s, prior 0 +- 1)
    assert err.max() < 0.3 and err[10:].max() < 0.03
    with pytest.raises(TrackingError):
        make_tracker(world).insert_frame(world["frames"][world["stamps"][0]])


def test_odometry_factor_option_tracks_too(world):
    tr = make_tracker(world, use_odometry_factor=True, compute_covariance=False)
    start(world, tr)
    ests = run(world, tr)
    assert np.sqrt(np.mean(errors(world, ests) ** 2)) < 0.03
    assert ests[-1].covariance is None


def test_a_start_with_the_velocity_unknown_settles_it_from_the_second_scan(world):
    """A global init gives a pose, not a velocity: the first scans are deskewed with zero velocity
    and land about v x half a sweep off. From the second keyframe on the velocity is known, and the
    window starts again with it (Estimator._settle): the second pose is right, not only after the
    window has forgotten the misplaced scans."""
    tr = make_tracker(world)
    s0 = world["stamps"][0]
    tr.initialize(world["traj"].pose(s0)[0], s0)  # no velocity
    err = errors(world, run(world, tr))
    counted = tr.counters["frames"]
    assert counted == len(world["stamps"])  # the scans registered again are counted once
    assert err[1] < 0.05 and err[2:12].max() < 0.05, np.round(err[:12], 3)
