"""A rival that NDT on the scan's every point brings back to the best's own optimum is no ambiguity
(``verify.one_optimum``, ``InitParams.resolve_on_every_point``): the decision after the search went on."""

import math
from dataclasses import replace

import numpy as np
import pytest

from blockloc.geometry import xyzrpy_to_T
from blockloc.global_init import verify
from blockloc.global_init.refine import RefineResult
from blockloc.global_init.relocalize import GlobalLocalizer, InitParams, pose_error
from blockloc.global_init.verify import InitCandidate, decide, nearby_rival, one_optimum

from .synthetic import Z_DOWN, gravity_body, scan_from, world_up
from .test_climb import setup as climb_setup  # noqa: F401  (the same world, pose, scan and target)


@pytest.fixture(scope="module")
def setup(climb_setup):
    """test_climb's, with the scan's every point (body frame, within max_range_m)."""
    loc, T_true, scan, scan_ndt, refiner = climb_setup
    scan_body = scan_from(world_up(seed=3) @ Z_DOWN.T, T_true)
    dense = scan_body[np.linalg.norm(scan_body, axis=1) <= loc.params.max_range_m]
    return loc, T_true, scan_body, dense, scan_ndt, refiner


def _best(refiner, scan_ndt, T_true, coverage=0.97):
    r = refiner.align(scan_ndt, T_true)
    best = InitCandidate(r.T_map_body, 1.0, r.fitness, True, True, T_true, r.ndt_score, 0.95, coverage=coverage,
                         see_through=0.0, refiner=refiner)
    best.probes = []  # probed already: no nearby rival (the far rule alone)
    return best


def _rival(best, T, refiner):
    """A verified candidate at ``T`` as the campus street's were: fitting nearly as well, scoring a
    little lower per point (its numbers made up: the thinned scan's optimum there)."""
    c = InitCandidate(T, 1.0, best.fitness - 0.01, True, True, T, best.ndt_score - 0.03, 0.9, coverage=1.0,
                      see_through=0.0, refiner=refiner)
    c.probes = []
    return c


@pytest.fixture
def untold(monkeypatch):
    """The inlier test on the thinned scan cannot tell the two apart (as along the campus street:
    ``better_fit`` z 1.8-2.4 < 2.5)."""
    monkeypatch.setattr(verify, "better_fit", lambda *a, **k: 0.0)


def test_a_rival_that_is_the_best_optimum_on_every_point_is_no_ambiguity(setup, untold):
    """Campus, nominal-mounting map ``--rng 7`` frame 17933 (best 0.27 m from the truth, a verified
    optimum 0.90 m along the street) and defaults' map frame 14583 (0.06 m; 0.68 m): ambiguous on
    the thinned scan; on every point NDT from the rival came back to the best's optimum."""
    loc, T_true, scan_body, dense, scan_ndt, refiner = setup
    p = loc.params
    best = _best(refiner, scan_ndt, T_true)
    T_near = best.T_map_body.copy()
    T_near[:2, 3] += (0.6, -0.5)  # 0.78 m off: NDT on every point slides back
    assert one_optimum(dense, best, _rival(best, T_near, refiner), p)
    res = decide([best, _rival(best, T_near, refiner)], {}, 0.0, p, scan_ndt, drop_targets=False)
    assert res.ambiguous and not res.verified  # the thinned scan alone: as before
    res = decide([best, _rival(best, T_near, refiner)], {}, 0.0, p, scan_ndt, drop_targets=False, dense_points=dense)
    assert res.verified and not res.ambiguous and res.T_map_body is best.T_map_body
    dt, dr = pose_error(res.T_map_body, T_true)
    assert dt < 0.1 and dr < 0.5

    # a rival at another place stays one; so does any rival of a best whose coverage was not judged
    T_far = xyzrpy_to_T(-25.0, 20.0, -(1.9 - 0.02 * 25.0), 0.03, -0.02, 0.7)
    res = decide([best, _rival(best, T_far, refiner)], {}, 0.0, p, scan_ndt, drop_targets=False, dense_points=dense)
    assert res.ambiguous and not res.verified
    unjudged = _best(refiner, scan_ndt, T_true, coverage=math.nan)
    assert not one_optimum(dense, unjudged, _rival(unjudged, T_near, refiner), p)
    res = decide([unjudged, _rival(unjudged, T_near, refiner)], {}, 0.0, p, scan_ndt, drop_targets=False,
                 dense_points=dense)
    assert res.ambiguous and not res.verified


