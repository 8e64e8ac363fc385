"""The final decision's climb (``GlobalLocalizer._climb``) and the later stages' leaves by 2D score."""

import math

import numpy as np
import pytest

from blockloc.geometry import xyzrpy_to_T
from blockloc.global_init.bnb import Window
from blockloc.global_init.refine import Refiner
from blockloc.global_init.relocalize import GlobalLocalizer, InitParams, pose_error
from blockloc.global_init.verify import InitCandidate, nearby_rival
from blockloc.jit import Deadline

from .synthetic import GRAVITY_Z_DOWN, Z_DOWN, gravity_body, scan_from, world_up


@pytest.fixture(scope="module")
def setup():
    world = world_up(seed=3) @ Z_DOWN.T
    loc = GlobalLocalizer.for_points(world, GRAVITY_Z_DOWN, InitParams())
    T_true = xyzrpy_to_T(6.0, 4.0, -(1.9 + 0.02 * 6.0), 0.03, -0.02, 2.4)
    scan_body = scan_from(world, T_true)
    scan, scan_ndt = loc.prepare_scan(scan_body, gravity_body(T_true))
    refiner = Refiner(loc.engine, world, loc.map.R_L_map, 1.0, 0.25)
    return loc, T_true, scan, scan_ndt, refiner


def _stalled(refiner, scan_ndt, T):
    """A candidate where NDT stopped short (as along a street): verified there, not an optimum."""
    score = refiner.engine.evaluate(refiner._target, scan_ndt, T).score / len(scan_ndt)
    return InitCandidate(T, 1.0, 0.9, True, True, T, score, 0.9, refiner=refiner)


def test_a_stalled_candidate_climbs_to_the_optimum_and_stays_a_candidate(setup):
    loc, T_true, scan, scan_ndt, refiner = setup
    T_off = T_true.copy()
    T_off[:2, 3] += (1.2, -0.6)
    stalled = _stalled(refiner, scan_ndt, T_off)
    out = loc._climb([stalled], scan, scan_ndt, None)
    assert out[0] is stalled and len(out) == 2  # nothing removed, the optimum added
    up = out[1]
    assert up.verified and up.ndt_score >= stalled.ndt_score + loc.params.climb_min_gain
    dt, dr = pose_error(up.T_map_body, T_true)
    assert dt < 0.1 and dr < 0.5, (dt, dr)
    # the restarts are kept on the candidate; the climbed one was probed in the next round and
    # went nowhere better, so the rival check reuses its probes instead of aligning again
    assert stalled.probes is not None and len(stalled.probes) == 4 * len(loc.params.probe_m)
    assert up.probes is not None


def test_an_optimum_does_not_climb_and_the_rival_check_reuses_its_probes(setup):
    loc, T_true, scan, scan_ndt, refiner = setup
    r = refiner.align(scan_ndt, T_true)
    best = InitCandidate(r.T_map_body, 1.0, r.fitness, True, True, T_true, r.ndt_score, 0.95, refiner=refiner)
    out = loc._climb([best], scan, scan_ndt, None)
    assert out == [best] and best.probes is not None

    calls = []

    class Counting:
        def align(self, *a):
            calls.append(1)
            return refiner.align(*a)

    best.refiner = Counting()
    nearby_rival(best, scan_ndt, None, loc.params)
    assert calls == []  # the probes of the climb were reused
    # without the climb, climb_rounds 0: the decision is as before (no candidate added, no climb time)
    plain = GlobalLocalizer(loc.map, InitParams(climb_rounds=0))
    res = plain._decide([_stalled(refiner, scan_ndt, T_true)], {}, 0.0, scan_ndt, scan=scan)
    assert "climb_s" not in res.stats and len(res.candidates) >= 1


