"""Hinted global initialization: the place index inside the hint's window, branch and bound where it
cannot answer (blockloc/global_init/hinted.py)."""

import numpy as np
import pytest

from blockloc.geometry import xyzrpy_to_T
from blockloc.global_init.relocalize import GlobalLocalizer, InitParams, pose_error

from .synthetic import GRAVITY_Z_DOWN, Z_DOWN, gravity_body, periodic_world_up, scan_from, world_up

G_UP = np.array([0.0, 0.0, -9.81])


@pytest.fixture(scope="module")
def periodic():
    m = periodic_world_up()
    loc = GlobalLocalizer.for_points(m, G_UP, InitParams())
    assert len(loc.place_index) > 0  # the corridor's boxes give places
    return m, loc


@pytest.mark.parametrize("copy", [-3, 0, 2])
def test_only_the_hint_tells_identical_copies_apart_and_the_index_searches_its_window(periodic, copy):
    # Identical boxes every 12 m along x: whole-map search cannot tell the copies apart (see
    # test_repeated_structure_is_reported_ambiguous_and_not_verified); an 8 m window can.
    m, loc = periodic
    T_true = xyzrpy_to_T(3.0, 0.0, 1.8, 0.0, 0.0, 0.0)
    scan = scan_from(m, T_true, radius=25.0)
    hint = (3.0 + 12.0 * copy + 1.5, -1.0)
    res = loc.localize(scan, G_UP, hint_xy=hint, window_m=8.0)
    assert res.verified and not res.ambiguous
    assert res.stats["hint_search"] == "places" and 0 < res.stats["places_in_window"] < len(loc.place_index)
    T_copy = T_true.copy()
    T_copy[0, 3] += 12.0 * copy
    dt, dr = pose_error(res.T_map_body, T_copy)
    assert dt < 0.15 and dr < 0.5, (dt, dr)
    # and every candidate refined lies in the window: none from another copy
    for c in res.candidates:
        assert abs(c.T_map_body[0, 3] - hint[0]) <= 4.0 + 1.0 and abs(c.T_map_body[1, 3] - hint[1]) <= 4.0 + 1.0


def test_a_window_holding_two_copies_stays_ambiguous(periodic):
    m, loc = periodic
    T_true = xyzrpy_to_T(3.0, 0.0, 1.8, 0.0, 0.0, 0.0)
    res = loc.localize(scan_from(m, T_true, radius=25.0), G_UP, hint_xy=(4.5, -1.0), window_m=40.0)
    assert res.ambiguous and not res.verified


@pytest.fixture(scope="module")
def zdown():
    m = world_up(seed=3) @ Z_DOWN.T
    return m, GlobalLocalizer.for_points(m, GRAVITY_Z_DOWN, InitParams())


def test_a_hint_15_m_off_finds_the_pose_through_the_places_with_fewer_nodes_than_branch_and_bound(zdown):
    m, loc = zdown
    T_true = xyzrpy_to_T(6.0, 4.0, -(1.9 + 0.02 * 6.0), 0.03, -0.02, 2.4)
    scan, g = scan_from(m, T_true), gravity_body(T_true)
    res = loc.localize(scan, g, hint_xy=(6.0 + 11.0, 4.0 - 13.0))
    bnb = GlobalLocalizer(loc.map, InitParams(use_place_index=False)).localize(scan, g, hint_xy=(17.0, -9.0))
    for r in (res, bnb):
        assert r.verified and not r.ambiguous
        assert pose_error(r.T_map_body, T_true)[0] < 0.1
    assert res.stats["hint_search"] == "places" and bnb.stats["hint_search"] == "branch and bound"
    assert res.stats["nodes_visited"] < 0.5 * bnb.stats["nodes_visited"]


def _without_places_near(loc, xy_map, radius_m):
    """A localizer on the same map whose index lacks every place within ``radius_m`` of ``xy_map``."""
    index = loc.place_index
    c = (index.R_L_map @ np.r_[xy_map, 0.0])[:2]
    keep = np.linalg.norm(index.xy_L - c, axis=1) > radius_m
    assert 0 < keep.sum() < len(index)
    return GlobalLocalizer(loc.map, InitParams(), place_index=index.subset(keep))


def test_branch_and_bound_searches_a_window_that_holds_no_indexed_place(zdown):
    m, loc = zdown
    T_true = xyzrpy_to_T(-10.0, -5.0, -1.8, 0.0, 0.0, -0.7)
    no_places = _without_places_near(loc, (-8.0, -6.0), 30.0)  # none in the 40 m window
    res = no_places.localize(scan_from(m, T_true, seed=5), gravity_body(T_true), hint_xy=(-8.0, -6.0))
    assert res.stats["places_in_window"] == 0 and res.stats["hint_search"] == "branch and bound"
    assert res.verified and pose_error(res.T_map_body, T_true)[0] < 0.1


def test_branch_and_bound_follows_places_that_give_nothing_verified(zdown):
    # The window's places all lie > 9 m from the pose: their small windows (12 m) miss it, and the
    # branch and bound over the whole window still finds it.
    m, loc = zdown
    T_true = xyzrpy_to_T(-10.0, -5.0, -1.8, 0.0, 0.0, -0.7)
    far = _without_places_near(loc, (-10.0, -5.0), 9.0)
    res = far.localize(scan_from(m, T_true, seed=5), gravity_body(T_true), hint_xy=(-8.0, -6.0))
    assert res.stats["places_in_window"] > 0
    assert res.stats["hint_search"] == "places, then branch and bound"
    assert res.verified and pose_error(res.T_map_body, T_true)[0] < 0.1


def test_a_hint_windows_subset_keeps_which_places_are_open():
    """The hint's window cuts the index; an open place (described in the open band) must stay open
    in the cut, or a scan would be matched against it in the wrong band."""
    from blockloc.global_init.place_descriptors import PlaceIndexParams
    from blockloc.global_init.place_index import PlaceIndex

    P = 6
    idx = PlaceIndex(PlaceIndexParams(), np.array([0.0, 0.0, -9.81]), np.zeros((P, 2), np.float32),
                     np.zeros(P, np.uint8), np.zeros((P, 2, 1), np.uint64), np.zeros((P, 2, 1), np.uint64),
                     band=np.array([0, 1, 0, 1, 1, 0], np.uint8))
    assert idx.subset(np.array([1, 2, 4])).band.tolist() == [1, 0, 1]
    assert idx.subset(idx.band == 1).band.tolist() == [1, 1, 1]
