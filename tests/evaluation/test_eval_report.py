"""evaluate_files / evaluate_trajectories / print_metrics: pairing, errors, plots, output."""

from __future__ import annotations

import json

import numpy as np
import pytest
from rich.console import Console

from blockloc.errors import BlocklocError, EvaluationError
from blockloc.commands.eval import print_metrics
from blockloc.evaluation.report import evaluate_files, evaluate_trajectories
from blockloc.trajectory_io import write_kitti, write_tum
from blockloc.geometry import Trajectory

from eval_trajgen import perturb, random_trajectory


def test_evaluate_files_tum_vs_untimed_kitti_pairs_by_index(tmp_path, rng):
    gt = random_trajectory(rng, n=150)
    est = perturb(rng, gt, 0.1, 0.01)
    write_tum(tmp_path / "gt.tum", gt)
    write_kitti(tmp_path / "est.kitti", est, write_times=False)
    m = evaluate_files(tmp_path / "gt.tum", tmp_path / "est.kitti")
    assert m["association"] == "index" and m["matched"] == 150
    direct = evaluate_trajectories(gt, est)
    assert m["ate_trans_rmse_m"] == pytest.approx(direct["ate_trans_rmse_m"], abs=1e-7)
    assert m["ate_full_rmse"] == pytest.approx(direct["ate_full_rmse"], abs=1e-7)
    json.dumps(m)  # JSON-able
    write_kitti(tmp_path / "short.kitti", Trajectory(est.stamps[:100], est.poses[:100]), write_times=False)
    with pytest.raises(EvaluationError, match="equal lengths, got 150 ground-truth and 100 estimated"):
        evaluate_files(tmp_path / "gt.tum", tmp_path / "short.kitti")


def test_no_time_overlap_names_both_spans(tmp_path, rng):
    gt = random_trajectory(rng, n=50, t0=1000.0)
    est = Trajectory(gt.stamps * 1e6, gt.poses)  # microseconds instead of seconds
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", est)
    with pytest.raises(EvaluationError, match=r"est.tum vs .*gt.tum: no estimated pose within 0.02 s.*"
                                              r"ground truth 1000.000..1004.900 s"):
        evaluate_files(tmp_path / "gt.tum", tmp_path / "est.tum")


def test_partial_overlap_is_noted_and_metrics_use_matched_poses_only(rng):
    gt = random_trajectory(rng, n=200)
    est = perturb(rng, gt, 0.05, 0.0)
    est = Trajectory(np.concatenate([est.stamps, est.stamps[-1] + 1 + np.arange(20)]),
                     np.concatenate([est.poses, np.repeat(est.poses[-1:], 20, axis=0)]))
    m = evaluate_trajectories(gt, est)
    assert m["matched"] == 200 and m["est_poses"] == 220
    assert "matched 200 of 220 estimated poses" in m["notes"]


def test_perfect_estimate_has_zero_error_and_known_offset_is_measured(rng):
    gt = random_trajectory(rng, n=100)
    m = evaluate_trajectories(gt, gt)
    assert m["ate_trans_rmse_m"] == 0.0 and m["ate_full_rmse"] < 1e-12 and m["ate_rot_rmse_deg"] < 1e-9
    shifted = Trajectory(gt.stamps, gt.poses.copy())
    shifted.poses[:, :3, 3] += [0.3, 0.4, 0.0]  # 0.5 m everywhere
    m = evaluate_trajectories(gt, shifted)
    assert m["ate_trans_rmse_m"] == pytest.approx(0.5) and m["ate_trans_max_m"] == pytest.approx(0.5)
    assert m["ate_full_rmse"] == pytest.approx(0.5)  # no rotation error: ||E - I||_F = ||t||
    assert evaluate_trajectories(gt, shifted, align=True)["ate_trans_rmse_m"] < 1e-9


def test_align_on_a_straight_line_is_refused(rng):
    t = np.arange(10.0)
    poses = np.tile(np.eye(4), (10, 1, 1))
    poses[:, 0, 3] = t
    line = Trajectory(t, poses)
    with pytest.raises(EvaluationError, match="collinear"):
        evaluate_trajectories(line, line, align=True)


