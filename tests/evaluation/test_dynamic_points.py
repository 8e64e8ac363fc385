"""SA / DA / AA of a cleaned map against labelled ground truth (the DynamicMap Benchmark's definition)."""

import math

import numpy as np
import pytest

from blockloc.evaluation.dynamic_points import BENCHMARK_RADIUS_M, dynamic_scores, kept_mask, scores_from_mask


def _grid(n, z=0.0):
    x, y = np.meshgrid(np.arange(n) * 0.5, np.arange(n) * 0.5)
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)


def test_known_answer():
    # 100 static points, 20 dynamic, 0.5 m apart (no accidental neighbour within 0.05 m)
    static, dynamic = _grid(10), _grid(5, z=3.0)[:20]
    gt = np.concatenate([static, dynamic])
    lab = np.r_[np.zeros(100, bool), np.ones(20, bool)]
    # the cleaned map keeps 90 static points (moved by 3 cm: still the same point) and 5 dynamic ones
    cleaned = np.concatenate([static[:90] + [0.03, 0, 0], dynamic[:5]])
    s = dynamic_scores(gt, lab, cleaned)
    assert (s.static_points, s.dynamic_points, s.static_kept, s.dynamic_removed) == (100, 20, 90, 15)
    assert s.sa == pytest.approx(90.0) and s.da == pytest.approx(75.0)
    assert s.aa == pytest.approx(math.sqrt(90.0 * 75.0))
    assert s.ha == pytest.approx(2 * 90 * 75 / 165)


def test_radius_is_the_benchmarks():
    gt = np.zeros((1, 3))
    assert BENCHMARK_RADIUS_M == 0.05
    assert kept_mask(gt, np.array([[0.049, 0, 0]])).all()
    assert not kept_mask(gt, np.array([[0.051, 0, 0]])).any()
    assert kept_mask(gt, np.array([[0.09, 0, 0]]), radius_m=0.1).all()


def test_raw_and_empty_maps():
    gt = _grid(6)
    lab = np.arange(len(gt)) % 4 == 0
    raw = dynamic_scores(gt, lab, gt)  # the raw map keeps everything: SA 100, DA 0
    assert raw.sa == 100.0 and raw.da == 0.0 and raw.aa == 0.0
    empty = dynamic_scores(gt, lab, np.zeros((0, 3)))
    assert empty.sa == 0.0 and empty.da == 100.0
    perfect = dynamic_scores(gt, lab, gt[~lab])
    assert perfect.sa == perfect.da == perfect.aa == 100.0


def test_no_dynamic_points_gives_nan_da():
    s = scores_from_mask(np.zeros(5, bool), np.ones(5, bool))
    assert s.sa == 100.0 and math.isnan(s.da) and math.isnan(s.aa)
    with pytest.raises(ValueError):
        scores_from_mask(np.zeros(5, bool), np.ones(4, bool))
