"""Velodyne HDL-32E model: 32 beams, 10 Hz spin, per-column firing times, motion distortion.

Frames: the lidar frame is NCLT's velodyne frame (z DOWN, as the devkit's points are; the
sensor spins clockwise seen from above, i.e. the azimuth atan2(y, x) grows with time).
Each azimuth column is cast from the lidar pose at its own firing time, and its points are
reported in the lidar frame of that instant: a sweep read without deskewing shows the motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.sim.presets import LidarModel

#: Elevation (deg, up positive) of HDL-32E lasers 0..31 in firing order (Velodyne manual).
HDL32E_ELEVATION_DEG = np.array([
    -30.67, -9.33, -29.33, -8.00, -28.00, -6.67, -26.67, -5.33, -25.33, -4.00, -24.00, -2.67,
    -22.67, -1.33, -21.33, 0.00, -20.00, 1.33, -18.67, 2.67, -17.33, 4.00, -16.00, 5.33,
    -14.67, 6.67, -13.33, 8.00, -12.00, 9.33, -10.67, 10.67])


@dataclass
class ScanResult:
    """One simulated sweep (before writing).

    points: (N, 3) float64, lidar frame at each point's own time, metres.
    intensity: (N,) float32 0..255. ring: (N,) uint16 laser id. time_offsets: (N,) float32 s
    from the sweep start. category: (N,) int, index into the scene's ``categories`` (for tests).
    """

    points: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    time_offsets: np.ndarray
    category: np.ndarray


@dataclass
class SensorCalibration:
    """One sensor's deviations from the nominal HDL-32E, drawn once per sensor (per seed).

    range_offset_m: (32,) added to every range of the laser; elevation_offset_deg,
    azimuth_offset_deg: (32,) the true beam angles minus the nominal ones (points are computed
    from the nominal ones, as the driver does); gain: (32,) intensity gain (mean 1).
    """

    range_offset_m: np.ndarray
    elevation_offset_deg: np.ndarray
    azimuth_offset_deg: np.ndarray
    gain: np.ndarray

    def fingerprint(self) -> bytes:
        return np.concatenate([self.range_offset_m, self.elevation_offset_deg,
                               self.azimuth_offset_deg, self.gain]).tobytes()

    @classmethod
    def draw(cls, model: LidarModel, seed: int) -> "SensorCalibration":
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5E_450]))
        r = rng.normal(0.0, 1.0, (4, 32))
        gain = np.exp(r[3] * model.laser_gain_sigma - 0.5 * model.laser_gain_sigma ** 2)
        return cls(r[0] * model.laser_range_offset_m, r[1] * model.laser_angle_offset_deg,
                   r[2] * model.laser_angle_offset_deg, gain)


#: Parts of the robot in the beams' way, boxes in the lidar frame (x forward, y left, z up,
#: metres): the mast and GPS antenna behind the sensor and the handle bar in front of it.
SELF_BOXES_FLU = np.array([[-1.02, -0.96, -0.025, 0.025, -0.9, 0.15],
                           [0.85, 0.95, -0.35, 0.35, -0.75, -0.55]])


def _self_hits(d_flu: np.ndarray) -> np.ndarray:
    """(N,) range at which directions (N, 3) from the lidar centre (x fwd, y left, z up) hit the
    robot (inf: they do not); slab test against SELF_BOXES_FLU."""
    out = np.full(len(d_flu), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d_flu
        for b in SELF_BOXES_FLU:
            t1 = b[0::2] * inv
            t2 = b[1::2] * inv
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (tmax >= tmin) & (tmin > 0)
            out = np.where(hit, np.minimum(out, tmin), out)
    return out


def beam_directions(azimuth_steps: int, az0: float = 0.0, calib: SensorCalibration | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (A, 32, 3) in the lidar frame (z down) and column azimuths (A,) rad.
    ``calib``: the sensor's true angles (default: the nominal ones)."""
    az = az0 + 2.0 * np.pi * np.arange(azimuth_steps) / azimuth_steps
    el = np.deg2rad(HDL32E_ELEVATION_DEG)
    az2 = np.broadcast_to(az[:, None], (azimuth_steps, 32))
    if calib is not None:
        el = el + np.deg2rad(calib.elevation_offset_deg)
        az2 = az2 + np.deg2rad(calib.azimuth_offset_deg)[None, :]
    ce, se = np.cos(el), np.sin(el)
    d = np.empty((azimuth_steps, 32, 3))
    d[..., 0] = np.cos(az2) * ce
    d[..., 1] = np.sin(az2) * ce
    d[..., 2] = -se  # z down: an upward beam has negative z
    return d, az


_BEAMS: dict = {}