def test_an_unconverged_candidate_is_judged_at_the_optimum_it_settles_at(setup):
    """Campus, defaults' map, frame 17933: the candidate 0.15 m from the truth fitted best of all but
    NDT left it unconverged, so it was never verified, and a wrong place 400 m off won (made
    ambiguous by it). A final decision aligns such a candidate once more from where it stopped and
    judges the optimum it settles at; one still sliding stays as it was (a rival). Without
    ``settle_unconverged``, the result stays ambiguous, as before."""
    from blockloc.global_init.verify import Thresholds, structure_fit

    loc, T_true, scan, scan_ndt, refiner = setup
    T_wrong = xyzrpy_to_T(-25.0, 20.0, -(1.9 - 0.02 * 25.0), 0.03, -0.02, 0.7)
    T_near = refiner.align(scan_ndt, T_true).T_map_body.copy()
    T_near[0, 3] += 0.15
    loc._verified(refiner.align(scan_ndt, T_true), refiner, 0.9, T_true, scan, None, Thresholds.of(loc.params))
    structures = loc._structure_body

    class Sliding:  # a refiner whose every alignment runs out of iterations
        def align_settled(self, scan_ndt, T):
            r = refiner.align(scan_ndt, T)
            r.converged = False
            return r

        def __getattr__(self, name):
            return getattr(refiner, name)

    def candidates(ref):
        # the wrong place verified (made so, as its scan fit is made up); the one near the truth
        # with the measurements NDT gave there, unconverged
        wrong = InitCandidate(T_wrong, 0.9, 0.8, True, True, T_wrong, 1.1, 0.65, refiner=ref)
        wrong.probes = []
        score = refiner.engine.evaluate(refiner._target, scan_ndt, T_near).score / len(scan_ndt)
        near = InitCandidate(T_near, 0.9, refiner.inlier_ratio(scan_ndt, T_near), False, False, T_near, score,
                             structure_fit(refiner, structures, T_near, loc.params.min_structure_fitness),
                             refiner=ref)
        assert near.fitness >= loc.params.min_fitness and near.structure_fitness >= loc.params.min_structure_fitness
        return [wrong, near]

    for settle, ref in ((True, refiner), (False, refiner), (True, Sliding())):
        nohint = GlobalLocalizer(loc.map, InitParams(settle_unconverged=settle, climb_rounds=0))
        cands = candidates(ref)
        res = nohint._decide(cands, {}, 0.0, scan_ndt, scan=scan)
        if settle and ref is refiner:
            assert res.verified and not res.ambiguous and res.stats["settled"] == 1
            dt, dr = pose_error(res.T_map_body, T_true)
            assert dt < 0.1 and dr < 0.5, (dt, dr)
        else:
            assert res.ambiguous and not res.verified
            assert np.allclose(res.T_map_body, T_wrong)
            assert any(c is cands[1] for c in res.candidates)  # the sliding one kept as it was


def test_a_later_stage_also_takes_the_best_leaves_by_2d_score(setup):
    loc, T_true, scan, _, _ = setup
    xy = (loc.map.R_L_map @ T_true[:3, 3])[:2]
    theta = loc._theta_from_yaw(math.atan2(T_true[1, 0], T_true[0, 0]), scan)
    wrong = Window(xy + np.array([-30.0, 25.0]), 12.0, theta + 1.0, math.radians(16.0))
    true = Window(xy, 12.0, theta, math.radians(16.0))
    # (every leaf kept, however poor: ambiguity_score_ratio 0)
    loc1 = GlobalLocalizer(loc.map, InitParams(place_top_k=1, ambiguity_score_ratio=0.0))
    ranked, _ = loc1._search_windows(scan, [wrong, true])
    assert len(ranked) == 1 and ranked[0].window == 0  # the first place's leaf only
    more, _ = loc1._search_windows(scan, [wrong, true], by_score=1)
    assert [c.window for c in more] == [0, 1]
    assert np.hypot(more[1].x - xy[0], more[1].y - xy[1]) < 1.0 and more[1].score > more[0].score


def test_the_third_stage_searches_the_first_places_at_every_yaw(setup, monkeypatch):
    """A yaw guess can be far off (small world seed 2, frame 847: 40 deg, the place ranked first):
    after the second stage (more places at their guesses: a true place ranked low is the commoner
    miss), the first ``place_all_yaw_candidates`` places at every yaw."""
    loc, T_true, scan, _, _ = setup
    params = InitParams(min_fitness=0.999, place_candidates=(3, 6), place_all_yaw_candidates=2,
                        whole_map_fallback=False, max_search_s=0.0)
    nohint = GlobalLocalizer(loc.map, params)
    seen = []
    real = GlobalLocalizer._search_windows

    def record(self, scan, windows, by_score=0, top_k=None):
        seen.append([(tuple(np.round(w.center, 3)), w.yaw_window) for w in windows])
        return real(self, scan, windows, by_score, top_k)

    monkeypatch.setattr(GlobalLocalizer, "_search_windows", record)
    res = nohint.localize(scan_from(world_up(seed=3) @ Z_DOWN.T, T_true), gravity_body(T_true))
    assert not res.verified and len(seen) == 3
    guess = math.radians(params.place_yaw_window_deg)
    assert [len(s) for s in seen] == [3, 3, 2]  # 3 places, the next 3, then the first 2 at every yaw
    assert all(y == guess for _, y in seen[0] + seen[1]) and all(y == 2 * math.pi for _, y in seen[2])
    assert [c for c, _ in seen[2]] == [c for c, _ in seen[0][:2]]
    assert not set(c for c, _ in seen[1]) & set(c for c, _ in seen[0])


