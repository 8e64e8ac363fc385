"""Tracker branches the synthetic drive never takes: registration raising, a failed relocalization
at start, a covariance that cannot be computed. A robot at rest with an exact IMU; the
registration is a small scripted object behind the tracker's duck-typed interface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from blockloc.datasets.base import LidarFrame
from blockloc.errors import TrackingError
from blockloc.geometry import xyzrpy_to_T
from blockloc.tracking.params import TrackerSettings
from blockloc.tracking.tracker import make_tracker
from blockloc.tracking.window import FrozenWindow, keys_of
from tests.tracking.synthetic import LocalMap

GRAVITY = np.array([0.0, 0.0, -9.81])
T_BODY_LIDAR = xyzrpy_to_T(0.1, 0.0, 0.8, 0.0, 0.0, 0.2)
T_START = xyzrpy_to_T(5.0, -2.0, 0.0, 0.0, 0.0, 0.3)


@dataclass
class _Result:
    T_target_source: np.ndarray
    converged: bool = True
    fitness: float = 1.0
    H: np.ndarray = None


class ScriptedRegistration:
    """Returns the initial guess as the registered pose, or raises on the calls listed."""

    def __init__(self, raise_on=()):
        self.raise_on = set(raise_on)
        self.calls = 0

    def align(self, target, source_points, T_init):
        self.calls += 1
        if self.calls - 1 in self.raise_on:
            raise RuntimeError("NDT target: no voxel has enough points")
        return _Result(np.asarray(T_init), H=np.diag([1e6] * 3 + [1e4] * 3))


class FixedProvider:
    def update(self, position_map, velocity_map, stamp):
        return LocalMap(target="map")


def _frame(index, stamp, n=2000):
    rng = np.random.default_rng(index)
    pts = rng.uniform(-20, 20, (n, 3))
    return LidarFrame(index, stamp, pts.astype(np.float32), None, None, None)


def _tracker(registration, relocalize=None, **params):
    return make_tracker(imu=True, map_provider=FixedProvider(), registration=registration,
                        T_body_lidar=T_BODY_LIDAR, T_body_imu=np.eye(4), gravity_map=GRAVITY,
                        settings=TrackerSettings.of(**params), relocalize=relocalize)


def _feed_imu(tracker, t0, t1):
    for t in np.arange(t0, t1, 0.01):
        tracker.insert_imu(float(t), -GRAVITY, np.zeros(3))  # at rest, z up: the IMU reads +g up


def test_registration_raising_is_a_rejected_scan_then_lost():
    reg = ScriptedRegistration(raise_on={1, 2, 3, 4})
    tr = _tracker(reg, max_bad_frames=3)
    tr.initialize(T_START, 0.0, velocity_map=np.zeros(3))
    statuses = []
    for k in range(1, 7):
        _feed_imu(tr, 0.1 * (k - 1), 0.1 * k + 1e-9)
        est = tr.insert_frame(_frame(k, 0.1 * k))
        statuses.append(est.diagnostics.status)
        assert est.T_map_body is not None and np.isfinite(est.T_map_body).all()
        # at rest, with an exact IMU, the prediction stays at the start pose
        assert np.linalg.norm(est.T_map_body[:3, 3] - T_START[:3, 3]) < 0.01
    assert statuses == ["ok", "rejected", "rejected", "lost", "lost", "ok"]
    assert tr.counters["rejected"] == 4 and tr.counters["failures"] == 1
    assert tr.counters["rejected_error"] == 4
    assert tr.counters["recoveries"] == 0  # no relocalizer: nothing to recover with
    assert reg.calls == 6


def test_failed_relocalization_at_start_reports_uninitialized_then_starts():
    calls = []

    def relocalize(points, hint, gravity_body, stamp):
        calls.append((len(points), hint, stamp))
        return None if len(calls) == 1 else T_START

    tr = _tracker(ScriptedRegistration(), relocalize=relocalize)
    _feed_imu(tr, 0.0, 0.1)
    est = tr.insert_frame(_frame(0, 0.1))
    assert est.diagnostics.status == "uninitialized" and est.T_map_body is None
    assert est.covariance is None and not tr.initialized
    _feed_imu(tr, 0.1, 0.2)
    est = tr.insert_frame(_frame(1, 0.2))
    assert tr.initialized and est.diagnostics.status == "ok"
    np.testing.assert_allclose(est.T_map_body, T_START, atol=1e-6)
    assert [c[1] for c in calls] == [None, None] and calls[0][0] >= 100
    # too few points: no relocalization is attempted at all
    tr2 = _tracker(ScriptedRegistration(), relocalize=relocalize)
    est = tr2.insert_frame(_frame(2, 0.3, n=20))
    assert est.diagnostics.status == "uninitialized" and len(calls) == 2
    with pytest.raises(TrackingError, match="no initial pose"):
        _tracker(ScriptedRegistration()).insert_frame(_frame(3, 0.4))


def test_gravity_from_a_resting_imu_before_any_pose():
    seen = []

    def relocalize(points, hint, gravity_body, stamp):
        seen.append(gravity_body)
        return None

    T_body_imu = xyzrpy_to_T(0.0, 0.0, 0.0, np.pi, 0.0, 0.0)  # imu mounted upside down
    tr = make_tracker(imu=True, map_provider=FixedProvider(), registration=ScriptedRegistration(),
                      T_body_lidar=T_BODY_LIDAR, T_body_imu=T_body_imu, gravity_map=GRAVITY,
                      relocalize=relocalize)
    for t in np.arange(0.0, 0.5, 0.01):
        tr.insert_imu(float(t), np.array([0.0, 0.0, -9.81]), np.zeros(3))  # upside down: reads -z
    tr.insert_frame(_frame(0, 0.5))
    np.testing.assert_allclose(seen[0], [0.0, 0.0, -9.81], atol=1e-9)


def test_covariance_failure_gives_no_covariance_not_a_crash(monkeypatch):
    tr = _tracker(ScriptedRegistration())
    tr.initialize(T_START, 0.0, velocity_map=np.zeros(3))
    _feed_imu(tr, 0.0, 0.1 + 1e-9)
    est = tr.insert_frame(_frame(1, 0.1))
    assert est.covariance is not None and est.covariance.shape == (6, 6)
    assert np.all(np.linalg.eigvalsh(est.covariance) > 0)

    def indeterminant(self, key):
        raise RuntimeError("Indeterminant linear system detected while working near variable x2")

    monkeypatch.setattr(FrozenWindow, "covariance", indeterminant)
    _feed_imu(tr, 0.1 + 1e-9, 0.2 + 1e-9)
    est = tr.insert_frame(_frame(2, 0.2))
    assert est.covariance is None and est.diagnostics.status == "ok"
    assert np.linalg.norm(est.T_map_body[:3, 3] - T_START[:3, 3]) < 0.01


class OffsetRegistration(ScriptedRegistration):
    """Answers the initial guess moved by ``offset`` (4, 4, lidar frame) with ``fitness``."""

    def __init__(self, offset=np.eye(4), fitness=1.0):
        super().__init__()
        self.offset, self.fitness = offset, fitness

    def align(self, target, source_points, T_init):
        self.calls += 1
        return _Result(np.asarray(T_init) @ self.offset, fitness=self.fitness,
                       H=np.diag([1e6] * 3 + [1e4] * 3))


@pytest.mark.parametrize("offset, fitness, status", [
    (np.eye(4), 0.5, "ok"),  # fitness above min_fitness 0.4
    (np.eye(4), 0.3, "rejected"),  # below
    (xyzrpy_to_T(0.9, 0.0, 0.0, 0, 0, 0), 1.0, "ok"),  # innovation 0.9 m < 1 m
    (xyzrpy_to_T(1.5, 0.0, 0.0, 0, 0, 0), 1.0, "rejected"),  # 1.5 m
    (xyzrpy_to_T(0, 0, 0, 0, 0, np.deg2rad(12.0)), 1.0, "rejected"),  # 12 deg > 10 deg
])
def test_health_gates(offset, fitness, status):
    tr = _tracker(OffsetRegistration(offset, fitness))
    tr.initialize(T_START, 0.0, velocity_map=np.zeros(3))
    _feed_imu(tr, 0.0, 0.1 + 1e-9)
    est = tr.insert_frame(_frame(1, 0.1))
    assert est.diagnostics.status == status
    assert est.diagnostics.fitness == fitness
    from blockloc.geometry import rotation_angle

    assert est.diagnostics.innovation_deg == pytest.approx(np.rad2deg(rotation_angle(offset[:3, :3])),
                                                           abs=1e-3)
    if np.allclose(offset[:3, :3], np.eye(3)):  # (a lidar-frame rotation also moves the body)
        assert est.diagnostics.innovation_m == pytest.approx(np.linalg.norm(offset[:3, 3]), abs=1e-3)


def test_scan_is_deskewed_with_the_predicted_motion():
    """Driving at 2 m/s along x with an exact IMU: each point, measured at its own time in the
    lidar frame, reaches the registration moved to the scan time (where T_init puts it on the
    world point it came from)."""
    from scipy.spatial import cKDTree

    speed = np.array([2.0, 0.0, 0.0])
    rng = np.random.default_rng(1)
    world = rng.uniform(-15, 15, (3000, 3)) + [10.0, 0.0, 0.0]
    stamp = 0.1
    offsets = rng.uniform(-0.1, 0.0, len(world))
    T_lidar_at = np.array([xyzrpy_to_T(*(speed * (stamp + dt)), 0, 0, 0) @ T_BODY_LIDAR for dt in offsets])
    R = np.swapaxes(T_lidar_at[:, :3, :3], 1, 2)
    pts = np.einsum("nij,nj->ni", R, world - T_lidar_at[:, :3, 3])
    seen = []

    class Capture(ScriptedRegistration):
        def align(self, target, source_points, T_init):
            seen.append((np.asarray(source_points), np.asarray(T_init)))
            return super().align(target, source_points, T_init)

    tr = _tracker(Capture(), voxel_size_m=0.0, max_points=0)
    tr.initialize(np.eye(4), 0.0, velocity_map=speed)
    _feed_imu(tr, 0.0, 0.2)
    frame = LidarFrame(1, stamp, pts.astype(np.float32), None, offsets.astype(np.float32), None)
    est = tr.insert_frame(frame)
    assert est.diagnostics.status == "ok"
    src, T_init = seen[0]
    np.testing.assert_allclose(T_init[:3, 3], (xyzrpy_to_T(*(speed * stamp), 0, 0, 0) @ T_BODY_LIDAR)[:3, 3],
                               atol=1e-3)
    d, _ = cKDTree(world).query(src @ T_init[:3, :3].T + T_init[:3, 3])
    assert np.median(d) < 0.002 and d.max() < 0.01  # without deskew: up to 0.2 m


class FlawedRegistration(ScriptedRegistration):
    """From the second call on, each result has one flaw: unconverged, a poor fit, or 3 m off."""

    def __init__(self, flaw):
        super().__init__()
        self.flaw = flaw

    def align(self, target, source_points, T_init):
        r = super().align(target, source_points, T_init)
        if self.calls > 1:
            if self.flaw == "unconverged":
                r.converged = False
            elif self.flaw == "fitness":
                r.fitness = 0.1
            elif self.flaw == "innovation":
                r.T_target_source = r.T_target_source.copy()
                r.T_target_source[0, 3] += 3.0
        return r


@pytest.mark.parametrize("flaw", ["unconverged", "fitness", "innovation"])
def test_each_rejection_is_counted_under_its_reason(flaw):
    tr = _tracker(FlawedRegistration(flaw), max_bad_frames=10)
    tr.initialize(T_START, 0.0, velocity_map=np.zeros(3))
    said = []
    for k in range(1, 4):
        _feed_imu(tr, 0.1 * (k - 1), 0.1 * k + 1e-9)
        said.append(tr.insert_frame(_frame(k, 0.1 * k)).diagnostics.reject_reason)
    assert said == ["", flaw, flaw]  # what diagnostics.csv shows per scan
    reasons = {k: v for k, v in tr.counters.items() if k.startswith("rejected_") and v}
    assert tr.counters["rejected"] == 2 and reasons == {f"rejected_{flaw}": 2}


def test_imu_stopping_mid_run_goes_on_lidar_only_from_the_current_state():
    """``without_imu`` (a live IMU that stopped): a LiDAR-only estimator starting at the IMU
    estimator's newest pose and velocity, sharing its counters; the drive goes on without a jump."""
    from blockloc.tracking.lidar_only import LidarOnlyTracker
    from blockloc.tracking.window import keys_of

    v = np.array([1.0, 0.5, 0.0])  # constant velocity: the IMU reads only gravity's reaction

    def truth(t):
        T = T_START.copy()
        T[:3, 3] += v * t
        return T

    tr = _tracker(ScriptedRegistration())
    tr.initialize(truth(0.0), 0.0, velocity_map=v)
    for k in range(1, 6):
        _feed_imu(tr, 0.1 * (k - 1), 0.1 * k + 1e-9)
        est = tr.insert_frame(_frame(k, 0.1 * k))
    assert est.diagnostics.status == "ok"
    lo = tr.without_imu()
    assert isinstance(lo, LidarOnlyTracker) and lo.lidar_only and not tr.lidar_only
    assert lo.counters is tr.counters and lo.initialized and len(lo.window) == 1
    T_last = tr.window.values.atPose3(keys_of(tr.window.latest)[0]).matrix()
    np.testing.assert_allclose(lo.window.values.atPose3(keys_of(lo.window.latest)[0]).matrix(), T_last, atol=1e-9)
    assert lo.window.stamps[lo.window.latest] == pytest.approx(0.5)
    frames_before = tr.counters["frames"]
    for k in range(6, 16):
        lo.insert_imu(0.1 * k, np.zeros(3), np.ones(3))  # ignored: no IMU from here
        est = lo.insert_frame(_frame(k, 0.1 * k))
        assert est.diagnostics.status == "ok"
        assert np.linalg.norm(est.T_map_body[:3, 3] - truth(0.1 * k)[:3, 3]) < 0.01
    np.testing.assert_allclose(est.velocity_map, v, atol=0.01)
    assert tr.counters["frames"] == frames_before + 10  # one set of counters for the run
    assert lo.without_imu() is lo


