"""blockloc.maps.pose_refine: the mapping poses refined against the drive's scans (issue 41).

The graph is checked with an engine that "registers" a pair by returning the true LiDAR motion
plus a little noise (what a perfect scan matcher would): the smooth input error must shrink where
the drive revisits a place, the mounting's rotation must come out of it, and a drive with no
revisit must come back untouched. The local maps (several keyframes' scans placed by the current
poses) are checked with a point-to-point matcher on a sparse landmark world, where a scan's
points are noisy: a local map of several scans averages the noise that scan-to-scan registration
keeps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from blockloc.geometry import inv_T, make_T, so3_exp, so3_log
from blockloc.maps.pose_refine import (choose_refine_pairs, corrected_poses, refine_poses,
                                       registrations_to_local_maps)


@dataclass
class _Result:
    T_target_source: np.ndarray
    converged: bool = True
    fitness: float = 0.9


class TruthEngine:
    """Registers keyframe j onto i as the truth says (clouds are the keyframe index), with
    ``noise_m`` / ``noise_rad`` of Gaussian error per pair."""

    def __init__(self, T_map_lidar_true, noise_m=0.002, noise_rad=0.0002, seed=0):
        self.T = T_map_lidar_true
        self.rng = np.random.default_rng(seed)
        self.noise = (noise_m, noise_rad)
        self.calls = 0

    def build_target(self, points):
        return int(points[0, 0])

    def align(self, target, source, guess):
        self.calls += 1
        j = int(source[0, 0])
        B = inv_T(self.T[target]) @ self.T[j]
        d = make_T(so3_exp(self.rng.normal(0, self.noise[1], 3)), self.rng.normal(0, self.noise[0], 3))
        return _Result(B @ d)


def _square_drive(laps, side=30.0, step=1.0, dt=1.0):
    """Body poses (K, 4, 4) along a square driven ``laps`` times, heading along the road; stamps (K,)."""
    corners = np.array([[0, 0], [side, 0], [side, side], [0, side], [0, 0]], float)
    pts, yaw = [], []
    for _ in range(laps):
        for a, b in zip(corners[:-1], corners[1:]):
            n = int(round(np.linalg.norm(b - a) / step))
            for s in range(n):
                pts.append(a + (b - a) * s / n)
                yaw.append(np.arctan2(*(b - a)[::-1]))
    T = np.stack([make_T(so3_exp([0, 0, y]), [p[0], p[1], 0.0]) for p, y in zip(pts, yaw)])
    return T, np.arange(len(T)) * dt


def _smooth_error(stamps, sigma_m, sigma_rad, seed, knot_s=2.0):
    """Right-multiplied body-frame errors (K, 4, 4): a cubic spline through Gaussian knots, as the
    simulator's offline-SLAM error."""
    from scipy.interpolate import CubicSpline

    rng = np.random.default_rng(seed)
    knots = np.arange(stamps[0] - knot_s, stamps[-1] + 2 * knot_s, knot_s)
    e = CubicSpline(knots, rng.normal(0, 1, (len(knots), 6)))(stamps)
    return np.stack([make_T(so3_exp(r * sigma_rad), t * sigma_m) for r, t in zip(e[:, :3], e[:, 3:])])


def _rmse(T, G):
    return float(np.sqrt(((T[:, :3, 3] - G[:, :3, 3]) ** 2).sum(axis=1).mean()))


X_NOMINAL = make_T(so3_exp([0.0, 0.0, np.pi / 2]), [0.1, 0.0, 1.0])


def test_refinement_shrinks_a_smooth_pose_error_where_the_drive_revisits_and_finds_the_mounting():
    G, t = _square_drive(laps=2)
    X_true = make_T(so3_exp(np.deg2rad([0.0, 0.0, 0.3])), [0.015, 0.0, 0.0]) @ X_NOMINAL  # 1.5 cm forward
    S = G @ _smooth_error(t, 0.03, 0.002, seed=1)
    engine = TruthEngine(G @ X_true)
    clouds = [np.array([[k, 0.0, 0.0]]) for k in range(len(G))]
    r = refine_poses(S, t, clouds, X_NOMINAL, engine, local_span=0)
    assert r.skipped is None and r.loop_pairs > 50 and r.odometry_pairs == 2 * len(G) - 3
    before, after = _rmse(S, G), _rmse(r.T_map_body, G)
    assert before > 0.03 and after < 0.4 * before, (before, after)
    yaw_err = lambda X: np.rad2deg(abs(so3_log(X[:3, :3] @ X_true[:3, :3].T)[2]))  # noqa: E731
    assert yaw_err(X_NOMINAL) == pytest.approx(0.3) and yaw_err(r.T_body_lidar) < 0.1
    assert r.as_dict()["loop_pairs"] == r.loop_pairs and r.shift_m.max() > 0.02
    # the forward translation shows in the turns: from exact poses it is found (from these smooth
    # 3 cm errors over only 8 corners it moved 6 of the 15 mm); y and z are held
    r = refine_poses(G, t, clouds, X_NOMINAL, TruthEngine(G @ X_true), local_span=0)
    assert abs(r.T_body_lidar[0, 3] - X_true[0, 3]) < 0.002, r.T_body_lidar[:3, 3] - X_true[:3, 3]
    np.testing.assert_allclose(r.T_body_lidar[1:3, 3], X_NOMINAL[1:3, 3], atol=1e-3)