def test_the_stages_after_the_first_refine_place_later_top_k_leaves_each_way(setup, monkeypatch):
    """Campus, defaults' map, --rng 13, frames 16591 and 24995: the true places ranked 13th and 34th
    (open places, whose windows come twice), their leaves never among the 6 refined a stage; a wrong
    place verified instead (ambiguous). After the first stage, ``place_later_top_k`` leaves of the
    best places and as many by 2D score; the first stage as before."""
    loc, T_true, scan, _, _ = setup
    real = GlobalLocalizer._search_windows
    params = InitParams(min_fitness=0.999, place_candidates=(3, 6), place_all_yaw_candidates=2,
                        whole_map_fallback=False, max_search_s=0.0, place_top_k=2, place_later_top_k=5)
    nohint = GlobalLocalizer(loc.map, params)
    calls = []

    def record(self, scan, windows, by_score=0, top_k=None):
        out = real(self, scan, windows, by_score, top_k)
        calls.append((top_k, by_score, len(windows), len(out[0])))
        return out

    monkeypatch.setattr(GlobalLocalizer, "_search_windows", record)
    nohint.localize(scan_from(world_up(seed=3) @ Z_DOWN.T, T_true), gravity_body(T_true))
    assert [(k, b) for k, b, _, _ in calls] == [(2, 0), (5, 5), (5, 5)]
    assert calls[0][3] <= 2
    # the budget itself: top_k leaves of the best windows first, in the windows' order
    xy = (loc.map.R_L_map @ T_true[:3, 3])[:2]
    theta = loc._theta_from_yaw(math.atan2(T_true[1, 0], T_true[0, 0]), scan)
    ws = [Window(xy + np.array([dx, 25.0]), 12.0, theta + 1.0, math.radians(16.0)) for dx in (-30.0, 0.0)]
    ws.append(Window(xy, 12.0, theta, math.radians(16.0)))
    one = GlobalLocalizer(loc.map, InitParams(place_top_k=1, ambiguity_score_ratio=0.0))
    assert [c.window for c in one._search_windows(scan, ws)[0]] == [0]
    assert [c.window for c in one._search_windows(scan, ws, top_k=3)[0]] == [0, 1, 2]


def test_open_places_are_also_searched_at_their_yaw_guess_reversed(setup, monkeypatch):
    """An open street's low band looks alike both ways (campus, defaults' map, frame 27961: the true
    places' yaw guesses 180 deg off): with no hint, an open place's window comes twice, at its yaw
    guess and reversed; without ``place_flip_open`` once. Every place is made open here."""
    loc, T_true, scan, _, _ = setup
    real = GlobalLocalizer._search_windows
    seen = {}
    for flip in (False, True):
        params = InitParams(min_fitness=0.999, place_candidates=(3,), place_all_yaw_candidates=0,
                            whole_map_fallback=False, max_search_s=0.0, place_flip_open=flip)
        nohint = GlobalLocalizer(loc.map, params)
        index = nohint.place_index
        monkeypatch.setattr(index, "band", np.ones_like(np.asarray(index.band)))
        stages = []

        def record(self, scan, windows, by_score=0, top_k=None, stages=stages):
            stages.append(list(windows))
            return real(self, scan, windows, by_score, top_k)

        monkeypatch.setattr(GlobalLocalizer, "_search_windows", record)
        nohint.localize(scan_from(world_up(seed=3) @ Z_DOWN.T, T_true), gravity_body(T_true))
        seen[flip] = stages[0]
    once, twice = seen[False], seen[True]
    assert len(once) == 3 and len(twice) == 6
    for w, (a, b) in zip(once, zip(twice[::2], twice[1::2])):
        assert np.allclose(a.center, w.center) and np.allclose(b.center, w.center)
        assert a.theta == w.theta and b.theta == pytest.approx(w.theta + math.pi)
        assert a.yaw_window == b.yaw_window == w.yaw_window


