"""IMU buffering and GTSAM preintegration.

The estimator's state is the BODY frame (``T_map_body``, velocity of the body origin in the map
frame); IMU samples arrive in the imu frame and GTSAM's ``body_P_sensor`` (= ``T_body_imu``) maps
them into the body frame after the bias (which lives in the imu frame) is removed. Gravity is a
vector in the map frame (NCLT and simulated sessions: z down, (0, 0, +9.81); ROS: (0, 0, -9.81)),
handed to ``PreintegrationCombinedParams`` as is: never assume z up.

gtsam is imported inside functions so importing this module stays cheap.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise (densities and random walks), units per sqrt(Hz).

    acc_noise_density: m/s^2/sqrt(Hz); gyro_noise_density: rad/s/sqrt(Hz);
    acc_bias_random_walk: m/s^3/sqrt(Hz); gyro_bias_random_walk: rad/s^2/sqrt(Hz);
    integration_sigma: position integration error, m (GTSAM's integrationCovariance).
    acc_noise_axes, gyro_noise_axes: () or per-axis densities (x, y, z) in the imu frame that
    replace the scalar ones. Why: on a moving platform the noise is what vibration and sampling
    leave, and that is not isotropic (the simulated Segway shakes mostly vertically: measured
    against ground truth, 0.35 m/s^2/sqrt(Hz) along z, 0.02-0.03 along x and y).
    """

    acc_noise_density: float = 0.004
    gyro_noise_density: float = 0.0003
    acc_bias_random_walk: float = 0.0002
    gyro_bias_random_walk: float = 0.00002
    integration_sigma: float = 1e-4
    acc_noise_axes: tuple = ()
    gyro_noise_axes: tuple = ()

    def __post_init__(self) -> None:
        from blockloc.errors import TrackingError

        for name in ("acc_noise_axes", "gyro_noise_axes"):
            v = tuple(getattr(self, name))
            if len(v) not in (0, 3) or any(not x > 0 for x in v):
                raise TrackingError(f"imu noise {name} {v!r}: expected [] or three densities > 0 (x, y, z)")

    def acc_densities(self) -> np.ndarray:
        """(3,) accelerometer white-noise density per imu axis, m/s^2/sqrt(Hz)."""
        return np.asarray(self.acc_noise_axes, float) if self.acc_noise_axes else np.full(3, self.acc_noise_density)

    def gyro_densities(self) -> np.ndarray:
        """(3,) gyro white-noise density per imu axis, rad/s/sqrt(Hz)."""
        return (np.asarray(self.gyro_noise_axes, float) if self.gyro_noise_axes
                else np.full(3, self.gyro_noise_density))


def make_preintegration_params(gravity_map: np.ndarray, T_body_imu: np.ndarray, noise: ImuNoise,
                               noise_inflation: float = 1.0):
    """``gtsam.PreintegrationCombinedParams`` for gravity (3,) m/s^2 in the map frame.

    noise_inflation multiplies every standard deviation: real IMUs are never as good as their
    datasheet once vibration and misalignment are counted.
    """
    import gtsam

    k2 = noise_inflation**2
    p = gtsam.PreintegrationCombinedParams(np.asarray(gravity_map, dtype=np.float64).reshape(3))
    I3 = np.eye(3)
    p.setAccelerometerCovariance(np.diag(noise.acc_densities() ** 2) * k2)
    p.setGyroscopeCovariance(np.diag(noise.gyro_densities() ** 2) * k2)
    p.setBiasAccCovariance(I3 * noise.acc_bias_random_walk**2 * k2)
    p.setBiasOmegaCovariance(I3 * noise.gyro_bias_random_walk**2 * k2)
    p.setIntegrationCovariance(I3 * noise.integration_sigma**2)
    if not np.allclose(T_body_imu, np.eye(4)):
        p.setBodyPSensor(gtsam.Pose3(np.asarray(T_body_imu, dtype=np.float64)))
    return p


