"""Helpers of the real-data benchmark (bench/real.py): the held-out frames and seeded hints, the
init outcome, the time statistics, the quote of the NDT fragment, the block footprints of the
plot, the target verdicts, and the config the walk runs with. Not a run of the benchmark."""

from __future__ import annotations

import numpy as np
import pytest

from bench import real
from blockloc.global_init.verify import Thresholds


def test_init_frames_are_every_fourth_held_out_scan():
    frames = real.init_frames(89, 177, 4)
    assert frames[0] == 89 and frames[-1] == 173 and len(frames) == 22
    assert set(np.diff(frames)) == {4}


def test_hints_are_seeded_and_within_the_error_box():
    ref = np.array([[0.0, 0.0], [10.0, -5.0], [3.0, 3.0]] * 50)
    a, b = real.draw_hints(ref, 8.0, 0), real.draw_hints(ref, 8.0, 0)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, real.draw_hints(ref, 8.0, 1))
    off = a - ref
    assert np.all(np.abs(off) <= 8.0) and np.abs(off).max() > 6.0  # uniform over the box, not a ring
    assert abs(off.mean()) < 1.5


@pytest.mark.parametrize("verified, err_m, err_deg, expected", [
    (True, 0.29, 1.9, "ok"), (True, 0.31, 0.1, "wrong"), (True, 0.01, 2.5, "wrong"),
    (False, 0.01, 0.1, "unverified"), (False, np.inf, np.inf, "unverified")])
def test_init_outcome(verified, err_m, err_deg, expected):
    assert real.init_outcome(verified, err_m, err_deg) == expected


def test_stats_drop_nans_and_give_percentiles():
    s = real.stats_ms([1.0, 2.0, 3.0, 4.0, np.nan, 100.0])
    assert s["n"] == 5 and s["median"] == 3.0 and s["max"] == 100.0
    assert 4.0 < s["p90"] < 100.0
    assert np.isnan(real.stats_ms([])["median"])


NDT_TEXT = """## NDT registration

Command: `python -m bench.ndt` (2030-01-02 03:04 UTC).
Machine: Some CPU, 2 cores; numba threads 2. Load average 1.0

| method | starts | median time [ms] | fastest [ms] | median iterations | within 5 cm / 0.5 deg | median error [cm] | median error [deg] |
|---|---|---|---|---|---|---|---|
| NDT DIRECT7, coarse-to-fine (default) | tracking | 4.4 | 3.5 | 7 | 30/30 | 1.9 | 0.13 |
| NDT DIRECT7, single level | tracking | 7.7 | 4.6 | 7 | 30/30 | 1.6 | 0.23 |
| small_gicp VGICP 1.0 m (source covariances precomputed) | wide | 3.7 | 3.0 | 4 | 29/30 | 2.1 | 0.16 |
| synthetic 100 m city block | 1,000,000 | 1.0 | 1 | 42,501 | 58 |
"""


def test_quote_ndt_takes_the_default_and_vgicp_rows_with_the_run_line():
    q = real.quote_ndt(NDT_TEXT)
    assert q["run"].startswith("Command: `python -m bench.ndt` (2030-01-02")
    assert q["machine"].startswith("Machine: Some CPU")
    assert q["rows"] == [("NDT DIRECT7, coarse-to-fine (default)", "tracking", "4.4", "30/30", "1.9", "0.13"),
                         ("small_gicp VGICP 1.0 m (source covariances precomputed)", "wide", "3.7", "29/30", "2.1",
                          "0.16")]


def test_quote_ndt_reads_the_fragment_in_the_repo():
    q = real.quote_ndt(real.NDT_FRAGMENT.read_text())
    assert q["run"] and {r[1] for r in q["rows"]} == {"tracking", "wide"}


def test_block_footprints_follow_the_nearest_keyframe_and_drop_stray_points():
    rng = np.random.default_rng(0)
    strip = np.column_stack([rng.uniform(0.0, 20.0, 40_000), rng.uniform(0.0, 4.0, 40_000)])
    stray = np.array([[60.0, 60.0]])
    keyframes = [np.array([[2.0, 2.0, 0.0], [4.0, 2.0, 0.0]]), np.array([[16.0, 2.0, 0.0]])]
    labels, xc, yc = real.block_footprints(keyframes, np.vstack([strip, stray]))
    assert labels.shape == (len(yc), len(xc))
    row = labels[np.argmin(np.abs(yc - 2.0))]
    inside = (xc > 0.5) & (xc < 19.5)
    assert np.all(row[inside & (xc < 9.5)] == 0) and np.all(row[inside & (xc > 10.5)] == 1)
    assert labels[np.argmin(np.abs(yc - 60.0)), np.argmin(np.abs(xc - 60.0))] == -1  # one stray return
    assert np.all(labels[yc > 6.0] == -1)