def test_a_resumed_place_search_runs_only_the_stages_after_those_done(setup, monkeypatch):
    loc, T_true, scan, _, _ = setup
    params = InitParams(min_fitness=0.999, place_candidates=(3, 6), place_all_yaw_candidates=2,
                        whole_map_fallback=False, max_search_s=0.0)
    nohint = GlobalLocalizer(loc.map, params)
    real = GlobalLocalizer._search_windows
    seen = []

    def record(self, scan, windows, by_score=0, top_k=None):
        seen.append([(tuple(np.round(w.center, 3)), w.yaw_window) for w in windows])
        return real(self, scan, windows, by_score, top_k)

    monkeypatch.setattr(GlobalLocalizer, "_search_windows", record)
    scan_body = scan_from(world_up(seed=3) @ Z_DOWN.T, T_true)
    sc, scan_ndt = nohint.prepare_scan(scan_body, gravity_body(T_true))
    cells = nohint._scan_cells(scan_body, gravity_body(T_true))
    done = []
    # stopped after the first stage (its deadline passed)
    _, stats = nohint._relocalize_places(sc, scan_ndt, cells, nohint.place_index, 0.0, 2 * math.pi, {},
                                         deadline=Deadline(0.0), done=done)
    assert stats["place_stage"] == 1 and stats["timed_out"] and len(seen) == 1 and len(done) > 0
    n_done = len(done)
    _, stats = nohint._relocalize_places(sc, scan_ndt, cells, nohint.place_index, 0.0, 2 * math.pi, {},
                                         first_stage=1, done=done)
    # places 4 to 6 (the first 3 were searched), then the all-yaw stage over the first 2 places
    assert [len(s) for s in seen] == [3, 3, 2] and stats["place_stage"] == 3
    assert not set(c for c, _ in seen[1]) & set(c for c, _ in seen[0])
    assert [c for c, _ in seen[2]] == [c for c, _ in seen[0][:2]]
    assert len(done) >= n_done
    # past the last stage: nothing searched, not even the index queried
    monkeypatch.setattr(nohint.place_index, "query_cells", None)
    more, stats = nohint._relocalize_places(sc, scan_ndt, cells, nohint.place_index, 0.0, 2 * math.pi, {},
                                            first_stage=3, done=done)
    assert more == [] and stats["place_stage"] == 3 and len(seen) == 3