def test_a_nearby_rival_that_is_the_best_optimum_is_passed_over(setup, untold):
    loc, T_true, scan_body, dense, scan_ndt, refiner = setup
    p = loc.params
    best = _best(refiner, scan_ndt, T_true)
    T_near = best.T_map_body.copy()
    T_near[:2, 3] += (0.6, -0.5)
    # the restart that stopped 0.78 m away (made so: the thinned scan's flat street)
    best.probes = [(T_near, RefineResult(T_near, best.fitness, True, 5, best.ndt_score - 0.03))]
    assert nearby_rival(best, scan_ndt, None, p) is not None
    assert nearby_rival(best, scan_ndt, None, p, dismiss=lambda r: one_optimum(dense, best, r, p)) is None
    assert decide([best], {}, 0.0, p, scan_ndt, drop_targets=False).ambiguous
    res = decide([best], {}, 0.0, p, scan_ndt, drop_targets=False, dense_points=dense)
    assert res.verified and not res.ambiguous


def test_the_decision_after_the_search_went_on_takes_every_point(setup, untold, monkeypatch):
    """The first stage's best and a rival along the street; the stages after it find nothing new. With
    ``resolve_on_every_point`` the decision made again over them takes every point and verifies
    the best; without it the result stays ambiguous, as before."""
    loc, T_true, scan_body, dense, scan_ndt, refiner = setup
    for resolve in (True, False):
        stages = []

        def places(self, scan, scan_ndt, cells, index, theta_c, yaw_win, stats, deadline=math.inf,
                   candidates=None, flip_open=False, first_stage=0, done=None, stages=stages):
            stages.append(first_stage)
            if first_stage == 0:
                best = _best(refiner, scan_ndt, T_true)
                T_near = best.T_map_body.copy()
                T_near[:2, 3] += (0.6, -0.5)
                return [best, _rival(best, T_near, refiner)], dict(stats, place_stage=1)
            return [], dict(stats, place_stage=3)

        monkeypatch.setattr(GlobalLocalizer, "_relocalize_places", places)
        nohint = GlobalLocalizer(loc.map, InitParams(resolve_on_every_point=resolve, max_search_s=0.0))
        res = nohint.localize(scan_body, gravity_body(T_true))
        assert stages == [0, 1]
        if resolve:
            assert res.verified and not res.ambiguous
            dt, dr = pose_error(res.T_map_body, T_true)
            assert dt < 0.1 and dr < 0.5, (dt, dr)
        else:
            assert res.ambiguous and not res.verified
        assert all(c.refiner is None for c in res.candidates)


