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