def test_a_verified_best_the_final_decision_doubts_does_not_end_the_place_search(setup, monkeypatch):
    """Campus, defaults' map, frames 17786 and 25289: a wrong place 507 m off passed verification at
    the first stage and ended the place search; the final decision found an NDT optimum next to it
    fitting about as well (ambiguous, not verified), and the true place was never searched. The
    stages go on after such a doubt; the decision judges everything found."""
    from blockloc.global_init import verify

    loc, T_true, scan, scan_ndt, refiner = setup
    T_wrong = xyzrpy_to_T(-25.0, 20.0, -(1.9 - 0.02 * 25.0), 0.03, -0.02, 0.7)
    real_rival = verify.nearby_rival

    def rival_of_the_wrong_place(best, scan_ndt, structures, p, dismiss=None):
        # the wrong place's scan fit is made up here, so is its rival (as the campus frames had)
        if np.linalg.norm(best.T_map_body[:3, 3] - T_wrong[:3, 3]) < 1e-6:
            T = best.T_map_body.copy()
            T[0, 3] += 0.85
            return InitCandidate(T, 0.0, best.fitness, True, False, T, best.ndt_score, best.structure_fitness,
                                 refiner=best.refiner)
        return real_rival(best, scan_ndt, structures, p, dismiss)

    monkeypatch.setattr(verify, "nearby_rival", rival_of_the_wrong_place)
    # (search on, the first stage's wrong places: one with a rival next to it; two far apart that
    # fit alike, as the nominal map's frame 20179 had four along a street)
    T_wrong2 = T_wrong.copy()
    T_wrong2[1, 3] += 12.0
    for search_on, wrong_poses in ((True, [T_wrong]), (False, [T_wrong]), (True, [T_wrong, T_wrong2])):
        stages = []

        def places(self, scan, scan_ndt, cells, index, theta_c, yaw_win, stats, deadline=math.inf,
                   candidates=None, flip_open=False, first_stage=0, done=None, stages=stages,
                   wrong_poses=wrong_poses):
            stages.append(first_stage)
            if first_stage == 0:  # the wrong places, verified (made so), probed and climbed already
                wrong = [InitCandidate(T, 0.9, 0.8, True, True, T, 1.1, 0.65, refiner=refiner) for T in wrong_poses]
                for c in wrong:
                    c.probes = []
                return wrong, dict(stats, place_stage=1)
            r = refiner.align(scan_ndt, T_true)
            return [self._verified(r, refiner, 0.95, T_true, scan, None, verify.Thresholds.of(self.params))], \
                dict(stats, place_stage=3)

        monkeypatch.setattr(GlobalLocalizer, "_relocalize_places", places)
        nohint = GlobalLocalizer(loc.map, InitParams(search_on_doubt=search_on, max_search_s=0.0))
        res = nohint.localize(scan_from(world_up(seed=3) @ Z_DOWN.T, T_true), gravity_body(T_true))
        if search_on:
            assert stages == [0, 1] and res.verified and not res.ambiguous
            dt, dr = pose_error(res.T_map_body, T_true)
            assert dt < 0.1 and dr < 0.5, (dt, dr)
            assert res.stats["searched_on"] == 1 and res.stats["place_stage"] == 3
            # the first best stayed a candidate (a rival of the new best, too poor to be one)
            assert any(np.allclose(c.T_map_body, T_wrong) for c in res.candidates)
            assert all(c.refiner is None for c in res.candidates)
        else:
            assert stages == [0] and res.ambiguous and not res.verified


def test_the_search_goes_on_stage_after_stage_while_the_result_stays_ambiguous(setup, monkeypatch):
    """Campus, defaults' map ``--rng 7``, frame 16517 (and nominal map, frame 25037): the first
    stage verified a wrong place; the next stage, resumed after that doubt, verified another wrong
    place far from it and ended the call (a stage with a verified candidate ends it), leaving the
    result ambiguous; the true place (29th) was in the stage after. Each resumed stage is decided
    over with everything found before; while that stays ambiguous the stages go on."""
    loc, T_true, scan, scan_ndt, refiner = setup
    T_a = xyzrpy_to_T(9.0, 4.0, -(1.9 + 0.02 * 9.0), 0.03, -0.02, 2.4)  # two wrong places 6 m apart,
    T_b = xyzrpy_to_T(3.0, 4.0, -(1.9 + 0.02 * 3.0), 0.03, -0.02, 2.4)  # verified (made so) alike
    stages = []

    def places(self, scan, scan_ndt, cells, index, theta_c, yaw_win, stats, deadline=math.inf,
               candidates=None, flip_open=False, first_stage=0, done=None):
        from blockloc.global_init import verify

        stages.append(first_stage)
        if first_stage < 2:  # one wrong place a stage
            c = InitCandidate((T_a, T_b)[first_stage], 0.9, 0.8, True, True, (T_a, T_b)[first_stage], 1.1, 0.65,
                              refiner=refiner)
            c.probes = []
            return [c], dict(stats, place_stage=first_stage + 1)
        if first_stage == 2:
            r = refiner.align(scan_ndt, T_true)
            return [self._verified(r, refiner, 0.95, T_true, scan, None, verify.Thresholds.of(self.params))], \
                dict(stats, place_stage=3)
        return [], dict(stats, place_stage=first_stage)

    monkeypatch.setattr(GlobalLocalizer, "_relocalize_places", places)
    nohint = GlobalLocalizer(loc.map, InitParams(max_search_s=0.0))
    res = nohint.localize(scan_from(world_up(seed=3) @ Z_DOWN.T, T_true), gravity_body(T_true))
    assert stages == [0, 1, 2], stages
    assert res.verified and not res.ambiguous, res.stats
    dt, dr = pose_error(res.T_map_body, T_true)
    assert dt < 0.1 and dr < 0.5, (dt, dr)
    assert res.stats["searched_on"] == 2 and res.stats["place_stage"] == 3
    assert all(c.refiner is None for c in res.candidates)