def test_a_held_mounting_stays_and_a_drive_without_revisits_comes_back_untouched():
    G, t = _square_drive(laps=2)
    S = G @ _smooth_error(t, 0.03, 0.002, seed=2)
    clouds = [np.array([[k, 0.0, 0.0]]) for k in range(len(G))]
    r = refine_poses(S, t, clouds, X_NOMINAL, TruthEngine(G @ X_NOMINAL), mounting_sigma_rad=1e-6,
                     mounting_sigma_m=1e-4, local_span=0)
    assert r.skipped is None and _rmse(r.T_map_body, G) < 0.5 * _rmse(S, G)
    assert np.rad2deg(np.linalg.norm(so3_log(r.T_body_lidar[:3, :3] @ X_NOMINAL[:3, :3].T))) < 1e-3
    np.testing.assert_allclose(r.T_body_lidar[:3, 3], X_NOMINAL[:3, 3], atol=1e-4)
    # one lap without closing it (the last side stops short): no place is seen twice
    G1, t1 = G[:100], t[:100]
    S1 = S[:100]
    engine = TruthEngine(G1 @ X_NOMINAL)
    r = refine_poses(S1, t1, clouds, X_NOMINAL, engine, local_span=0)
    assert r.skipped.startswith("no revisit") and r.loop_pairs == 0
    np.testing.assert_array_equal(r.T_map_body, S1)
    np.testing.assert_array_equal(r.T_body_lidar, X_NOMINAL)
    assert r.as_dict() == {"skipped": r.skipped, "tried_pairs": r.tried_pairs}


def test_the_jackknife_of_the_mounting_x_shows_how_well_the_revisits_determine_it():
    # issue 41: x is read from the input poses at the revisits; their smooth error is what the
    # jackknife's spread must show (exact poses, exact registrations: none), without changing the
    # estimate itself
    G, t = _square_drive(laps=2)
    X_true = make_T(so3_exp(np.deg2rad([0.0, 0.0, 0.3])), [0.015, 0.0, 0.0]) @ X_NOMINAL
    clouds = [np.array([[k, 0.0, 0.0]]) for k in range(len(G))]
    exact = lambda: TruthEngine(G @ X_true, noise_m=0.0, noise_rad=0.0)  # noqa: E731
    S = G @ _smooth_error(t, 0.03, 0.002, seed=1)
    r = refine_poses(S, t, clouds, X_NOMINAL, exact(), local_span=0, jackknife_blocks=4)
    plain = refine_poses(S, t, clouds, X_NOMINAL, exact(), local_span=0)
    np.testing.assert_array_equal(r.T_body_lidar, plain.T_body_lidar)
    assert len(plain.mounting_x_jackknife_m) == 0 and np.isnan(plain.mounting_x_se_m)
    assert "mounting_x_se_m" not in plain.as_dict()
    x = r.mounting_x_jackknife_m
    assert len(x) == 4 and r.mounting_x_se_m == pytest.approx(np.sqrt(3 / 4 * ((x - x.mean()) ** 2).sum()))
    assert r.as_dict()["mounting_x_se_m"] == round(r.mounting_x_se_m, 4)
    from_truth = refine_poses(G, t, clouds, X_NOMINAL, exact(), local_span=0, jackknife_blocks=4)
    assert from_truth.mounting_x_se_m < 1e-4 and r.mounting_x_se_m > 1e-3, (from_truth.mounting_x_se_m,
                                                                            r.mounting_x_se_m)
    # each leave-one-out is a whole refinement without that run of revisits
    _, loops = choose_refine_pairs(S, t)
    run = np.array_split(loops[np.argsort(t[loops[:, 1]], kind="stable")], 4)[3]
    alone = refine_poses(S, t, clouds, X_NOMINAL, exact(), local_span=0, revisits_left_out=run)
    assert alone.loop_pairs == len(loops) - len(run) and alone.T_body_lidar[0, 3] == pytest.approx(x[3], abs=1e-9)


