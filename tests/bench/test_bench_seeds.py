"""bench.seeds' report: the table rows and the issue targets it checks (no run: metrics given)."""

from bench.seeds import report


def _m(ate, rot, along, failures=0):
    return {"ate_trans_rmse_m": ate, "ate_trans_max_m": 2 * ate, "ate_rot_rmse_deg": rot,
            "err_along_mean_m": along, "err_along_rms_m": abs(along) + 0.01, "err_cross_rms_m": 0.02,
            "err_vertical_rms_m": 0.01, "err_time_shift_s": -0.01, "failures": failures,
            "estimated": 100, "frames": 100, "_build_s": 30.0}


def test_the_targets_are_checked_on_the_default_run_over_every_seed(tmp_path):
    met = report({1: {"default": _m(0.025, 0.1, 0.004)}, 2: {"default": _m(0.03, 0.12, -0.008),
                                                              "nominal": _m(0.09, 0.5, 0.05)}},
                 ["--seeds", "1,2"], "now", 1.0, tmp_path)
    assert "| 2 | nominal | 0.090 | 0.180 | 0.500 | +5.0 |" in met
    assert "ATE median 0.028 m, worst 0.030 m" in met
    assert "Issue targets on `default`: median ATE <= 0.03 m: met; worst ATE <= 0.035 m: met" in met
    assert "along-track mean within +-1 cm (every seed): met" in met
    missed = report({1: {"default": _m(0.025, 0.2, 0.004)}, 2: {"default": _m(0.04, 0.1, 0.02, failures=1)}},
                    [], "now", 1.0, tmp_path)
    assert "worst ATE <= 0.035 m: **not met**" in missed and "rotation <= 0.15 deg (every seed): **not met**" in missed
    assert "no failures: **not met**" in missed and "within +-1 cm (every seed): **not met**" in missed
    assert "seed 1: default 30 s" in missed
    # a build timed with its CPU time and load; the map's mounting translation axes in the row
    timed = report({3: {"default": {**_m(0.03, 0.1, 0.0), "_build_s": [50.0, 41.0, 12.5], "_translation": "nominal"}}},
                   [], "now", 1.0, tmp_path)
    assert "seed 3: default 50 s (CPU 41 s, load 12.5)" in timed and "| 100/100 | nominal |" in timed


def test_bench_passes_a_named_benchmarks_options_to_it(monkeypatch):
    import bench.__main__ as bm

    calls = []
    monkeypatch.setattr(bm.subprocess, "call", lambda cmd, cwd: calls.append(cmd[2:]) or 0)
    monkeypatch.setattr(bm, "assemble", lambda: "assembled")
    assert bm.main(["seeds", "--preset", "small", "--seeds", "1,2,3,4,5"]) == 0
    assert calls == [["bench.seeds", "--preset", "small", "--seeds", "1,2,3,4,5"]]
    assert bm.main(["seeds", "ndt", "--seeds", "1"]) == 2 and bm.main(["all", "--seeds", "1"]) == 2
    assert len(calls) == 1


def _drive(heading_deg: float, n: int = 201):
    """(n, 4, 4) body poses along the map x axis, 0.5 m apart, all heading ``heading_deg``."""
    import numpy as np

    from blockloc.geometry import make_T, so3_exp

    R = so3_exp(np.array([0.0, 0.0, np.deg2rad(heading_deg)]))
    return np.stack([make_T(R, np.array([0.5 * k, 0.0, 0.0])) for k in range(n)])


