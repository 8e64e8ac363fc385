"""Each error source of the simulator can be switched off, and switching it off moves its statistic
the right way (issue 15); the same seed gives the same scan, IMU and ground truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from blockloc.evaluation.realism import median_stats, scan_realism
from blockloc.sim.presets import get_preset
from blockloc.sim.stream import SimSequence

SEED = 4
FRAMES = (60, 200, 340)


def _seq(session="loc", **change) -> SimSequence:
    """The tiny world at 1080 columns with the named parts of the preset replaced."""
    p = get_preset("tiny", azimuth_steps=1080)
    for part, fields in change.items():
        p = replace(p, **{part: replace(getattr(p, part), **fields)}) if isinstance(fields, dict) \
            else replace(p, **{part: fields})
    return SimSequence(p, session, SEED)


def _stats(seq: SimSequence) -> dict:
    rows = []
    for i in FRAMES:
        f = seq.frame(i)
        rows.append(scan_realism(f.points, f.intensity, f.ring, up=(0, 0, -1)))
    return median_stats(rows)


@pytest.fixture(scope="module")
def full():
    return _stats(_seq())


def test_volumetric_vegetation_makes_points_scattered(full):
    off = _stats(_seq(detail={"volumetric_vegetation": False}))
    assert full["scattered_share"] > off["scattered_share"] + 0.02
    assert full["thickness_m"] > off["thickness_m"]
    f, cat = _seq().frame_with_labels(FRAMES[1])
    names = np.array(_seq().scene.categories + ["none"])[cat]
    assert (names == "foliage").sum() > 100


def test_ground_relief_roughens_the_ground():
    # the sensor's own per-laser offsets already spread the ground: compare without them
    exact = {"laser_range_offset_m": 0.0, "laser_angle_offset_deg": 0.0, "range_tail_prob": 0.0}
    on = _surface_error(_seq(lidar=exact), FRAMES[1], ("terrain",))
    off = _surface_error(_seq(lidar=exact, detail={"ground_relief": False}), FRAMES[1], ("terrain",))
    # grass (4-12 cm layers), kerbs (12 cm) and micro relief lift returns off the smooth terrain
    assert np.quantile(on, 0.9) > 1.5 * np.quantile(off, 0.9)
    assert np.quantile(on, 0.99) > 0.06


def test_laser_gains_spread_ground_intensity_over_rings(full):
    off = _stats(_seq(lidar={"laser_gain_sigma": 0.0}))
    assert full["ground_ring_cv"] > off["ground_ring_cv"] + 0.1


def test_weak_returns_are_lost_and_speckle_spreads_intensity():
    on = _seq().frame(FRAMES[1])
    kept = _seq(lidar={"weak_return_dropout": False}).frame(FRAMES[1])
    assert len(kept) > len(on)  # weak returns are lost ...
    # ... and they are the dark ones: most of the returns it keeps read <= 3
    assert (kept.intensity <= 3).sum() - (on.intensity <= 3).sum() > 0.5 * (len(kept) - len(on))
    plain = _seq(lidar={"intensity_speckle": 0.0}).frame(FRAMES[1])
    np.testing.assert_array_equal(plain.points, on.points)
    ok = (on.intensity < 180) & (plain.intensity < 180)  # retroreflectors read at random anyway
    assert np.std(np.log1p(on.intensity[ok])) > np.std(np.log1p(plain.intensity[ok])) + 0.02


def test_intensity_range_falloff_darkens_far_returns(full):
    flat = _seq(lidar={"intensity_exponent": 0.0})  # no fall-off: as bright at 30 m as at 3 m
    assert full["dark_share"] > _stats(flat)["dark_share"]
    on, off = _seq().frame(FRAMES[1]), flat.frame(FRAMES[1])
    np.testing.assert_array_equal(on.points, off.points)  # intensity only: the same returns
    far = np.linalg.norm(on.points, axis=1) > 10.0
    assert far.sum() > 100
    assert np.median(on.intensity[far]) < 0.5 * np.median(off.intensity[far])


def test_retroreflectors_make_bright_points():
    seq_on, seq_off = _seq(), _seq(detail={"retroreflectors": False})
    on = [seq_on.frame(i) for i in range(0, 400, 20)]
    off = [seq_off.frame(i) for i in range(0, 400, 20)]
    assert sum((f.intensity >= 180).sum() for f in on) > sum((f.intensity >= 180).sum() for f in off)


def _surface_error(seq, index, cats=("building", "wall", "ceiling", "terrain")):
    """|distance| of each static point (true pose, true extrinsic) to the world's surfaces."""
    from blockloc.sim.trajectory import D4

    f, cat = seq.frame_with_labels(index)
    names = np.array(seq.scene.categories + ["none"])[cat]
    static = np.isin(names, list(cats))
    t = f.stamp - seq.epoch_us * 1e-6 + f.time_offsets.astype(np.float64)
    uniq, inv = np.unique(np.round(t, 7), return_inverse=True)
    T = seq.trajectory.T_world_flu(uniq) @ (D4 @ seq.T_body_lidar_true)
    P = np.einsum("nij,nj->ni", T[inv][:, :3, :3], f.points) + T[inv][:, :3, 3]
    return seq.scene.distance(P[static])