def test_revisit_pairs_need_the_time_gap_and_the_radius():
    G, t = _square_drive(laps=2)
    odometry, loops = choose_refine_pairs(G, t, odometry_span=2, loop_radius_m=6.0, loop_min_gap_s=10.0)
    assert len(odometry) == 2 * len(G) - 3 and (odometry[:, 1] - odometry[:, 0] <= 2).all()
    assert len(loops) > 0 and (np.abs(t[loops[:, 1]] - t[loops[:, 0]]) >= 10.0).all()
    d = np.linalg.norm(G[loops[:, 0], :3, 3] - G[loops[:, 1], :3, 3], axis=1)
    assert (d <= 6.0).all()
    # every keyframe of the second lap finds its twin from the first (exactly 120 s earlier)
    assert {(i, i + 120) for i in range(120)} <= set(map(tuple, loops.tolist()))
    _, none = choose_refine_pairs(G, t, loop_min_gap_s=1e6)
    assert len(none) == 0


def test_local_maps_are_the_neighbours_and_the_other_pass():
    regs, is_loop = registrations_to_local_maps(6, np.array([[0, 5]]), 2)
    assert regs[:6] == [(0, (1, 2), 0), (1, (0, 2, 3), 1), (2, (0, 1, 3, 4), 2), (3, (1, 2, 4, 5), 3),
                        (4, (2, 3, 5), 4), (5, (3, 4), 5)]
    # the revisit: the later keyframe against the other pass's local map, the earlier one included
    assert regs[6:] == [(5, (0, 1, 2), 0)] and is_loop.tolist() == [False] * 6 + [True]
    assert len(registrations_to_local_maps(1, np.zeros((0, 2)), 2)[0]) == 0  # one keyframe: nothing


class LandmarkEngine:
    """Point-to-point ICP (nearest neighbour, Kabsch) on landmarks far apart: a matcher whose only
    error is the points' own noise."""

    def build_target(self, points):
        from scipy.spatial import cKDTree

        return np.asarray(points, float), cKDTree(points)

    def align(self, target, source, guess):
        pts, tree = target
        T = np.asarray(guess, float).copy()
        for _ in range(8):
            moved = source @ T[:3, :3].T + T[:3, 3]
            d, idx = tree.query(moved, distance_upper_bound=0.5)
            ok = np.isfinite(d)
            a, b = source[ok], pts[idx[ok]]
            ca, cb = a.mean(0), b.mean(0)
            U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
            D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
            R = Vt.T @ D @ U.T
            T = make_T(R, cb - R @ ca)
        return _Result(T, True, float(ok.mean()))


def test_local_maps_see_more_of_each_place_than_one_scan_does():
    """Each scan sees a random 30% of the landmarks near it (a sparse scan): two scans share few,
    a local map of four shares most with the scan registered against it."""
    G, t = _square_drive(laps=2, side=20.0)
    rng = np.random.default_rng(5)
    world = np.c_[rng.uniform(-12, 32, (1500, 2)), rng.uniform(0, 4, 1500)]
    clouds = []
    for L in G @ X_NOMINAL:  # LiDAR frame, 3 cm noise a point
        near = world[(np.linalg.norm(world[:, :2] - L[:2, 3], axis=1) < 12.0) & (rng.random(len(world)) < 0.3)]
        clouds.append((near - L[:3, 3]) @ L[:3, :3] + rng.normal(0, 0.03, near.shape))
    S = G @ _smooth_error(t, 0.03, 0.002, seed=3)
    held = {"mounting_sigma_rad": 1e-6, "mounting_sigma_m": 1e-4}
    pairwise = refine_poses(S, t, clouds, X_NOMINAL, LandmarkEngine(), local_span=0, **held)
    local = refine_poses(S, t, clouds, X_NOMINAL, LandmarkEngine(), local_span=2, local_rounds=2, **held)
    assert local.skipped is None and local.odometry_pairs == len(G) and local.loop_pairs > 50
    before, after_pairwise, after_local = _rmse(S, G), _rmse(pairwise.T_map_body, G), _rmse(local.T_map_body, G)
    # measured: 4.7 -> 2.0 (scan to scan) / 1.8 cm (local maps)
    assert after_local < 0.4 * before and after_local < after_pairwise, (before, after_pairwise, after_local)