def test_a_hinted_search_whose_places_leave_doubt_goes_on_with_the_windows_branch_and_bound(setup, monkeypatch):
    """Campus, nominal-mounting map, hinted frames 14583 and 20179: the places in the hint's window
    gave verified candidates along a street that left the result ambiguous, and the window's branch
    and bound never ran. With ``search_on_doubt`` it runs, and the decision judges everything found;
    without it the result stays ambiguous, as before."""
    loc, T_true, scan, scan_ndt, refiner = setup
    T_a = xyzrpy_to_T(9.0, 4.0, -(1.9 + 0.02 * 9.0), 0.03, -0.02, 2.4)  # two places 6 m apart, both
    T_b = xyzrpy_to_T(3.0, 4.0, -(1.9 + 0.02 * 3.0), 0.03, -0.02, 2.4)  # verified (made so) alike
    for search_on in (True, False):
        regions = []

        def places(self, scan, scan_ndt, cells, index, theta_c, yaw_win, stats, deadline=math.inf,
                   candidates=None, flip_open=False, first_stage=0, done=None):
            wrong = [InitCandidate(T, 0.9, 0.8, True, True, T, 1.1, 0.65, refiner=refiner) for T in (T_a, T_b)]
            for c in wrong:
                c.probes = []
            return wrong, dict(stats, place_stage=1)

        def region(self, scan, scan_ndt, center, window_m, theta_c, yaw_win, cells=None, regions=regions):
            from blockloc.global_init import verify

            regions.append((tuple(np.round(center, 3)), window_m))
            r = refiner.align(scan_ndt, T_true)
            return [self._verified(r, refiner, 0.95, T_true, scan, None, verify.Thresholds.of(self.params))], {}

        monkeypatch.setattr(GlobalLocalizer, "_relocalize_places", places)
        monkeypatch.setattr(GlobalLocalizer, "_search_region", region)
        hinted = GlobalLocalizer(loc.map, InitParams(search_on_doubt=search_on))
        res = hinted.localize(scan_from(world_up(seed=3) @ Z_DOWN.T, T_true), gravity_body(T_true),
                              hint_xy=(6.0, 4.0), window_m=30.0)
        if search_on:
            assert len(regions) == 1 and regions[0][1] == 30.0
            assert res.verified and not res.ambiguous, res.stats
            dt, dr = pose_error(res.T_map_body, T_true)
            assert dt < 0.1 and dr < 0.5, (dt, dr)
            assert res.stats["searched_on"] and res.stats["hint_search"] == "places, then branch and bound"
            assert all(c.refiner is None for c in res.candidates)
        else:
            assert regions == [] and res.ambiguous and not res.verified


def test_a_hinted_best_whose_coverage_was_not_judged_does_not_end_the_search(setup, monkeypatch):
    """A hint constrains the no-hint search, doubts included. Defaults' map, ``--rng 13``, hinted
    frame 25176 with 8 m place windows: a place 23 m off verified on its fit alone (0.77, static-band
    coverage not judged) stood, a wrong answer; the window's branch and bound finds the truth (0.92).
    Such a best sends the search on to the window's branch and bound; one whose coverage was judged,
    or without the rule, stands."""
    from blockloc.global_init import verify

    loc, T_true, scan, scan_ndt, refiner = setup
    T_wrong = xyzrpy_to_T(9.0, 4.0, -(1.9 + 0.02 * 9.0), 0.03, -0.02, 2.4)
    for unjudged, coverage, searched_on in ((True, math.nan, True), (False, math.nan, False), (True, 0.95, False)):
        regions = []

        def places(self, scan, scan_ndt, cells, index, theta_c, yaw_win, stats, deadline=math.inf,
                   candidates=None, flip_open=False, first_stage=0, done=None, coverage=coverage):
            wrong = InitCandidate(T_wrong, 0.9, 0.773, True, True, T_wrong, 1.1, 0.62, coverage=coverage,
                                  see_through=0.0, refiner=refiner)
            wrong.probes = []
            return [wrong], dict(stats, place_stage=1)

        def region(self, scan, scan_ndt, center, window_m, theta_c, yaw_win, cells=None, regions=regions):
            regions.append(window_m)
            r = refiner.align(scan_ndt, T_true)
            found = self._verified(r, refiner, 0.95, T_true, scan, None, verify.Thresholds.of(self.params))
            return [found], {}

        monkeypatch.setattr(GlobalLocalizer, "_relocalize_places", places)
        monkeypatch.setattr(GlobalLocalizer, "_search_region", region)
        hinted = GlobalLocalizer(loc.map, InitParams(search_on_unjudged=unjudged, whole_scan_voxel_m=0.0))
        res = hinted.localize(scan_from(world_up(seed=3) @ Z_DOWN.T, T_true), gravity_body(T_true),
                              hint_xy=(6.0, 4.0), window_m=30.0)
        assert res.verified and not res.ambiguous, res.stats
        if searched_on:
            assert regions == [30.0] and res.stats["hint_search"] == "places, then branch and bound"
            dt, dr = pose_error(res.T_map_body, T_true)
            assert dt < 0.1 and dr < 0.5, (dt, dr)
        else:
            assert regions == [] and np.allclose(res.T_map_body, T_wrong)