def test_range_errors_widen_the_surface_error():
    lidar_off = {"range_tail_prob": 0.0, "laser_range_offset_m": 0.0, "laser_angle_offset_deg": 0.0,
                 "mixed_pixel_prob": 0.0}
    detail_off = {"ground_relief": False, "facade_detail": False}
    clean = _surface_error(_seq(lidar=lidar_off, detail=detail_off), FRAMES[1])
    tail = _surface_error(_seq(lidar={**lidar_off, "range_tail_prob": 0.2}, detail=detail_off), FRAMES[1])
    offs = _surface_error(_seq(lidar={**lidar_off, "laser_range_offset_m": 0.05}, detail=detail_off),
                          FRAMES[1])
    assert np.quantile(tail, 0.99) > 1.3 * np.quantile(clean, 0.99)
    assert np.median(offs) > 1.3 * np.median(clean)


def test_self_hits_are_near_and_can_be_switched_off():
    on = _seq().frame(FRAMES[0])
    off = _seq(lidar={"self_hits": False}).frame(FRAMES[0])
    near = lambda f: (np.linalg.norm(f.points, axis=1) < 1.3).sum()  # noqa: E731
    assert near(on) > 20 and near(off) < near(on) / 4


def test_balancing_pitch_follows_acceleration():
    on, off = _seq(session="map"), _seq(session="map", platform={"balance_pitch": False,
                                                                "wobble_deg": 0.0,
                                                                "vibration_deg": 0.0})
    t = np.arange(1.0, on.trajectory.duration - 1, 0.05)

    def pitch(seq):
        R = seq.trajectory.rotation(t)
        return np.arcsin(-R[:, 2, 0])  # forward axis below the horizon: nose down

    tr = on.trajectory
    psi = tr._sp(t)
    a = tr._sx(t, 2) * np.cos(psi) + tr._sy(t, 2) * np.sin(psi)
    d = pitch(on) - pitch(off)  # the terrain's share cancels
    assert np.deg2rad(1.0) < np.abs(d).max() < np.deg2rad(8.0)  # a few degrees
    assert np.corrcoef(d, a)[0, 1] > 0.5  # leaning into the acceleration
    assert np.abs(pitch(off) - pitch(_seq(session="map", platform={"balance_pitch": False,
                                                                   "wobble_deg": 0.0,
                                                                   "vibration_deg": 0.0,
                                                                   "vibration_z_m": 0.0}))).max() < 1e-12


def test_imu_errors_and_drops_switch_off():
    imu_off = {"scale_factor_sigma": 0.0, "misalignment_sigma_rad": 0.0, "acc_bias_instability": 0.0,
               "gyro_bias_instability": 0.0, "time_offset_s": 0.0, "drop_prob": 0.0,
               "drop_burst_per_min": 0.0}
    on, off = _seq().imu(), _seq(imu=imu_off).imu()
    assert len(on.t) < len(off.t)  # lost samples
    assert np.all(np.diff(off.t) > 0.009)
    assert np.max(np.diff(on.t)) > 0.015  # a lost sample
    burst = _seq(imu={**imu_off, "drop_burst_per_min": 30.0}).imu()
    assert np.max(np.diff(burst.t)) > 0.035  # 3-12 samples lost in a row
    # the time offset: the IMU lags; its gyro matches the ideal one read 4 ms earlier
    seq = _seq(imu={**imu_off, "time_offset_s": 0.004})
    ideal_now = seq.trajectory.imu_ideal(seq.imu().t - seq.epoch_us * 1e-6)[1]
    ideal_before = seq.trajectory.imu_ideal(seq.imu().t - seq.epoch_us * 1e-6 - 0.004)[1]
    g = seq.imu().gyro
    assert np.linalg.norm(g - ideal_before) < np.linalg.norm(g - ideal_now)