def test_the_hinted_decision_after_the_window_search_takes_every_point(setup, untold, monkeypatch):
    """A hint constrains the no-hint search; its decision after the search went on is the same.
    Campus, nominal-mounting map, hinted frames 17933 and 17958 (``--rng 7``), 20361 and 29071
    (``--rng 13``): the best 0.07-0.31 m from the truth, a verified optimum 0.9-1.4 m along the
    street, the window's branch and bound found nothing better, and the result stayed unverified
    because that decision did not take the scan's every point as the no-hint one does. With
    ``resolve_on_every_point`` it does; without it the result stays ambiguous, as before."""
    loc, T_true, scan_body, dense, scan_ndt, refiner = setup
    for resolve in (True, False):
        regions = []

        def places(self, scan, scan_ndt, cells, index, theta_c, yaw_win, stats, deadline=math.inf,
                   candidates=None, flip_open=False, first_stage=0, done=None):
            best = _best(refiner, scan_ndt, T_true)
            T_near = best.T_map_body.copy()
            T_near[:2, 3] += (0.6, -0.5)
            return [best, _rival(best, T_near, refiner)], dict(stats, place_stage=1)

        def region(self, scan, scan_ndt, center, window_m, theta_c, yaw_win, cells=None, regions=regions):
            regions.append(window_m)
            return [], {}  # the window holds nothing better

        monkeypatch.setattr(GlobalLocalizer, "_relocalize_places", places)
        monkeypatch.setattr(GlobalLocalizer, "_search_region", region)
        hinted = GlobalLocalizer(loc.map, InitParams(resolve_on_every_point=resolve))
        res = hinted.localize(scan_body, gravity_body(T_true), hint_xy=T_true[:2, 3] + (3.0, -2.0), window_m=30.0)
        assert regions == [30.0] and res.stats["hint_search"] == "places, then branch and bound"
        if resolve:
            assert res.verified and not res.ambiguous, res.stats
            dt, dr = pose_error(res.T_map_body, T_true)
            assert dt < 0.1 and dr < 0.5, (dt, dr)
        else:
            assert res.ambiguous and not res.verified
        assert all(c.refiner is None for c in res.candidates)


def test_the_best_every_point_run_that_stops_unconverged_is_settled_once_more(setup, untold, monkeypatch):
    """Nominal map, frames 20361 and 14599: the rival came back to within 0.01 / 0.08 m of the best's
    every-point optimum, but the best's own run had stopped at its iteration limit (still sliding
    along the flat street), so the rival counted. That run is settled once more, as the rival's is."""
    loc, T_true, scan_body, dense, scan_ndt, refiner = setup
    p = loc.params
    best = _best(refiner, scan_ndt, T_true)
    T_near = best.T_map_body.copy()
    T_near[:2, 3] += (0.6, -0.5)
    real = type(refiner).align_settled
    calls = []

    def first_stops_short(self, points, T_start, *a, **k):
        r = real(self, points, T_start, *a, **k)
        calls.append(len(points))
        if len(calls) == 1:  # the best's run: stopped 5 cm short of its optimum, unconverged
            T = r.T_map_body.copy()
            T[:2, 3] += (0.04, -0.03)
            return RefineResult(T, r.fitness, False, 60, r.ndt_score)
        return r

    monkeypatch.setattr(type(refiner), "align_settled", first_stops_short)
    assert one_optimum(dense, best, _rival(best, T_near, refiner), p)
    assert len(calls) == 3  # the best's run twice, the rival's once


def test_where_every_point_leaves_two_optima_the_whole_scan_may_make_them_one(setup, untold):
    """Defaults' map ``--rng 7`` frame 17992: a best 0.12 m and a rival 0.63 m from the truth, both
    verified, stayed apart on every point within 60 m against the map within 50 m; the whole scan
    against the map 65 m around brought both to 0.04-0.05 m. Here the rival's own target is made so
    that NDT cannot bring it back (a target holding none of the map), and ``align_whole`` is
    NDT on the scan's every point against the whole world."""
    from blockloc.global_init.refine import Refiner
    from blockloc.registration.engines import make_engine

    loc, T_true, scan_body, dense, scan_ndt, refiner = setup
    p = loc.params
    best = _best(refiner, scan_ndt, T_true)
    T_near = best.T_map_body.copy()
    T_near[:2, 3] += (0.6, -0.5)
    from blockloc.global_init.refine import WholeScan

    elsewhere = Refiner(make_engine("ndt"), world_up(seed=99) @ Z_DOWN.T)  # the dense runs stay apart
    calls = []

    def refiner_over(xy, d):
        calls.append(xy)
        return refiner

    whole = WholeScan(scan_body, refiner_over, np.eye(3), 65.0, reuse_m=0.0)  # a target asked for each pose
    assert not one_optimum(dense, best, _rival(best, T_near, elsewhere), p)
    assert one_optimum(dense, best, _rival(best, T_near, elsewhere), p, whole=whole)
    assert len(calls) == 2  # from the best, from the rival
    res = decide([best, _rival(best, T_near, elsewhere)], {}, 0.0, p, scan_ndt, drop_targets=False,
                 dense_points=dense, whole=whole)
    assert res.verified and not res.ambiguous
    # a rival at another place stays one; a best whose coverage was not judged keeps every rival
    T_far = xyzrpy_to_T(-25.0, 20.0, -(1.9 - 0.02 * 25.0), 0.03, -0.02, 0.7)
    assert not one_optimum(dense, best, _rival(best, T_far, elsewhere), p, whole=whole)
    unjudged = _best(refiner, scan_ndt, T_true, coverage=math.nan)
    calls.clear()
    assert not one_optimum(dense, unjudged, _rival(unjudged, T_near, elsewhere), p, whole=whole)
    assert not calls


