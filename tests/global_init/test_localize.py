"""Pose recovery on small synthetic maps, from a hint and without one; ambiguity; bad input."""

import math

import numpy as np
import pytest

from blockloc.errors import GlobalInitError
from blockloc.geometry import T_to_xyzrpy, xyzrpy_to_T
from blockloc.global_init.relocalize import GlobalLocalizer, InitParams, localize_points, pose_error

from .synthetic import GRAVITY_Z_DOWN, Z_DOWN, gravity_body, periodic_world_up, scan_from, world_up


@pytest.fixture(scope="module")
def zdown_map():
    return world_up(seed=3) @ Z_DOWN.T


@pytest.fixture(scope="module")
def zdown_localizer(zdown_map):
    return GlobalLocalizer.for_points(zdown_map, GRAVITY_Z_DOWN, InitParams())


def test_recovers_a_z_down_pose_from_a_hint_15_m_off_with_unknown_yaw(zdown_map, zdown_localizer):
    # z-down body (NCLT convention) on the sloped ground: roll/pitch from gravity, z from the map.
    T_true = xyzrpy_to_T(6.0, 4.0, -(1.9 + 0.02 * 6.0), 0.03, -0.02, 2.4)
    scan = scan_from(zdown_map, T_true)
    res = zdown_localizer.localize(scan, gravity_body(T_true), hint_xy=(6.0 + 11.0, 4.0 - 13.0))
    assert res.verified and not res.ambiguous
    dt, dr = pose_error(res.T_map_body, T_true)
    assert dt < 0.1 and dr < 0.5, (dt, dr)
    assert res.fitness >= InitParams().min_fitness
    # the fall-back, plain branch and bound over the window, finds it too
    bnb = GlobalLocalizer(zdown_localizer.map, InitParams(use_place_index=False)).localize(
        scan, gravity_body(T_true), hint_xy=(6.0 + 11.0, 4.0 - 13.0))
    assert bnb.verified and pose_error(bnb.T_map_body, T_true)[0] < 0.1
    assert bnb.stats["num_angles"] > 360  # full circle at the range-derived step


def test_plain_bbs_finds_the_same_pose_as_bbs_with_s0(zdown_map):
    T_true = xyzrpy_to_T(-10.0, -5.0, -1.8, 0.0, 0.0, -0.7)
    scan = scan_from(zdown_map, T_true, seed=5)
    out = []
    for use_s0 in (True, False):
        res = localize_points(zdown_map, scan, gravity_body=gravity_body(T_true), gravity_map=GRAVITY_Z_DOWN,
                              hint_xy=(-2.0, -12.0), params=InitParams(use_s0=use_s0, use_place_index=False))
        assert res.verified
        out.append(res)
    assert pose_error(out[0].T_map_body, T_true)[0] < 0.1
    assert pose_error(out[0].T_map_body, out[1].T_map_body)[0] < 0.05
    # S0 raises the pruning threshold from the start: fewer nodes are scored.
    assert out[0].stats["nodes_visited"] < out[1].stats["nodes_visited"]


def test_z_up_map_with_roll_pitch_and_a_yaw_hint():
    m = world_up(seed=4)
    T_true = xyzrpy_to_T(-5.0, 8.0, 1.8 - 0.1, 0.02, 0.03, 0.5)
    scan = scan_from(m, T_true)
    for use_index in (True, False):  # the places in the window, and plain branch and bound
        res = localize_points(m, scan, roll_pitch=(0.02, 0.03), gravity_map=(0, 0, -9.81),
                              hint_xy=(0.0, 0.0), hint_yaw=0.5 + math.radians(10), yaw_window_deg=60,
                              params=InitParams(use_place_index=use_index))
        assert res.verified
        dt, dr = pose_error(res.T_map_body, T_true)
        assert dt < 0.1 and dr < 0.5
    assert res.stats["num_angles"] < 400  # only the 60 deg yaw window was searched


def test_relocalizes_without_a_hint_over_regions(zdown_map):
    params = InitParams(reloc_window_m=60.0, use_place_index=False)
    loc = GlobalLocalizer.for_points(zdown_map, GRAVITY_Z_DOWN, params)
    T_true = xyzrpy_to_T(30.0, -25.0, -1.8, 0.0, 0.0, -2.0)
    res = loc.localize(scan_from(zdown_map, T_true, seed=7), gravity_body(T_true))
    assert res.verified
    assert pose_error(res.T_map_body, T_true)[0] < 0.1
    # 120 m of map (plus boxes over the edge) in 60 m regions: 3 x 3, searched best cheap score first
    assert res.stats["regions"] == 9 and 1 <= res.stats["regions_searched"] <= 3


def test_repeated_structure_is_reported_ambiguous_and_not_verified():
    m = periodic_world_up()
    T_true = xyzrpy_to_T(3.0, 0.0, 1.8, 0.0, 0.0, 0.0)
    scan = scan_from(m, T_true, radius=25.0)
    res = localize_points(m, scan, gravity_body=np.array([0, 0, -9.81]), gravity_map=(0, 0, -9.81),
                          hint_xy=(3.0, 0.0), window_m=40.0, params=InitParams(top_k=5))
    # Two places fit: the result is ambiguous and so not verified (its pose may be the wrong copy).
    assert res.ambiguous and not res.verified
    xs = sorted(round(c.T_map_body[0, 3] - 3.0) for c in res.candidates if c.verified)
    assert any(abs(abs(x) - 12) <= 1 for x in xs), xs  # a copy one period away was also verified