def test_plots_are_written_as_png(tmp_path, rng):
    gt = random_trajectory(rng, n=120)
    est = perturb(rng, gt, 0.1, 0.02)
    m = evaluate_trajectories(gt, est, plot_dir=tmp_path / "plots")
    names = ("error_breakdown.png", "errors.png", "trajectories.png")
    assert sorted(m["plots"]) == sorted(str(tmp_path / "plots" / n) for n in names)
    for p in m["plots"]:
        data = open(p, "rb").read()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == list(names)


def test_print_metrics_shows_the_numbers(rng):
    gt = random_trajectory(rng, n=200)
    est = perturb(rng, gt, 0.1, 0.02)
    m = evaluate_trajectories(gt, est, rpe_deltas_m=(1.0, 1000.0))
    console = Console(record=True, width=140)
    print_metrics(m, console)
    text = console.export_text()
    assert f"{m['ate_trans_rmse_m']:.4f}" in text and f"{m['ate_full_rmse']:.4f}" in text
    assert f"{m['rpe_1m_trans_rmse_m']:.4f}" in text
    assert "RPE 1000 m skipped" in text
    assert "translation [m]" in text and "[deg/m]" in text  # units survive rich markup


def test_interpolation_removes_time_skew_bias(rng):
    # ground truth at 100 Hz, estimate = exact poses at stamps 4 ms off the grid: nearest matching
    # sees the robot's motion over 4 ms as error, interpolation does not
    gt = random_trajectory(rng, n=1000, dt=0.01, speed=1.5)
    t_est = gt.stamps[5:-5:10] + 0.004
    est = Trajectory(t_est, gt.interpolate(t_est))
    nearest = evaluate_trajectories(gt, est, max_time_diff_s=0.02)
    interp = evaluate_trajectories(gt, est, max_time_diff_s=0.02, interpolate=True)
    assert nearest["ate_trans_rmse_m"] == pytest.approx(1.5 * 0.004, rel=0.05)
    assert interp["ate_trans_rmse_m"] < 1e-9
    assert interp["matched"] == nearest["matched"] == len(est)
    assert interp["association"] == "interpolated"
    far = Trajectory(t_est + 100.0, est.poses)
    with pytest.raises(EvaluationError, match="no estimated pose within"):
        evaluate_trajectories(gt, far, interpolate=True)


def test_parse_deltas():
    from blockloc.commands.common import parse_deltas

    assert parse_deltas("1, 10,100") == (1.0, 10.0, 100.0) and parse_deltas("") == ()
    for bad in ("1,x", "0", "-5"):
        with pytest.raises(BlocklocError, match="--rpe-deltas .* expected positive distances"):
            parse_deltas(bad)


def test_evaluate_files_nclt_groundtruth_against_tum_and_timed_kitti(tmp_path, rng):
    from blockloc.geometry import T_to_xyzrpy

    gt = random_trajectory(rng, n=300, t0=1326044400.0, dt=0.1)
    rows = ["%d,nan,nan,nan,nan,nan,nan" % 1326044399000000]  # NCLT's leading NaN row
    for t, v in zip(gt.stamps, T_to_xyzrpy(gt.poses)):
        rows.append(",".join(["%d" % round(t * 1e6)] + ["%.9f" % x for x in v]))
    (tmp_path / "groundtruth_2012-01-22.csv").write_text("\n".join(rows) + "\n")
    est = perturb(rng, gt, 0.08, 0.01)
    est = Trajectory(est.stamps + 0.005, est.poses)
    write_tum(tmp_path / "est.tum", est)
    write_kitti(tmp_path / "est.kitti", est)  # with est.times.txt
    direct = evaluate_trajectories(gt, est)
    for name in ("est.tum", "est.kitti"):
        m = evaluate_files(tmp_path / "groundtruth_2012-01-22.csv", tmp_path / name)
        assert m["matched"] == 300 and m["association"] == "time"
        assert m["ate_trans_rmse_m"] == pytest.approx(direct["ate_trans_rmse_m"], abs=1e-6)
        assert m["ate_full_rmse"] == pytest.approx(direct["ate_full_rmse"], abs=1e-6)