def _track(ate, lost=0, update=20.0):
    return {"metrics": {"ate_trans_rmse_m": ate}, "statuses": {"ok": 88 - lost, "lost": lost},
            "counters": {"recoveries": 0, "rotation_retries": 2}, "update_ms": {"median": update},
            "thread_cpu_ms": {"median": update / 2}}


def _init(ok, n=22, median_s=0.5):
    return {"share_ok": ok / n, "ok": ok, "rows": [None] * n, "wrong": 0, "total_s": {"median": median_s}}


def test_targets_say_met_and_missed_at_the_thresholds():
    walk = {"threads": [2], "gt_2": _track(0.0299), "hint": _track(0.031, lost=1, update=35.0),
            "init_2": _init(21, median_s=1.01), "init_default": _init(20)}
    sim = {"metrics": {"ate_trans_rmse_m": 0.05, "failures": 0}, "statuses": {"ok": 10}}
    rows = {t: v for t, _, v, _ in real.targets(walk, sim)}
    assert rows["ATE translation RMSE <= 0.03 m, held-out half, `--init gt`"] == "met"
    assert rows["ATE translation RMSE <= 0.03 m, held-out half, from a hint"] == "**missed**"
    assert rows["no lost scan (`--init gt`; recoveries allowed)"] == "met"
    assert rows["no lost scan (from a hint; recoveries allowed)"] == "**missed**"
    assert rows["global init: >= 95% of hinted scans within 0.3 m and 2 deg (`handheld`)"] == "met"  # 21/22
    assert rows["global init: >= 95% of hinted scans within 0.3 m and 2 deg (default thresholds)"] == "**missed**"
    assert rows["global init: median time <= 1 s (`handheld`)"] == "**missed**"
    assert rows["median per-scan update <= 30 ms (~25k-point scans)"] == "met"
    assert rows["LiDAR-only on the small world: ATE <= 0.10 m"] == "met"
    assert rows["LiDAR-only on the small world: no failure"] == "met"


def test_the_handheld_preset_is_the_walk_tests_config_but_for_documented_settings():
    from tests.tracking.walk import walk_config

    a, b = real.walk_config_handheld().to_dict(), walk_config().to_dict()
    differ = {(s, k) for s in a for k in a[s] if a[s][k] != b[s][k]}
    # global-init verification (the preset's: its floors, the clear best's, every scan point counted),
    # every scan a keyframe (the walk's map builder passes 0/0 itself), deskew (a no-op on the walk's
    # scans, which have no per-point times)
    assert differ == {("global_init", "min_fitness"), ("global_init", "min_structure_fitness"),
                      ("global_init", "structure_from_static"), ("global_init", "min_coverage"),
                      ("global_init", "unjudged_end_min_fitness"),
                      ("global_init", "unjudged_end_min_structure_fitness"), ("global_init", "footprint_cell_m"),
                      ("map", "keyframe_distance_m"), ("map", "keyframe_angle_deg"), ("lidar", "deskew")}
    assert a["map"]["block_size_m"] == b["map"]["block_size_m"] == 8.0


def test_decide_takes_the_best_passing_candidate_by_ndt_score():
    # (correct, fitness, above-ground inlier ratio, converged, NDT score)
    cands = [(True, 0.55, 0.80, True, 1.0), (False, 0.65, 0.65, True, 1.2), (False, 0.9, 0.9, False, 2.0)]
    assert real.decide(cands, Thresholds(0.75, 0.6, 0.9, 0.35)) is None  # the only fit one did not converge
    assert real.decide(cands, Thresholds(0.5, 0.6, 0.9, 0.35)) == "wrong"  # the wrong one scores higher and passes
    assert real.decide(cands, Thresholds(0.5, 0.7, 0.9, 0.35)) == "ok"  # the above-ground ratio rules it out
    # static-band consistency: the wrong one's map structure where the scan saw through
    cands = [c + (0.95, 0.1) for c in cands[:1]] + [cands[1] + (0.95, 0.5), cands[2] + (np.nan, np.nan)]
    assert real.decide(cands, Thresholds(0.5, 0.6, 0.9, 0.35)) == "ok"