def test_bad_inputs_raise_one_line_errors(zdown_map, zdown_localizer):
    T_true = xyzrpy_to_T(0.0, 0.0, -1.8, 0.0, 0.0, 0.0)
    scan = scan_from(zdown_map, T_true)
    g = gravity_body(T_true)
    with pytest.raises(GlobalInitError, match="outside the map"):
        zdown_localizer.localize(scan, g, hint_xy=(500.0, 0.0))
    with pytest.raises(GlobalInitError, match="window 0"):
        zdown_localizer.localize(scan, g, hint_xy=(0.0, 0.0), window_m=0)
    with pytest.raises(GlobalInitError, match="yaw window"):
        zdown_localizer.localize(scan, g, hint_xy=(0.0, 0.0), yaw_window_deg=0)
    with pytest.raises(GlobalInitError, match="usable points"):
        zdown_localizer.localize(scan[:10], g, hint_xy=(0.0, 0.0))
    with pytest.raises(GlobalInitError, match="gravity"):
        zdown_localizer.localize(scan, np.zeros(3), hint_xy=(0.0, 0.0))
    for exc in (GlobalInitError,):
        with pytest.raises(exc) as info:
            zdown_localizer.localize(scan, g, hint_xy=(np.nan, 0.0))
        assert "\n" not in str(info.value)


def test_no_match_is_not_verified(zdown_map, zdown_localizer):
    # A scan of another world: the search returns its best guess, refinement does not verify it.
    other = world_up(seed=99) @ Z_DOWN.T
    T = xyzrpy_to_T(0.0, 0.0, -1.8, 0.0, 0.0, 0.3)
    res = zdown_localizer.localize(scan_from(other, T), gravity_body(T), hint_xy=(0.0, 0.0))
    assert not res.verified
    assert res.candidates and all(not c.verified for c in res.candidates)
    assert res.score < 0.6


def test_a_scan_half_outside_the_map_is_scored_on_what_overlaps_and_verified(zdown_map):
    """The map holds only x < 0 (a map built from part of a drive); the robot stands at its edge,
    half of its scan on ground the map never saw. Judged on what overlaps, the true pose is
    verified; judged on the whole scan (footprint off) it is not (fitness about the overlap share);
    and a pose hung off the edge with too little overlap is never verified."""
    m = zdown_map[zdown_map[:, 0] < 0.0]
    T_true = xyzrpy_to_T(1.0, 4.0, -(1.9 + 0.02 * 1.0), 0.0, 0.0, 0.8)
    scan = scan_from(zdown_map, T_true)  # the world as it is, beyond the map too
    res = localize_points(m, scan, gravity_body=gravity_body(T_true), gravity_map=GRAVITY_Z_DOWN, hint_xy=(-4.0, 0.0))
    dt, dr = pose_error(res.T_map_body, T_true)
    assert res.verified and dt < 0.1 and dr < 0.5, (res.verified, dt, dr)
    assert 0.3 <= res.candidates[0].overlap <= 0.7, res.candidates[0].overlap
    whole = localize_points(m, scan, gravity_body=gravity_body(T_true), gravity_map=GRAVITY_Z_DOWN, hint_xy=(-4.0, 0.0),
                            params=InitParams(footprint_cell_m=0.0))
    assert not whole.verified and whole.fitness < InitParams().min_fitness
    # Farther out, too little of the scan overlaps the map: not verified, however well it fits.
    T_far = xyzrpy_to_T(20.0, 4.0, -(1.9 + 0.02 * 20.0), 0.0, 0.0, 0.8)
    far = localize_points(m, scan_from(zdown_map, T_far), gravity_body=gravity_body(T_far), gravity_map=GRAVITY_Z_DOWN,
                          hint_xy=(-2.0, 0.0), window_m=50.0)
    assert not far.verified
    assert all(c.overlap < InitParams().min_overlap or not c.verified for c in far.candidates)


def test_an_along_street_ambiguity_is_resolved_by_a_second_scan_and_the_motion():
    """The first scan sees only the repeated boxes: ambiguous. 8 m on, the second scan sees a box
    that stands nowhere else; each hypothesis moved by the motion is verified (or not) there, and
    only the true one holds. A second scan of the same repeated stretch stays ambiguous."""
    from blockloc.geometry import inv_T
    from blockloc.global_init.second_scan import ambiguous_hypotheses, resolve_with_second_scan

    from .synthetic import box_outline

    rng = np.random.default_rng(3)
    m = np.concatenate([periodic_world_up(), box_outline(rng, 34.0, 13.0, 6.0, 4.0, 3.0, 0.0, 0.0)])
    T1 = xyzrpy_to_T(3.0, 0.0, 1.8, 0.0, 0.0, 0.0)
    g = np.array([0, 0, -9.81])
    params = InitParams(top_k=5)
    loc = GlobalLocalizer.for_points(m, (0, 0, -9.81), params)
    first = loc.localize(scan_from(m, T1, radius=25.0), g, hint_xy=(3.0, 0.0), window_m=40.0)
    assert first.ambiguous and not first.verified
    hyps = ambiguous_hypotheses(first, params)
    assert len(hyps) >= 2 and any(pose_error(h, T1)[0] < 0.3 for h in hyps)
    T2 = xyzrpy_to_T(11.0, 0.0, 1.8, 0.0, 0.0, 0.05)
    res = resolve_with_second_scan(loc, hyps, inv_T(T1) @ T2, scan_from(m, T2, radius=25.0, seed=2), g)
    assert res.verified and not res.ambiguous
    dt, dr = pose_error(res.T_map_body, T2)
    assert dt < 0.1 and dr < 0.5, (dt, dr)
    # Without the unique box in view (4 m on, still the repeated stretch): still ambiguous, not verified.
    T3 = xyzrpy_to_T(7.0, 0.0, 1.8, 0.0, 0.0, 0.0)
    same = resolve_with_second_scan(loc, hyps, inv_T(T1) @ T3, scan_from(m, T3, radius=12.0, seed=4), g)
    assert not same.verified