def _whole(refiner, scan_body):
    from blockloc.global_init.refine import WholeScan

    return WholeScan(scan_body, lambda xy, d: refiner, np.eye(3), 65.0)


def test_the_whole_scan_decides_a_far_ambiguity_for_the_place_that_explains_it(setup):
    """Defaults' map ``--rng 41``, frame 47154: the true place verified, outranked on the thinned scan
    by a wrong place 158 m off; on the whole scan the truth fits 0.95 against 0.75. Here the wrong
    place is made to score higher per point on the thinned scan."""
    from blockloc.global_init.verify import whole_scan_decides

    loc, T_true, scan_body, dense, scan_ndt, refiner = setup
    p = loc.params
    truth = _best(refiner, scan_ndt, T_true)
    T_far = xyzrpy_to_T(-25.0, 20.0, -(1.9 - 0.02 * 25.0), 0.03, -0.02, 0.7)
    wrong = _rival(truth, T_far, refiner)
    wrong.ndt_score = truth.ndt_score + 0.2  # ranked first on the thinned scan
    whole = _whole(refiner, scan_body)
    res = decide([wrong, truth], {}, 0.0, p, scan_ndt, drop_targets=False, dense_points=dense)
    assert res.ambiguous and not res.verified  # without the whole scan: as before
    res = decide([wrong, truth], {}, 0.0, p, scan_ndt, drop_targets=False, dense_points=dense, whole=whole)
    assert res.verified and not res.ambiguous and res.candidates[0] is truth and res.stats["whole_scan_decided"]
    assert pose_error(res.T_map_body, T_true)[0] < 0.1
    # only after the search went on (the decision given every point), as one_optimum
    assert decide([wrong, truth], {}, 0.0, p, scan_ndt, drop_targets=False, whole=whole).ambiguous
    # the winner must have been verified by the search
    truth.verified = False
    assert whole_scan_decides([wrong, truth], whole, p) is None
    truth.verified = True
    # more candidates than judged: still ambiguous
    assert whole_scan_decides([wrong, truth], whole, replace(p, whole_scan_max_candidates=1)) is None


def test_the_whole_scan_never_decides_among_wrong_places(setup):
    """Every wrong place of the campus's ambiguous frames fit the whole scan at 0.84 or less: none
    reaches the strong-fit floor, so an ambiguity of wrong places stays one."""
    from blockloc.global_init.verify import whole_scan_decides

    loc, T_true, scan_body, dense, scan_ndt, refiner = setup
    p = loc.params
    truth = _best(refiner, scan_ndt, T_true)
    far = [xyzrpy_to_T(-25.0, 20.0, -(1.9 - 0.02 * 25.0), 0.03, -0.02, 0.7),
           xyzrpy_to_T(30.0, -28.0, -(1.9 + 0.02 * 30.0), 0.0, 0.02, -1.2)]
    wrongs = [_rival(truth, T, refiner) for T in far]
    assert whole_scan_decides(wrongs, _whole(refiner, scan_body), p) is None
    res = decide(wrongs, {}, 0.0, p, scan_ndt, drop_targets=False, dense_points=dense,
                 whole=_whole(refiner, scan_body))
    assert not res.verified
