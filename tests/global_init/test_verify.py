"""Verification thresholds: one test (``verify.passes``) for the localizer and bench/real.py."""

from __future__ import annotations

import math

import numpy as np

from blockloc.config import Config, load_config
from blockloc.geometry import rotation_angle, rpy_to_R
from blockloc.global_init.params import InitParams
from blockloc.global_init.verify import Thresholds, consistency_passes, fit_passes, passes

TH = Thresholds(0.75, 0.6, 0.9, 0.35)


def test_thresholds_come_from_the_section():
    assert Thresholds.of(Config().global_init) == TH
    gi = load_config("handheld").global_init
    assert Thresholds.of(gi) == Thresholds(gi.min_fitness, gi.min_structure_fitness, gi.min_coverage,
                                           gi.max_see_through)


def test_every_threshold_decides():
    assert passes(True, 0.8, 0.7, 0.95, 0.1, TH)
    assert not passes(False, 0.8, 0.7, 0.95, 0.1, TH)  # not converged
    assert not passes(True, 0.8, 0.7, 0.95, 0.1, TH, finite=False)
    assert not passes(True, 0.7, 0.7, 0.95, 0.1, TH)  # fitness
    assert not passes(True, 0.8, 0.5, 0.95, 0.1, TH)  # above-ground structure
    assert not passes(True, 0.8, 0.7, 0.85, 0.1, TH)  # coverage
    assert not passes(True, 0.8, 0.7, 0.95, 0.4, TH)  # seen through the map's structure
    assert fit_passes(True, True, 0.75, 0.6, TH)  # the floors themselves pass


def test_consistency_not_judged_passes():
    assert consistency_passes(math.nan, math.nan, TH)
    assert not consistency_passes(0.5, math.nan, TH) and not consistency_passes(math.nan, 0.5, TH)


# --------------------------------------------------------------- the whole scan's last alignment


def _result(T, converged=True, fitness=0.9):
    from blockloc.global_init.refine import RefineResult

    return RefineResult(np.array(T, float), fitness, converged)


def _moved(dx):
    T = np.eye(4)
    T[0, 3] = dx
    return T


def _candidate(T, probes_at=(0.3,)):
    """A verified candidate at T whose NDT restarts ended ``probes_at`` metres from it along x."""
    from blockloc.global_init.verify import InitCandidate

    c = InitCandidate(np.array(T, float), 0.9, 0.9, True, True, np.array(T, float), 1.5, 0.9, refiner=object())
    c.probes = [(None, _result(np.array(T, float) @ _moved(d))) for d in probes_at]
    return c


class _Align:
    """A ``refine.WholeScan`` whose run ends where the test says (``verify.on_whole_scan``'s rule alone)."""

    def __init__(self, T, converged=True, fitness=0.9):
        self.result, self.calls = _result(T, converged, fitness), 0
        self.points = np.zeros((10, 3))

    def align(self, T_map_body):
        self.calls += 1
        return self.result

    def release(self):
        self.released = True


class _NoMap(_Align):
    def __init__(self):
        super().__init__(np.eye(4))

    def align(self, T_map_body):
        self.calls += 1
        return None


def test_the_whole_scan_brings_a_loosely_held_pose_to_its_optimum():
    from blockloc.global_init.refine import Refiner
    from blockloc.global_init.verify import on_whole_scan
    from blockloc.registration.engines import make_engine

    from .synthetic import scan_from, world_up

    world = world_up(seed=3)
    T_true = np.eye(4)
    T_true[:3, 3] = (4.0, -3.0, 1.5)
    T_off = T_true.copy()
    T_off[:3, :3] = rpy_to_R(0.0, 0.0, math.radians(1.0))
    T_off[:2, 3] += (0.25, -0.1)  # where the near scan left it
    from blockloc.global_init.refine import WholeScan

    refiner = Refiner(make_engine("ndt"), world)
    whole = WholeScan(scan_from(world, T_true), lambda xy, d: refiner, np.eye(3), 65.0)
    best = _candidate(T_off)
    assert on_whole_scan(best, whole, InitParams())
    assert np.linalg.norm(best.T_map_body[:3, 3] - T_true[:3, 3]) < 0.05
    assert rotation_angle(best.T_map_body[:3, :3].T @ T_true[:3, :3]) < math.radians(0.2)


def test_only_a_pose_the_scan_holds_loosely_is_aligned_again():
    from blockloc.global_init.verify import loosely_held, on_whole_scan

    p = InitParams()
    for probes_at, loose in (((0.05, -0.08), False),  # every restart came back: held firmly
                             ((0.05, p.one_optimum_m + 0.05), True),  # one ended along a flat direction
                             ((3.0, -2.5), False),  # other places: rivals, not looseness
                             ((), False)):  # no restarts run
        best = _candidate(np.eye(4), probes_at)
        align = _Align(_moved(0.1))
        assert loosely_held(best, p) is loose
        assert on_whole_scan(best, align, p) is loose and align.calls == int(loose)
        assert best.T_map_body[0, 3] == (0.1 if loose else 0.0)
    unconverged = _candidate(np.eye(4), ())
    unconverged.probes = [(None, _result(_moved(0.3), converged=False))]
    assert not loosely_held(unconverged, p)


def test_the_whole_scan_never_moves_a_verified_pose_to_what_was_not_verified():
    from blockloc.global_init.verify import on_whole_scan

    p = InitParams()
    for align in (_Align(_moved(p.ambiguity_distance_m + 0.3)),  # another place
                  _Align(_moved(0.1), converged=False),  # still sliding
                  _Align(_moved(0.1), fitness=p.min_fitness - 0.05),  # fits worse than verification asks
                  _Align(np.full((4, 4), np.nan))):
        best = _candidate(np.eye(4))
        assert not on_whole_scan(best, align, p) and np.array_equal(best.T_map_body, np.eye(4))
        assert align.calls == 1
    assert not on_whole_scan(_candidate(np.eye(4)), _NoMap(), p)  # no map there


def test_a_standing_decision_aligns_only_a_verified_best_and_drops_every_target():
    from blockloc.global_init.verify import InitResult, stand

    p = InitParams()
    for verified in (True, False):
        cands = [_candidate(np.eye(4)), _candidate(_moved(5.0))]
        res = InitResult(cands[0].T_map_body, 0.9, 0.9, cands, not verified, 0.2, verified, {})
        whole = _Align(_moved(0.1))
        stand(res, whole, p)
        assert all(c.refiner is None for c in cands) and whole.released
        assert res.T_map_body[0, 3] == (0.1 if verified else 0.0)
        assert res.stats.get("whole_scan_moved", False) is verified
        # a second standing (a decision returned as it stood) changes nothing: the targets are gone
        stand(res, _Align(_moved(0.2)), p)
        assert res.T_map_body[0, 3] == (0.1 if verified else 0.0)
