"""The realism statistics (the simulator's yardstick) on real HDL-32E scans and on made-up clouds."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.evaluation import realism as R


def _real(shared_data, name):
    from pypcd4 import PointCloud

    a = PointCloud.from_path(shared_data / "hdl32e_pair" / f"{name}.pcd").numpy().astype(np.float64)
    return a[:, :3], a[:, 3]


@pytest.mark.parametrize("name", ["source", "target"])
def test_real_scans_give_the_issue_table(shared_data, name):
    """Issue 15's table for the real scans: 0.165 deg, 20 %, 97 mm, 22 mm, 16.5 % / 0.8 %, 0.49."""
    pts, inten = _real(shared_data, name)
    s = R.scan_realism(pts, inten, None, up=(0, 0, 1))
    assert 0.160 < s["azimuth_step_deg"] < 0.170
    assert 0.15 < s["scattered_share"] < 0.26
    assert 0.065 < s["thickness_m"] < 0.13
    assert 0.015 < s["ground_residual_m"] < 0.03
    assert 0.14 < s["dark_share"] < 0.20
    assert 0.002 < s["bright_share"] < 0.015
    assert 0.35 < s["ground_ring_cv"] < 0.6


def test_real_intensity_falls_off_with_range(shared_data):
    """The real pair's intensity by range (the simulator's intensity yardstick): dark returns
    are about twice as common at 5-20 m as within 5 m, and the median drops by half."""
    prof = R.intensity_by_range([_real(shared_data, n) for n in ("source", "target")])
    near, mid, far = prof[0], prof[1], prof[2]
    assert near["share"] > 0.5  # an enclosed place: most returns within 5 m
    assert 0.08 < near["dark"] < 0.18 and mid["dark"] > 1.6 * near["dark"] and far["dark"] > 0.2
    assert mid["median"] < 0.6 * near["median"]
    assert abs(sum(b["share"] for b in prof) - 1.0) < 0.05  # what lies beyond 40 m


def test_intensity_by_range_on_made_up_returns():
    r = np.r_[np.full(10, 2.0), np.full(10, 7.0), np.full(5, 50.0)]
    pts = np.c_[r, np.zeros(25), np.zeros(25)]
    inten = np.r_[np.full(10, 20.0), np.full(5, 2.0), np.full(5, 30.0), np.full(5, 1.0)]
    prof = R.intensity_by_range([(pts, inten)])
    assert [b["share"] for b in prof] == [0.4, 0.4, 0.0, 0.0]
    assert prof[0]["dark"] == 0.0 and prof[1]["dark"] == 0.5 and np.isnan(prof[2]["dark"])
    assert prof[0]["median"] == 20.0 and prof[1]["median"] == 16.0


def test_rings_from_elevation_recover_the_laser_ids(shared_data):
    pts, _ = _real(shared_data, "source")
    ring = R.rings_from_elevation(pts)
    assert len(np.unique(ring)) == 32
    el = np.degrees(np.arcsin(pts[:, 2] / np.maximum(np.linalg.norm(pts, axis=1), 1e-9)))
    ok = np.linalg.norm(pts, axis=1) > 0.1
    assert np.abs(el[ok] - R.HDL32E_ELEVATION_DEG[ring[ok]]).max() < 0.05
    # frame handling: the same cloud with z down (the NCLT lidar frame) gives the same rings
    assert np.array_equal(R.rings_from_elevation(pts * [1, -1, -1], up=(0, 0, -1)), ring)


def _synthetic_scan(rng, wall_noise=0.01, bush=False, ground_noise=0.005, gains=None):
    """A flat ground disc and a wall (and optionally a bush of scattered points), z up."""
    n = 40000
    r = rng.uniform(2.0, 20.0, n)
    a = rng.uniform(-np.pi, np.pi, n)
    ring = rng.integers(0, 32, n)
    ground = np.c_[r * np.cos(a), r * np.sin(a), -1.8 + rng.normal(0, ground_noise, n)]
    gi = 20.0 * (np.ones(32) if gains is None else gains)[ring] + rng.normal(0, 1, n)
    m = 15000
    wall = np.c_[np.full(m, 8.0) + rng.normal(0, wall_noise, m), rng.uniform(-6, 6, m),
                 rng.uniform(-1.5, 3.0, m)]
    parts, inten, rings = [ground, wall], [gi, np.full(m, 50.0)], [ring, rng.integers(0, 32, m)]
    if bush:
        c = rng.normal(0, 0.8, (m, 3)) + [-6.0, 0.0, 0.5]
        parts.append(c)
        inten.append(np.full(m, 10.0))
        rings.append(rng.integers(0, 32, m))
    return np.concatenate(parts), np.concatenate(inten), np.concatenate(rings)


def test_statistics_move_the_right_way_on_synthetic_clouds():
    rng = np.random.default_rng(3)
    base = R.scan_realism(*_synthetic_scan(rng))
    rough = R.scan_realism(*_synthetic_scan(rng, wall_noise=0.06, ground_noise=0.03))
    bush = R.scan_realism(*_synthetic_scan(rng, bush=True))
    gains = R.scan_realism(*_synthetic_scan(rng, gains=rng.lognormal(0, 0.5, 32)))
    assert base["scattered_share"] < 0.05 and bush["scattered_share"] > 0.2
    assert base["thickness_m"] < 0.02 < rough["thickness_m"]
    assert base["ground_residual_m"] < 0.01 and 0.02 < rough["ground_residual_m"] < 0.04
    assert base["ground_ring_cv"] < 0.05 and gains["ground_ring_cv"] > 0.25
    assert base["dark_share"] == 0.0 and base["bright_share"] == 0.0


def test_median_stats_ignore_nan():
    rows = [dict.fromkeys(R.STAT_NAMES, 1.0), dict.fromkeys(R.STAT_NAMES, float("nan")),
            dict.fromkeys(R.STAT_NAMES, 3.0)]
    assert R.median_stats(rows)["thickness_m"] == 2.0