def test_a_mounting_translation_error_cancels_on_the_map_drives_heading_and_doubles_against_it():
    import numpy as np

    from bench.seeds import predicted_along_m

    X_true = np.eye(4)
    X_map = np.eye(4)
    X_map[0, 3] = 0.01  # the map built with the LiDAR 1 cm too far forward
    mapping = _drive(0.0)
    same = predicted_along_m(mapping, mapping, _drive(0.0)[40:160], X_map, X_true)
    back = predicted_along_m(mapping, mapping, _drive(180.0)[40:160], X_map, X_true)
    assert abs(same["mounting"]) < 1e-9 and same["opposite"] == 0.0
    # (R_map - R_loc) d = 2 cm along the map's +x, which is behind a body heading -x
    assert np.isclose(back["mounting"], -0.02) and back["opposite"] == 1.0
    assert np.isclose(back["both"], -0.02) and abs(back["slam"]) < 1e-9
    # tracked with the true mounting, the map's own error is left: 1 cm along +x, behind
    assert np.isclose(back["true_tracking"], -0.01) and np.isclose(same["true_tracking"], 0.01)
    # a SLAM error that moved the whole map drive 3 cm along +x moves the map with it
    slam = mapping.copy()
    slam[:, 0, 3] += 0.03
    moved = predicted_along_m(mapping, slam, _drive(180.0)[40:160], X_true, X_true)
    assert np.isclose(moved["slam"], -0.03) and np.isclose(moved["both"], -0.03) and abs(moved["mounting"]) < 1e-9


def test_the_explanation_table_sits_beside_the_measured_along_track_mean(tmp_path):
    import json

    e = {"predicted": {"both": 0.022, "mounting": 0.026, "slam": -0.004, "true_tracking": 0.011, "opposite": 1.0},
         "map_translation_minus_true_m": [-0.0116, 0.0012, 0.0048]}
    for name, t in (("slam_poses", -0.0176), ("true_poses", -0.0009)):
        e[name] = {"translation_solved_minus_true_m": [t, 0.004, 0.0], "rotation_minus_true_deg": [0.0, 0.0, -0.142],
                   "jackknife_m": [0.0097, 0.0065, None], "translation_estimated": ""}
    (tmp_path / "s1_explain.json").write_text(json.dumps(e))
    text = report({1: {"default": _m(0.037, 0.11, 0.028)}}, [], "now", 1.0, tmp_path)
    assert "| 1 | +2.8 | +2.2 | +2.6 | -0.4 | +1.1 | 100% opposite | -11.6, +1.2 | -17.6, +4.0 (-0.142; 9.7, 6.5) |" in text
    assert "| -0.9, +4.0 (-0.142; 9.7, 6.5) |" in text
    assert "--explain" not in report({2: {"default": _m(0.03, 0.1, 0.0)}}, [], "now", 1.0, tmp_path)


def test_the_refine_table_gives_the_mounting_x_jackknife_and_copes_with_an_older_cache():
    from bench.seeds import refine_table

    pose = {"rmse_m": 0.05, "along_rms_m": 0.03, "cross_rms_m": 0.03, "rot_rmse_deg": 0.2}
    e = {"keyframes": 200, "revisited_share": 0.5, "summary": {"odometry_pairs": 199, "loop_pairs": 80},
         "before": pose, "after": pose, "lidar_rmse_m": [0.05, 0.03], "mounting_x_minus_true_m": [0.0087, 0.0092],
         "predicted_along_m": [-0.018, -0.018], "refine_wall_s": 200.0, "refine_cpu_s": 60.0, "load": 20.0,
         "mounting_x_jackknife_minus_true_m": [0.0094, 0.0091, 0.0097, 0.0090, 0.0139, 0.0054]}
    row = refine_table({2: e}, {})[2]
    # sqrt(5/6 * sum (x - mean)^2) of the six leave-one-out values: 5.5 mm (seed 2's, 15:20 UTC)
    assert "| 5.5 (+9.4, +9.1, +9.7, +9.0, +13.9, +5.4) | 200 / 60 (20.0) |" in row, row
    old = {k: v for k, v in e.items() if k != "mounting_x_jackknife_minus_true_m"}
    assert "| - | 200 / 60 (20.0) |" in refine_table({2: old}, {})[2]