def test_reset_forgets_the_state_and_the_imu_but_keeps_the_counters():
    tr = _tracker(ScriptedRegistration())
    tr.initialize(T_START, 0.0, velocity_map=np.zeros(3))
    _feed_imu(tr, 0.0, 0.1 + 1e-9)
    tr.insert_frame(_frame(1, 0.1))
    tr.reset()
    assert not tr.initialized and len(tr.imu) == 0 and tr.counters["frames"] == 1
    T2 = xyzrpy_to_T(-3.0, 4.0, 0.0, 0.0, 0.0, -1.0)
    tr.initialize(T2, 10.0, velocity_map=np.zeros(3))  # earlier history does not matter
    _feed_imu(tr, 10.0, 10.1 + 1e-9)
    est = tr.insert_frame(_frame(2, 10.1))
    assert est.diagnostics.status == "ok"
    np.testing.assert_allclose(est.T_map_body, T2, atol=1e-3)


def test_covariance_read_later_is_the_one_of_its_own_frame():
    """The covariance is computed on the first read, from the window as it was at its frame: the
    window moving on (new keyframes, marginalization) does not change it."""
    tr = _tracker(ScriptedRegistration())
    tr.initialize(T_START, 0.0, velocity_map=np.zeros(3))
    tr.window.max_size = 3  # marginalize within the few frames below
    _feed_imu(tr, 0.0, 0.1 + 1e-9)
    first = tr.insert_frame(_frame(1, 0.1))
    assert callable(first._covariance)  # deferred: not computed inside insert_frame
    then = tr.window.covariance(keys_of(tr.window.latest)[0])
    later = []
    for i in range(2, 7):
        _feed_imu(tr, 0.1 * (i - 1) + 1e-9, 0.1 * i + 1e-9)
        later.append(tr.insert_frame(_frame(i, 0.1 * i)))
    now = tr.window.covariance(keys_of(tr.window.latest)[0])
    assert not np.allclose(now, then)  # the window did move on
    np.testing.assert_allclose(first.covariance, then, rtol=1e-9, atol=1e-15)
    assert first.covariance is first.covariance  # computed once, kept
    np.testing.assert_allclose(later[-1].covariance, now, rtol=1e-9, atol=1e-15)