def _beams(A: int, az0: float, calib: SensorCalibration | None):
    """Nominal and true beam directions (A, 32, 3) and the self-hit ranges (A * 32,), cached
    per sensor (they are the same every sweep)."""
    key = (A, float(az0), None if calib is None else calib.fingerprint())
    if key not in _BEAMS:
        if len(_BEAMS) > 8:
            _BEAMS.clear()
        d_nom, _ = beam_directions(A, az0)
        d_true = beam_directions(A, az0, calib)[0] if calib is not None else d_nom
        r_self = _self_hits(d_true.reshape(-1, 3) * [1.0, -1.0, -1.0])  # z down -> z up
        _BEAMS[key] = (d_nom, d_true, r_self)
    return _BEAMS[key]


def simulate_scan(scene, T_world_lidar_cols: np.ndarray, col_offsets: np.ndarray,
                  model: LidarModel, rng: np.random.Generator, t_mid: float | None,
                  az0: float = 0.0, calib: SensorCalibration | None = None) -> ScanResult:
    """Cast one sweep.

    scene: ``SessionScene``. T_world_lidar_cols: (A, 4, 4) true lidar pose at each column's
    firing time (world, z up). col_offsets: (A,) s from sweep start. t_mid: session time at which
    moving actors are placed (None: no actors). rng: the frame's generator. calib: the sensor's
    deviations (None: nominal). Points are reported from the nominal beam angles.
    """
    A = len(col_offsets)
    d_nom, d_true, r_self = _beams(A, az0, calib)
    R = T_world_lidar_cols[:, :3, :3]
    dirs = np.matmul(d_true, R.transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat(T_world_lidar_cols[:, :3, 3], 32, axis=0)
    h = scene.cast_full(origins, dirs, t_mid, model.max_range_m, rng)
    from blockloc.sim import _kernels

    rng_true, cat = h["range"], h["cat"]
    n = len(rng_true)
    # the draws in their order (the generator's stream is the scan's bytes); the per-ray models
    # run in the kernels, numpy's exp and power ufuncs here (see blockloc.sim._kernels)
    if model.mixed_pixel_prob > 0:
        mix_u = rng.random((A, 32)).reshape(-1)
        mix_frac = rng.uniform(0.1, 0.9, (A, 32)).reshape(-1)
    else:
        mix_u = mix_frac = np.zeros(n)
    cosi, rng_true = _kernels.lidar_ranges(rng_true, h["normal"], dirs, h["reflect"], cat, r_self,
                                           scene.categories.index("self"), bool(model.self_hits),
                                           mix_u, mix_frac, float(model.mixed_pixel_prob),
                                           float(model.mixed_pixel_gap_m))
    nrm = rng.normal(0.0, model.range_noise_m, n)
    if model.range_tail_prob > 0:
        tail_u = rng.random(n)
        # Generator.laplace(0, s, n) is s * log of its n uniform draws, computed in the kernel
        # where the tail is used; a draw of exactly 0 (p = 2^-53 a ray) makes numpy's laplace draw
        # again, so then the stream is drawn again by numpy itself
        state = rng.bit_generator.state
        lap_u = rng.random(n)
        if not lap_u.all():
            rng.bit_generator.state = state
            lap_u = None
            lap = rng.laplace(0.0, model.range_tail_scale_m, n)
    else:
        tail_u = lap_u = nrm
    u_drop = rng.random(n)
    u_graze = rng.random(n)
    u_weak = rng.random(n)
    # lognormal(0, s, n) is exp of normal(0, s, n): the exp is taken in the kernel for the kept returns
    speckle_n = rng.normal(0.0, model.intensity_speckle, n) if model.intensity_speckle > 0 else np.zeros(0)
    gain = calib.gain if calib is not None else np.ones(32)
    if lap_u is None:  # the rare redraw: the tail's values as numpy gave them
        nrm = np.where(tail_u < model.range_tail_prob, lap, nrm)
        tail_u = np.ones(n)
        lap_u = nrm
    r, ok, power, rr, snr = _kernels.lidar_returns(
        rng_true, cosi, h["reflect"], nrm, tail_u, float(model.range_tail_prob), lap_u,
        float(model.range_tail_scale_m), calib.range_offset_m if calib is not None else np.zeros(32),
        calib is not None, u_drop, u_graze, gain, float(model.max_range_m), float(model.min_range_m),
        float(model.dropout_prob), float(model.grazing_dropout_cos))
    if model.weak_return_dropout:
        # received power ~ reflectance * cos(incidence) / range^2: weak returns are lost (dark,
        # far, grazing)
        cand = np.flatnonzero(ok)
        ok[cand] = u_weak[cand] >= np.exp(-snr[cand] / 0.004)
    idx = np.flatnonzero(ok)
    # intensity: the unit reports the power partly range-compensated (see LidarModel.intensity_*)
    falloff = np.minimum(1.0, (model.intensity_knee_m / rr[idx]) ** model.intensity_exponent)
    retro_u = rng.uniform(180.0, 255.0, n)
    pts, ring, toff, i_out = _kernels.lidar_points(
        idx, r, d_nom.reshape(-1, 3), col_offsets.astype(np.float32), float(model.intensity_scale), gain,
        power, speckle_n, falloff, h["retro"], retro_u)
    return ScanResult(pts, i_out, ring, toff, cat[idx])