def test_a_verified_best_whose_coverage_was_not_judged_does_not_end_the_place_search(setup, monkeypatch):
    """Campus, nominal-mounting map, ``--rng 7`` after the hinted frames: frames 16517 (a place
    197.5 m off, fitness 0.83, structure 0.69) and 39798 (the true place's reverse, 174 deg turned)
    verified at the first stage on their NDT fit alone, the static-band coverage not judged (too
    few bins: open stretches), and the true places were never searched. Such a best does not end
    the place search (as a doubted one does not); the decision judges everything found. A best
    whose coverage was judged ends it as before, and so does one that fits strongly (inlier ratio
    >= 0.90 and structure >= 0.85 by default: no wrong candidate with coverage not judged reached
    both on 12 campus draws; frame 16517's wrong place fit 0.83 / 0.69)."""
    from blockloc.global_init import verify

    loc, T_true, scan, scan_ndt, refiner = setup
    T_wrong = xyzrpy_to_T(-25.0, 20.0, -(1.9 - 0.02 * 25.0), 0.03, -0.02, 0.7)
    # (rule on, coverage, the first best's fitness / structure, its strong-fit floors, searched on?)
    cases = ((True, math.nan, 0.831, 0.690, (0.90, 0.85), True),  # frame 16517's numbers
             (False, math.nan, 0.831, 0.690, (0.90, 0.85), False),  # no rule: it stands
             (True, 0.95, 0.831, 0.690, (0.90, 0.85), False),  # coverage judged: it stands
             (True, math.nan, 0.95, 0.97, (0.90, 0.85), False),  # a strong fit stands
             (True, math.nan, 0.95, 0.97, (0.96, 0.85), True),  # ... not strong enough
             (True, math.nan, 0.95, 0.84, (0.90, 0.85), True))  # ... nor here
    for unjudged, coverage, fitness, structure, (min_fit, min_struct), searched_on in cases:
        stages = []

        def places(self, scan, scan_ndt, cells, index, theta_c, yaw_win, stats, deadline=math.inf,
                   candidates=None, flip_open=False, first_stage=0, done=None, stages=stages, coverage=coverage,
                   fitness=fitness, structure=structure):
            stages.append(first_stage)
            if first_stage == 0:  # the wrong place, verified (made so), probed already: no rival
                wrong = InitCandidate(T_wrong, 0.9, fitness, True, True, T_wrong, 1.1, structure, coverage=coverage,
                                      see_through=0.0, refiner=refiner)
                wrong.probes = []
                return [wrong], dict(stats, place_stage=1)
            r = refiner.align(scan_ndt, T_true)
            found = self._verified(r, refiner, 0.95, T_true, scan, None, verify.Thresholds.of(self.params))
            found.coverage = 0.97
            return [found], dict(stats, place_stage=3)

        monkeypatch.setattr(GlobalLocalizer, "_relocalize_places", places)
        # whole_scan_voxel_m 0: the wrong place is verified by hand, not at an NDT optimum; the whole
        # scan's alignment would move it to one
        nohint = GlobalLocalizer(loc.map, InitParams(search_on_unjudged=unjudged, max_search_s=0.0,
                                                     whole_scan_voxel_m=0.0, unjudged_min_fitness=min_fit,
                                                     unjudged_min_structure_fitness=min_struct))
        res = nohint.localize(scan_from(world_up(seed=3) @ Z_DOWN.T, T_true), gravity_body(T_true))
        assert res.verified and not res.ambiguous
        dt, _ = pose_error(res.T_map_body, T_true)
        if searched_on:
            assert stages == [0, 1] and res.stats["searched_on"] == 1
            assert any(np.allclose(c.T_map_body, T_wrong) for c in res.candidates)  # judged
            if fitness < 0.9:  # the true place fits better: it wins
                assert dt < 0.1, dt
        else:  # the first stage's best stands
            assert stages == [0] and np.allclose(res.T_map_body, T_wrong)