def test_corrected_poses_move_the_keyframes_where_refined_and_interpolate_between():
    G, t = _square_drive(laps=1)
    key = np.arange(0, len(G), 5)
    after = G[key] @ np.stack([make_T(so3_exp([0, 0, 0.001 * k]), [0.01 * k, 0, 0]) for k in range(len(key))])
    fine_t = np.linspace(t[0] - 3, t[-1] + 3, 1000)
    from blockloc.geometry import Trajectory

    fine = Trajectory(t, G).interpolate(fine_t)
    out = corrected_poses(fine_t, fine, t[key], G[key], after)
    at_key = corrected_poses(t[key], G[key], t[key], G[key], after)
    np.testing.assert_allclose(at_key, after, atol=1e-9)
    # between two keyframes the correction is between theirs (x grows 1 cm per keyframe)
    mid = corrected_poses(t[key[:2]].mean(keepdims=True), Trajectory(t, G).interpolate(t[key[:2]].mean(keepdims=True)),
                          t[key], G[key], after)
    assert 0.0 < (inv_T(Trajectory(t, G).interpolate(t[key[:2]].mean(keepdims=True))[0]) @ mid[0])[0, 3] < 0.01
    # held beyond the ends
    D_first = inv_T(fine[0]) @ out[0]
    np.testing.assert_allclose(D_first, np.eye(4), atol=1e-9)


