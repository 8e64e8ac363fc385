"""`blockloc eval` end to end in a subprocess: JSON equals evo's APE; bad input is one line."""

from __future__ import annotations

import copy
import json
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

evo_metrics = pytest.importorskip("evo.core.metrics")
from evo.core import sync  # noqa: E402
from evo.tools import file_interface  # noqa: E402

from blockloc.trajectory_io import write_tum  # noqa: E402
from blockloc.geometry import Trajectory  # noqa: E402


def blockloc(*args: str) -> subprocess.CompletedProcess:
    exe = shutil.which("blockloc")
    cmd = [exe] if exe else [sys.executable, "-m", "blockloc.cli"]
    return subprocess.run(cmd + list(args), capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def tum_pair(tmp_path_factory):
    rng = np.random.default_rng(7)
    n = 300
    yaw = np.cumsum(rng.normal(0, 0.08, n))
    pos = np.cumsum(np.stack([np.cos(yaw), np.sin(yaw), rng.normal(0, 0.05, n)], 1) * 0.12, 0)
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, :3, :3] = Rotation.from_euler("xyz", np.stack([rng.normal(0, .05, n), rng.normal(0, .05, n), yaw], 1)
                                        ).as_matrix()
    gt[:, :3, 3] = pos
    est = gt.copy()
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0, 0.02, (n, 3))).as_matrix()
    est[:, :3, 3] += rng.normal(0, 0.1, (n, 3))
    offset = np.eye(4)
    offset[:3, :3] = Rotation.from_euler("z", 0.3).as_matrix()
    offset[:3, 3] = [2.0, -1.0, 0.5]
    est = offset @ est
    t = 1e9 + 0.1 * np.arange(n)
    d = tmp_path_factory.mktemp("cli_eval")
    write_tum(d / "gt.tum", Trajectory(t, gt))
    write_tum(d / "est.tum", Trajectory(t + rng.uniform(-0.005, 0.005, n), est))
    return d / "gt.tum", d / "est.tum"


def evo_rmse(gt_path, est_path, relation, align):
    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.02)
    if align:
        est = copy.deepcopy(est)
        est.align(ref)
    ape = evo_metrics.APE(relation)
    ape.process_data((ref, est))
    return ape.get_statistic(evo_metrics.StatisticsType.rmse)


def plain_rpe(gt_path, est_path, delta_m, rel_tol=0.1):
    """RPE written out from its definition, independent of blockloc: the TUM files read with
    numpy (t x y z qx qy qz qw), rows matched by index (the stamps differ by < 5 ms), for each
    i the first j > i whose ground-truth path distance from i is nearest to ``delta_m``, kept
    when within ``rel_tol * delta_m``; error E = inv(inv(G_i) G_j) inv(P_i) P_j.
    Returns (pairs, translation RMSE m, rotation RMSE deg)."""
    def poses(path):
        rows = np.loadtxt(path, comments="#")
        T = np.tile(np.eye(4), (len(rows), 1, 1))
        T[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()  # scalar last, as TUM
        T[:, :3, 3] = rows[:, 1:4]
        return T

    G, P = poses(gt_path), poses(est_path)
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1))])
    trans, rot = [], []
    for i in range(len(G) - 1):
        gaps = [abs(d[j] - d[i] - delta_m) for j in range(i + 1, len(G))]
        j = i + 1 + int(np.argmin(gaps))
        if gaps[j - i - 1] > rel_tol * delta_m:
            continue
        E = np.linalg.inv(np.linalg.inv(G[i]) @ G[j]) @ (np.linalg.inv(P[i]) @ P[j])
        trans.append(np.linalg.norm(E[:3, 3]))
        rot.append(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude()))
    return len(trans), float(np.sqrt(np.mean(np.square(trans)))), float(np.sqrt(np.mean(np.square(rot))))


@pytest.mark.parametrize("align", [False, True])
def test_eval_json_equals_evo_ape(tum_pair, align):
    gt, est = tum_pair
    res = blockloc("eval", "--gt", str(gt), "--est", str(est), "--json", *(["--align"] if align else []))
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 1
    m = json.loads(lines[0])
    PR = evo_metrics.PoseRelation
    assert m["matched"] == 300 and m["aligned"] is align
    assert m["ate_trans_rmse_m"] == pytest.approx(evo_rmse(gt, est, PR.translation_part, align), abs=1e-6)
    assert m["ate_full_rmse"] == pytest.approx(evo_rmse(gt, est, PR.full_transformation, align), abs=1e-6)
    assert m["ate_rot_rmse_deg"] == pytest.approx(evo_rmse(gt, est, PR.rotation_angle_deg, align), abs=1e-6)
    for delta in (1.0, 10.0):
        pairs, trans_rmse, rot_rmse = plain_rpe(gt, est, delta)
        key = f"rpe_{delta:g}m"
        assert m[f"{key}_pairs"] == pairs > 10
        assert m[f"{key}_trans_rmse_m"] == pytest.approx(trans_rmse, rel=1e-9)
        assert m[f"{key}_rot_rmse_deg"] == pytest.approx(rot_rmse, rel=1e-9)
    assert m["rpe_100m_pairs"] is None  # the path is ~36 m