class ImuBuffer:
    """Time-ordered IMU samples (imu frame) kept for the current window.

    Samples older than what the window needs are dropped with :meth:`discard_before`.
    Integration over [t0, t1] uses zero-order hold: each sample holds until the next one, the
    last known sample holds across gaps and past the newest sample (so an IMU gap or a frame
    that arrives before its IMU data still integrates; the gap is reported).
    """

    def __init__(self) -> None:
        self._t: list[float] = []
        self._acc: list[np.ndarray] = []
        self._gyro: list[np.ndarray] = []
        self._arrays: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # the lists as arrays

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The samples held as arrays: times (K,) s, acc (K, 3) m/s^2, gyro (K, 3) rad/s, imu frame.
        Built once per change of the buffer (a frame step reads them a dozen times); read-only."""
        if self._arrays is None:
            arrs = (np.asarray(self._t, dtype=np.float64), np.asarray(self._acc, dtype=np.float64).reshape(-1, 3),
                    np.asarray(self._gyro, dtype=np.float64).reshape(-1, 3))
            for a in arrs:
                a.flags.writeable = False
            self._arrays = arrs
        return self._arrays

    def __len__(self) -> int:
        return len(self._t)

    @property
    def last_time(self) -> float | None:
        return self._t[-1] if self._t else None

    def insert(self, t: float, acc: np.ndarray, gyro: np.ndarray) -> bool:
        """Append one sample; returns False (and ignores it) when t is not after the last one."""
        if self._t and t <= self._t[-1]:
            return False
        acc = np.asarray(acc, dtype=np.float64).reshape(3)
        gyro = np.asarray(gyro, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(acc)) and np.all(np.isfinite(gyro))):
            return False
        self._t.append(float(t))
        self._acc.append(acc)
        self._gyro.append(gyro)
        self._arrays = None
        return True

    def discard_before(self, t: float) -> None:
        """Drop samples no longer needed to integrate from t on (keeps the one holding at t)."""
        i = int(np.searchsorted(self._t, t, side="right")) - 1
        if i > 0:
            del self._t[:i], self._acc[:i], self._gyro[:i]
            self._arrays = None

    def segments(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Zero-order-hold pieces covering [t0, t1].

        Returns acc (K, 3), gyro (K, 3), dt (K,) seconds with sum(dt) = t1 - t0, and the longest
        stretch (s) inside [t0, t1] covered by no fresh sample. K = 0 when t1 <= t0 or no sample
        is known at all.
        """
        if t1 <= t0 or not self._t:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), 0.0
        t, acc_all, gyro_all = self.arrays()
        i0 = max(int(np.searchsorted(t, t0, side="right")) - 1, 0)
        i1 = int(np.searchsorted(t, t1, side="left"))
        idx = np.arange(i0, max(i1, i0 + 1))
        starts = np.maximum(t[idx], t0)
        starts[0] = t0
        ends = np.append(starts[1:], t1)
        dt = ends - starts
        keep = dt > 1e-9
        acc = acc_all[idx][keep]
        gyro = gyro_all[idx][keep]
        # Longest stretch without a fresh sample, counted from the sample holding at t0 (so a
        # gap spanning several frames is seen whole), up to t1.
        first = t[i0] if t[i0] <= t0 else t0 - (t[0] - t0)  # none before t0: extrapolated back
        knots = np.concatenate([[first], t[(t > t0) & (t < t1)], [t1]])
        max_gap = float(np.max(np.diff(knots))) if len(knots) > 1 else 0.0
        return acc, gyro, dt[keep], max_gap


def integrate(pim, buffer: ImuBuffer, t0: float, t1: float) -> float:
    """Integrate ``buffer`` over [t0, t1] into the preintegrator ``pim``; returns the longest gap (s)."""
    acc, gyro, dt, max_gap = buffer.segments(t0, t1)
    for a, w, d in zip(acc, gyro, dt):
        pim.integrateMeasurement(a, w, float(d))
    return max_gap


def predict_states(params, state_i, bias, buffer: ImuBuffer, t_i: float,
                   times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """IMU-propagated body poses at increasing ``times`` (K,) from the NavState at ``t_i``.

    Returns T_map_body (K, 4, 4) and velocities (K, 3) in the map frame. Times before t_i get
    the state at t_i (the window never needs to go back in time). One preintegration over
    [t_i, times[-1]], read at every time (the zero-order-hold pieces of ``buffer.segments``,
    one cut at each time that falls inside a piece): the same pieces as integrating from one
    time to the next.
    """
    import gtsam

    times = np.asarray(times, dtype=np.float64)
    poses = np.empty((len(times), 4, 4))
    vels = np.empty((len(times), 3))
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
    if len(times) == 0:
        return poses, vels
    acc, gyro, dt, _ = buffer.segments(t_i, float(times[-1]))
    ends = t_i + np.cumsum(dt)
    if len(ends):
        ends[-1] = max(ends[-1], float(times[-1]))  # no rounding sliver after the last piece
    j, t_at = 0, t_i  # the piece integrating now; the time integrated up to
    for k, t in enumerate(times):
        while j < len(dt) and t_at < t:
            stop = min(ends[j], t)
            if stop - t_at > 1e-9:  # as segments(): slivers below a nanosecond are not integrated
                pim.integrateMeasurement(acc[j], gyro[j], float(stop - t_at))
            t_at = stop
            if stop >= ends[j]:
                j += 1
        s = pim.predict(state_i, bias) if pim.deltaTij() > 0 else state_i
        poses[k] = s.pose().matrix()
        vels[k] = s.velocity()
    return poses, vels