def test_a_best_verified_on_its_fit_alone_is_the_answer_of_a_search_only_as_the_clear_best(setup, monkeypatch):
    """Campus, nominal-mounting map, frame 39893: a place 465 m off (fitness 0.776, structure 0.61,
    static-band coverage not judged; another candidate fit 0.781) verified at the last stage,
    nothing better was found, and it was reported verified. Such a best, where the search ends with
    it (without a hint, and with one after the window's branch and bound found nothing more), is
    the answer only as the clear best: fitting well (0.88 / 0.75 by default) and by 0.05 better
    than every other candidate (campus: the right ones fit 0.90-0.93 / 0.82-0.86, by 0.09-0.14);
    else it is reported ambiguous (``stats['unjudged']``). A best whose coverage was judged, or
    that fits strongly, is the answer as before."""
    loc, T_true, scan, scan_ndt, refiner = setup
    T_wrong = xyzrpy_to_T(9.0, 4.0, -(1.9 + 0.02 * 9.0), 0.03, -0.02, 2.4)
    T_far = xyzrpy_to_T(-20.0, 10.0, -(1.9 - 0.02 * 20.0), 0.03, -0.02, 0.4)
    # (coverage, fitness, structure, another candidate's fitness (None: none), the answer?)
    cases = ((math.nan, 0.776, 0.61, 0.781, False),  # frame 39893's numbers
             (math.nan, 0.776, 0.61, None, False),  # alone, but not a good fit
             (math.nan, 0.92, 0.83, None, True),  # the clear best
             (math.nan, 0.92, 0.83, 0.90, False),  # ... not clear
             (0.95, 0.776, 0.61, 0.781, True),  # coverage judged
             (math.nan, 0.95, 0.97, 0.93, True))  # a strong fit
    # (``unjudged_clear_best`` false, the handheld preset's choice: any verified best is the answer)
    cases += tuple((c, f, s, o, True, False) for c, f, s, o, _ in cases[:2])
    cases = tuple(c if len(c) == 6 else c + (True,) for c in cases)
    for hint in (None, (6.0, 4.0)):
        for coverage, fitness, structure, other, answer, rule in cases:
            def found():
                best = InitCandidate(T_wrong, 0.9, fitness, True, True, T_wrong, 1.9, structure, coverage=coverage,
                                     see_through=0.0, refiner=refiner)
                best.probes = []
                if other is None:
                    return [best]
                rival = InitCandidate(T_far, 0.9, other, True, False, T_far, 1.0, 0.5, refiner=refiner)
                rival.probes = []
                return [best, rival]

            def places(self, scan, scan_ndt, cells, index, theta_c, yaw_win, stats, deadline=math.inf,
                       candidates=None, flip_open=False, first_stage=0, done=None):
                if first_stage > 0:
                    return [], dict(stats, place_stage=first_stage)  # every stage searched: nothing more
                return found(), dict(stats, place_stage=4)

            def region(self, scan, scan_ndt, center, window_m, theta_c, yaw_win, cells=None):
                return [], {}  # the hint's window: nothing more either

            monkeypatch.setattr(GlobalLocalizer, "_relocalize_places", places)
            monkeypatch.setattr(GlobalLocalizer, "_search_region", region)
            other_loc = GlobalLocalizer(loc.map, InitParams(max_search_s=0.0, whole_scan_voxel_m=0.0,
                                                            unjudged_clear_best=rule))
            res = other_loc.localize(scan_from(world_up(seed=3) @ Z_DOWN.T, T_true), gravity_body(T_true),
                                     hint_xy=hint, window_m=30.0)
            assert res.candidates and np.allclose(res.candidates[0].T_map_body, T_wrong)
            assert res.verified is answer and res.ambiguous is not answer, (hint, coverage, fitness, other, rule)
            assert res.stats.get("unjudged", False) is not answer
