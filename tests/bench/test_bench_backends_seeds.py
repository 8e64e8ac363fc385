"""bench.backends_seeds' report: a row per seed and run, then median and worst per run (no run: metrics given)."""

from bench.backends_seeds import RUNS, report


def _m(ate, rot=0.1, fail=0, along=0.004):
    return {"ate_trans_rmse_m": ate, "ate_trans_max_m": 2 * ate, "ate_rot_rmse_deg": rot, "failures": fail,
            "rejected": 0, "frames": 100, "err_along_mean_m": along}


def test_report_rows_and_summary():
    res = {s: {name: _m(0.02 + 0.01 * s + 0.001 * i, fail=int(name == "srt" and s == 3))
               for i, name in enumerate(RUNS)} for s in (1, 2, 3)}
    text = "\n".join(report(res, "small", 0, "python -m bench.backends_seeds --work W", "now", "box"))
    assert "| 2 | grid | 0.042 | 0.084 | 0.100 | +0.4 | 0 | 0 | 100 |" in text
    # grid over seeds 1-3: 0.032, 0.042, 0.052 -> median 0.042, worst 0.052
    assert "| grid | 0.042 | 0.052 | 0.100 | 0 |" in text
    assert "| srt | 0.043 | 0.053 | 0.100 | 1 |" in text
    assert "every frame" in text and "seeds 1, 2, 3" in text
