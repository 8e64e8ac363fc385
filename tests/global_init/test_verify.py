"""Verification thresholds: one test (``verify.passes``) for the localizer and bench/real.py."""

from __future__ import annotations

import math

from blockloc.config import Config, load_config
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
