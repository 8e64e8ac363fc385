"""ATE/RPE agree with evo (GPL: used here, in tests only, never by blockloc itself)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from blockloc.evaluation.metrics import (absolute_pose_errors, associate, pairs_by_path_distance,
                                         relative_pose_errors, umeyama_alignment)
from blockloc.evaluation.report import evaluate_trajectories
from blockloc.geometry import Trajectory

from eval_trajgen import perturb, random_trajectory

evo_metrics = pytest.importorskip("evo.core.metrics")
from evo.core import sync  # noqa: E402
from evo.core.trajectory import PoseTrajectory3D  # noqa: E402

PR = evo_metrics.PoseRelation


def to_evo(traj: Trajectory) -> PoseTrajectory3D:
    return PoseTrajectory3D(poses_se3=list(traj.poses.copy()), timestamps=traj.stamps.copy())


def evo_ape(gt: Trajectory, est: Trajectory, relation, align: bool, max_diff: float = 0.02) -> float:
    ref, e = sync.associate_trajectories(to_evo(gt), to_evo(est), max_diff=max_diff)
    if align:
        e = copy.deepcopy(e)
        e.align(ref)
    ape = evo_metrics.APE(relation)
    ape.process_data((ref, e))
    return ape.get_statistic(evo_metrics.StatisticsType.rmse)


def offset_T(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [0.02, -0.03, 0.7]).as_matrix()
    T[:3, 3] = rng.normal(0, 3.0, 3)
    return T


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("align", [False, True])
def test_ate_equals_evo_ape(seed, align):
    rng = np.random.default_rng(seed)
    gt = random_trajectory(rng, n=300)
    est = perturb(rng, gt, 0.15, 0.03, T_offset=offset_T(rng) if align else None)
    # jitter the estimate's stamps, well inside the association tolerance
    est = Trajectory(est.stamps + rng.uniform(-0.008, 0.008, len(est)), est.poses)
    m = evaluate_trajectories(gt, est, align=align, max_time_diff_s=0.02)
    assert m["matched"] == 300
    assert m["aligned"] is align
    assert m["ate_trans_rmse_m"] == pytest.approx(evo_ape(gt, est, PR.translation_part, align), abs=1e-6)
    assert m["ate_full_rmse"] == pytest.approx(evo_ape(gt, est, PR.full_transformation, align), abs=1e-6)
    assert m["ate_rot_rmse_deg"] == pytest.approx(evo_ape(gt, est, PR.rotation_angle_deg, align), abs=1e-6)
    if align:
        # the injected offset is large; alignment must remove it (ATE back to the noise level)
        assert m["ate_trans_rmse_m"] < 0.4
        unaligned = evaluate_trajectories(gt, est, align=False)
        assert unaligned["ate_trans_rmse_m"] > 1.0


def test_ate_stats_match_evo_statistics(rng):
    gt = random_trajectory(rng, n=200)
    est = perturb(rng, gt, 0.2, 0.05)
    ref_e, est_e = sync.associate_trajectories(to_evo(gt), to_evo(est), max_diff=0.01)
    ape = evo_metrics.APE(PR.translation_part)
    ape.process_data((ref_e, est_e))
    s = ape.get_all_statistics()
    m = evaluate_trajectories(gt, est)
    for ours, theirs in (("rmse", "rmse"), ("mean", "mean"), ("median", "median"), ("std", "std"),
                         ("max", "max")):
        assert m[f"ate_trans_{ours}_m"] == pytest.approx(s[theirs], abs=1e-9)


@pytest.mark.parametrize("delta", [1.0, 10.0])
def test_rpe_equals_evo_all_pairs_by_path(rng, delta):
    gt = random_trajectory(rng, n=400)
    est = perturb(rng, gt, 0.05, 0.01)
    res = relative_pose_errors(gt.poses, est.poses, delta)
    for relation, ours in ((PR.translation_part, res.trans_m), (PR.rotation_angle_deg, res.rot_deg)):
        rpe = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.meters, all_pairs=True,
                              pairs_from_reference=True, rel_delta_tol=0.1)
        rpe.process_data((to_evo(gt), to_evo(est)))
        assert list(res.j) == rpe.delta_ids
        np.testing.assert_allclose(ours, rpe.error, atol=1e-9)


def test_rpe_pairs_with_stops_pick_first_index_on_ties(rng):
    # a robot standing still repeats positions: distance plateaus must pair like evo (first index)
    gt = random_trajectory(rng, n=200, speed=1.0)
    poses = gt.poses.copy()
    poses[50:80] = poses[50]
    poses[120:150] = poses[120]
    gt = Trajectory(gt.stamps, poses)
    i, j = pairs_by_path_distance(gt.positions, 2.0)
    rpe = evo_metrics.RPE(PR.translation_part, delta=2.0, delta_unit=evo_metrics.Unit.meters, all_pairs=True,
                          pairs_from_reference=True)
    rpe.process_data((to_evo(gt), to_evo(gt)))
    assert list(j) == rpe.delta_ids
    assert np.all(j > i)


def test_rpe_skips_deltas_longer_than_path(rng):
    gt = random_trajectory(rng, n=100, speed=1.0)  # ~10 m
    est = perturb(rng, gt, 0.02, 0.0)
    assert relative_pose_errors(gt.poses, est.poses, 100.0) is None
    m = evaluate_trajectories(gt, est, rpe_deltas_m=(1.0, 100.0))
    assert m["rpe_1m_pairs"] > 50
    assert m["rpe_100m_pairs"] is None and m["rpe_100m_trans_rmse_m"] is None
    assert any("RPE 100 m skipped" in n for n in m["notes"])


def test_rpe_is_invariant_to_a_global_transform_and_zero_for_a_perfect_estimate(rng):
    gt = random_trajectory(rng, n=300)
    T = offset_T(rng)
    moved = Trajectory(gt.stamps, T @ gt.poses)
    res = relative_pose_errors(gt.poses, moved.poses, 10.0)
    assert res is not None and len(res.i) > 100
    assert res.trans_m.max() < 1e-9 and res.rot_deg.max() < 1e-6
    ate = absolute_pose_errors(gt.poses, moved.poses, align=True)
    assert ate.trans_m.max() < 1e-9 and ate.full.max() < 1e-9
    np.testing.assert_allclose(ate.T_align @ T, np.eye(4), atol=1e-9)  # T_gt_est undoes the offset


def test_umeyama_recovers_transform_and_matches_evo(rng):
    from evo.core.geometry import umeyama_alignment as evo_umeyama

    src = rng.normal(0, 10, (50, 3))
    T = offset_T(rng)
    dst = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.01, (50, 3))
    ours = umeyama_alignment(src, dst)
    r, t, _ = evo_umeyama(src.T, dst.T, False)
    np.testing.assert_allclose(ours[:3, :3], r, atol=1e-12)
    np.testing.assert_allclose(ours[:3, 3], t, atol=1e-9)
    np.testing.assert_allclose(ours, T, atol=0.02)


def test_association_matches_evo_with_jitter_and_missing_stamps(rng):
    gt = random_trajectory(rng, n=500, dt=0.1)
    keep = np.sort(rng.choice(500, 350, replace=False))  # 150 estimates missing
    stamps = gt.stamps[keep] + rng.uniform(-0.03, 0.03, len(keep))
    est = Trajectory(stamps, gt.poses[keep])
    i_gt, i_est = associate(gt.stamps, est.stamps, 0.02)
    # each matched at most once, within the tolerance, and exactly the in-tolerance jitters
    assert len(np.unique(i_gt)) == len(i_gt) and len(np.unique(i_est)) == len(i_est)
    assert np.all(np.abs(gt.stamps[i_gt] - est.stamps[i_est]) <= 0.02)
    expected = np.flatnonzero(np.abs(stamps - gt.stamps[keep]) <= 0.02)
    np.testing.assert_array_equal(i_est, expected)
    np.testing.assert_array_equal(i_gt, keep[expected])
    ref_e, est_e = sync.associate_trajectories(to_evo(gt), to_evo(est), max_diff=0.02)
    assert ref_e.num_poses == len(i_gt)
    np.testing.assert_array_equal(est_e.timestamps, est.stamps[i_est])
    np.testing.assert_array_equal(ref_e.timestamps, gt.stamps[i_gt])