def _blockloc(*args):
    """``blockloc ARGS`` as a user types it (a subprocess of the console script's module)."""
    import os
    import subprocess
    import sys

    # a terminal wide enough that `map info`'s table does not wrap a line
    return subprocess.run([sys.executable, "-m", "blockloc.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=900, env={**os.environ, "COLUMNS": "400"})


def _session(path, waypoints, wander_m):
    """An NCLT-layout session of the synthetic world driven along ``waypoints``, whose ground truth
    (the poses a map is built from) wanders ``wander_m`` around the truth, smoothly."""
    from blockloc.datasets.base import ImuData
    from blockloc.datasets.nclt import NCLT_T_BODY_IMU, NCLT_T_BODY_LIDAR, write_session
    from blockloc.geometry import Trajectory

    from .synthetic import MemorySequence, route, world_points

    world = world_points(extent=(-20, 40), seed=3, density=0.4)
    traj = route(waypoints, speed=4.0)
    seq = MemorySequence(world, traj, radius=20.0, T_body_lidar=np.asarray(NCLT_T_BODY_LIDAR, float))
    t = traj.stamps - traj.stamps[0]
    wander = traj.poses.copy()
    wander[:, 0, 3] += wander_m * np.sin(2 * np.pi * t / 9.0)
    wander[:, 1, 3] += wander_m * np.cos(2 * np.pi * t / 7.0)
    f_imu = np.asarray(NCLT_T_BODY_IMU, float)[:3, :3].T @ np.array([0.0, 0.0, -9.81])  # at rest
    imu = ImuData(traj.stamps, np.tile(f_imu, (len(traj), 1)), np.zeros((len(traj), 3)))
    write_session(path, date="2012-01-15", frames=seq.frames(), imu=imu,
                  ground_truth=Trajectory(traj.stamps, wander))


def test_map_build_refine_poses_from_the_command_line(tmp_path):
    """`map build --refine-poses`: a drive that closes its loop is refined (the manifest and
    `map info` say with how many pairs); a drive that never sees a place twice is left as it came
    (a warning; `map info` says why); a global PCD is refused naming the option."""
    from blockloc.maps.store import open_map

    _session(tmp_path / "loop", [[0, 0], [20, 0], [20, 20], [0, 20], [0, 0], [10, 0]], wander_m=0.04)
    res = _blockloc("map", "build", "--seq", tmp_path / "loop", "--kind", "block", "--block-size", "20",
                    "--nominal-mounting", "--refine-poses", "--out", tmp_path / "m")
    assert res.returncode == 0, res.stderr
    (r,) = open_map(tmp_path / "m").params["pose_refinement"].values()
    assert r["loop_pairs"] > 5 and r["odometry_pairs"] > 50 and r["shift_max_m"] > 0.01, r
    from typer.testing import CliRunner

    from blockloc.cli import app

    runner = CliRunner(env={"COLUMNS": "400"})
    info = " ".join(runner.invoke(app, ["map", "info", str(tmp_path / "m")]).output.split())
    assert f"refined against the drive's scans ({r['odometry_pairs']} neighbour and {r['loop_pairs']} revisit" in info

    _session(tmp_path / "line", [[0, 0], [12, 0]], wander_m=0.04)
    res = runner.invoke(app, ["map", "build", "--seq", str(tmp_path / "line"), "--kind", "block",
                              "--nominal-mounting", "--refine-poses", "--out", str(tmp_path / "l")])
    assert res.exit_code == 0, res.output
    (r,) = open_map(tmp_path / "l").params["pose_refinement"].values()
    assert r["skipped"].startswith("no revisit")
    info = " ".join(runner.invoke(app, ["map", "info", str(tmp_path / "l")]).output.split())
    assert f"mapping poses │ {tmp_path / 'line'}: as given (no revisit" in info, info

    res = runner.invoke(app, ["map", "build", "--from-pcd", str(tmp_path / "g.pcd"), "--poses",
                              str(tmp_path / "p.tum"), "--refine-poses", "--out", str(tmp_path / "g")])
    assert "--refine-poses needs --seq" in str(res.exception) and not (tmp_path / "g").exists()


def test_a_build_with_an_estimated_mounting_estimates_it_again_with_the_refined_poses(tmp_path):
    """In the build (in process, the synthetic loop): the hand-eye step estimates the mounting, the
    refinement estimates its rotation and forward translation again with the poses, and the
    manifest's mounting (what `track` takes) is the refined one, marked so."""
    from blockloc.datasets.base import RemountedSequence
    from blockloc.datasets.nclt import NCLT_T_BODY_LIDAR
    from blockloc.geometry import Trajectory
    from blockloc.maps.build_plan import build_map_from_drives
    from blockloc.maps.build_tasks import Drive
    from blockloc.maps.mounting import map_mounting

    from .synthetic import MemorySequence, route, world_points

    X_nominal = np.asarray(NCLT_T_BODY_LIDAR, float)
    X_true = make_T(so3_exp(np.deg2rad([0.0, 0.0, 0.3])), [0.02, 0.0, 0.0]) @ X_nominal
    traj = route([[0, 0], [20, 0], [20, 20], [0, 20], [0, 0], [10, 0]], speed=4.0)
    inner = MemorySequence(world_points(extent=(-20, 40), seed=3, density=0.4), traj, radius=20.0, T_body_lidar=X_true)
    t = traj.stamps - traj.stamps[0]
    wander = traj.poses.copy()
    wander[:, 0, 3] += 0.02 * np.sin(2 * np.pi * t / 9.0)
    inner.mapping_poses = lambda: Trajectory(traj.stamps, wander)
    seq = RemountedSequence(inner, X_nominal)  # the drawing says nominal; the scans say otherwise
    store = build_map_from_drives([Drive.of(seq)], "block", tmp_path / "m", block_size_m=20.0,
                                  calibrate_mounting=True, refine_poses=True,
                                  mounting_translation_tolerance_m=0.0005)
    (m,) = store.params["mounting"].values()
    (r,) = store.params["pose_refinement"].values()
    assert m["refined_with_poses"] is True and r["loop_pairs"] > 5, (m, r)
    X = map_mounting(store.params)
    np.testing.assert_allclose(X, np.asarray(m["T_body_lidar"]), atol=1e-9)
    assert abs(X[0, 3] - X_true[0, 3]) < abs(X_nominal[0, 3] - X_true[0, 3]) / 2, (X[:3, 3], X_true[:3, 3])
    assert np.rad2deg(np.linalg.norm(so3_log(X[:3, :3] @ X_true[:3, :3].T))) < 0.1
    np.testing.assert_allclose(m["translation_m"], (X[:3, 3] - X_nominal[:3, 3]).round(4), atol=1e-9)


def test_the_default_refines_the_drives_whose_mounting_the_build_estimated(tmp_path):
    """`map.refine_poses` true (the default) is auto: a body-pose drive whose mounting the build
    estimated is refined; with the mounting left nominal (`--nominal-mounting`, as for a drive with
    LiDAR poses) the poses are left as they came and the manifest says why."""
    from blockloc.maps.store import open_map

    _session(tmp_path / "loop", [[0, 0], [20, 0], [20, 20], [0, 20], [0, 0], [10, 0]], wander_m=0.04)
    res = _blockloc("map", "build", "--seq", tmp_path / "loop", "--kind", "block", "--block-size", "20",
                    "--out", tmp_path / "m")
    assert res.returncode == 0, res.stderr
    store = open_map(tmp_path / "m")
    (src,) = store.params["mounting_source"].values()
    (r,) = store.params["pose_refinement"].values()
    assert src["source"] == "estimated", src
    assert "skipped" not in r and r["loop_pairs"] > 5, r
    res = _blockloc("map", "build", "--seq", tmp_path / "loop", "--kind", "block", "--block-size", "20",
                    "--nominal-mounting", "--out", tmp_path / "n")
    assert res.returncode == 0, res.stderr
    (r,) = open_map(tmp_path / "n").params["pose_refinement"].values()
    assert r["skipped"].startswith("poses of the LiDAR or mounting not estimated"), r