def test_eval_table_and_plots(tum_pair, tmp_path):
    gt, est = tum_pair
    res = blockloc("eval", "--gt", str(gt), "--est", str(est), "--plot", str(tmp_path / "p"))
    assert res.returncode == 0, res.stderr
    assert "ATE" in res.stdout and "RPE" in res.stdout
    assert (tmp_path / "p" / "trajectories.png").stat().st_size > 0
    assert (tmp_path / "p" / "errors.png").stat().st_size > 0


def test_eval_bad_file_is_one_line_without_traceback(tum_pair, tmp_path):
    gt, _ = tum_pair
    bad = tmp_path / "bad.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n0.1 0 0 0 0 1\n")
    res = blockloc("eval", "--gt", str(gt), "--est", str(bad), "--json")
    assert res.returncode != 0
    assert res.stdout == ""
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in res.stderr
    assert str(bad) in err[0] and ":2:" in err[0] and "expected 8 numbers" in err[0]
    res = blockloc("eval", "--gt", str(tmp_path / "missing.tum"), "--est", str(gt))
    assert res.returncode != 0 and len(res.stderr.strip().splitlines()) == 1
    assert "missing.tum" in res.stderr and "Traceback" not in res.stderr


def test_eval_options_interpolate_and_rpe_deltas(tum_pair):
    gt, est = tum_pair
    res = blockloc("eval", "--gt", str(gt), "--est", str(est), "--json", "--interpolate", "--rpe-deltas", "2,5")
    assert res.returncode == 0, res.stderr
    m = json.loads(res.stdout)
    assert m["association"] == "interpolated" and m["rpe_deltas_m"] == [2.0, 5.0]
    assert m["rpe_5m_pairs"] > 0 and "rpe_10m_pairs" not in m
    res = blockloc("eval", "--gt", str(gt), "--est", str(est), "--rpe-deltas", "a")
    assert res.returncode != 0 and res.stderr.strip().startswith("error: --rpe-deltas 'a'")


def test_eval_breaks_a_planted_lag_and_offset_down(tmp_path):
    """`blockloc eval` on an estimate 50 ms late and 5 cm off in x on a circle: the JSON, the
    tables and the plot say so."""
    t = 1e9 + 0.1 * np.arange(400)
    th = 4 * np.pi * np.arange(len(t)) / len(t)  # two whole turns of a 16 m circle at 5.03 m/s
    gt = np.tile(np.eye(4), (len(t), 1, 1))
    gt[:, :3, :3] = Rotation.from_euler("z", (th + np.pi / 2)[:, None]).as_matrix()
    gt[:, :3, 3] = np.stack([16 * np.cos(th), 16 * np.sin(th), np.zeros_like(th)], 1)
    gt_traj = Trajectory(t, gt)
    est = gt_traj.interpolate(t - 0.05)
    est[:, 0, 3] += 0.05
    write_tum(tmp_path / "gt.tum", gt_traj)
    write_tum(tmp_path / "est.tum", Trajectory(t, est))
    res = blockloc("eval", "--gt", str(tmp_path / "gt.tum"), "--est", str(tmp_path / "est.tum"), "--json")
    assert res.returncode == 0, res.stderr
    m = json.loads(res.stdout)
    assert m["err_time_shift_s"] == pytest.approx(0.05, abs=2e-3)
    assert m["err_offset_m"][0] == pytest.approx(0.05, abs=5e-3)
    assert m["err_along_mean_m"] == pytest.approx(-0.05 * 1.6 * np.pi, abs=5e-3)
    assert [r["lo"] for r in m["err_by_speed"]] == [4.0] and m["err_by_speed"][0]["count"] == m["matched"]
    res = blockloc("eval", "--gt", str(tmp_path / "gt.tum"), "--est", str(tmp_path / "est.tum"),
                   "--plot", str(tmp_path / "plots"))
    assert res.returncode == 0, res.stderr
    text = " ".join(res.stdout.split())
    assert re.search(r"time shift that best explains the along-track error: \+0\.0(49|50)\d s", text), text
    assert "constant offset (mean error, map frame): [+0.05" in text
    assert "error against speed" in text and "error against turn rate" in text
    assert (tmp_path / "plots" / "error_breakdown.png").stat().st_size > 10_000