def test_extrinsic_error_is_not_told():
    seq, ideal = _seq(), _seq(extrinsic_error_m=0.0, extrinsic_error_deg=0.0)
    assert np.allclose(seq.info.T_body_lidar, ideal.info.T_body_lidar)  # nominal in both
    assert np.allclose(ideal.T_body_lidar_true, ideal.info.T_body_lidar)
    dt = np.linalg.norm(seq.T_body_lidar_true[:3, 3] - seq.info.T_body_lidar[:3, 3])
    assert 0.002 < dt < 0.05


def test_foliage_differs_between_days():
    m, loc = _seq(session="map").scene, _seq().scene
    assert m._vol_mfp is not None and not np.allclose(m._vol_mfp, loc._vol_mfp)
    same = _seq(detail={"foliage_change": 0.0}).scene
    assert np.allclose(m._vol_mfp, same._vol_mfp)


def test_same_seed_same_scan_and_imu():
    a, b = _seq(), _seq()
    fa, fb = a.frame(123), b.frame(123)
    assert fa.points.tobytes() == fb.points.tobytes()
    assert fa.intensity.tobytes() == fb.intensity.tobytes()
    assert a.imu().acc.tobytes() == b.imu().acc.tobytes()
    assert a.ground_truth().poses.tobytes() == b.ground_truth().poses.tobytes()
    c = SimSequence(a.preset, "loc", SEED + 1)
    assert len(c.frame(123)) != len(fa) or not np.array_equal(c.frame(123).points, fa.points)


def test_city_preset_opens_and_is_large():
    """Issue 19: a 3.2 km city, five mapping drives sharing one frame, a crossing localization drive."""
    from blockloc.app.catalog import open_sequence
    from blockloc.sim.stream import session_trajectory

    p = get_preset("city")
    assert min(p.size_m) >= 3000 and p.scene_window_m > 0
    maps = [s for s in p.sessions if p.is_mapping(s)]
    assert len(maps) >= 3
    lengths = [session_trajectory(p, 1, s).path_length() for s in maps]
    assert sum(lengths) >= 40_000
    seq = open_sequence("sim:city/loc")
    assert seq.info.name.startswith("sim:city/loc")
    loc = session_trajectory(p, 1, "loc").samples[::50, 1:3]
    from scipy.spatial import cKDTree

    near = []
    for s in maps:
        d, _ = cKDTree(session_trajectory(p, 1, s).samples[::20, 1:3]).query(loc)
        near.append(d < 15.0)
    near = np.array(near)
    assert near.any(axis=0).mean() > 0.95  # the localization drive stays on mapped streets
    assert (near.sum(axis=1) > 20).sum() >= 3  # and crosses several mapping drives


def test_thinned_vegetation_moves_nothing_else_and_scatters_less(full):
    from blockloc.sim.world import build_world

    p = get_preset("tiny")
    every, third = build_world(p, SEED), build_world(replace(p, vegetation=1 / 3), SEED)
    # the same roads, buildings, movables and terrain: only plants are left out
    for k in ("building", "wall", "terrain"):
        for a, b in zip(every.meshes[k], third.meshes[k]):
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(every.movables.xy, third.movables.xy)
    # each kept plant is one of the full world's, at the same place and size
    rows = {tuple(r) for r in np.c_[every.volumes.center, every.volumes.radii].round(9)}
    kept = np.c_[third.volumes.center, third.volumes.radii].round(9)
    assert all(tuple(r) in rows for r in kept)
    assert 0.15 * len(every.volumes) < len(third.volumes) < 0.55 * len(every.volumes)
    assert len(third.meshes["trunk"][1]) < len(every.meshes["trunk"][1])
    thin = _stats(_seq(vegetation=1 / 3))
    assert thin["scattered_share"] < full["scattered_share"] - 0.02
    # the campus grows a share of the plants (lawns with trees, as the real scans see)
    assert 0.0 < get_preset("campus").vegetation < 1.0 and get_preset("small").vegetation == 1.0
