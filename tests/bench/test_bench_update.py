"""Helpers of the per-scan update benchmark (bench/update.py): the cProfile split by stage, the table
it writes, and the message when a world is missing. Not a run of the benchmark."""

from __future__ import annotations

import cProfile
import subprocess
import sys
from pathlib import Path

from bench import update


def test_profile_split_adds_up_cumulative_times_by_stage(monkeypatch):
    """A fake pstats table: registration's rest is its call minus the kernel's."""
    import pstats

    def entry(ct):
        return (1, 1, ct, ct, {})

    table = {("/x/blockloc/tracking/estimator.py", 1, "insert_frame"): entry(2.0),
             ("/x/blockloc/tracking/estimator.py", 2, "_register"): entry(1.0),
             ("/x/blockloc/registration/_ndt_kernels.py", 3, "ndt_level"): entry(0.75),
             ("/x/blockloc/tracking/estimator.py", 4, "_preprocess"): entry(0.25)}

    class FakeStats:
        def __init__(self, prof):
            self.stats = table

    monkeypatch.setattr(pstats, "Stats", FakeStats)
    split = update.profile_split(cProfile.Profile(), scans=10)
    assert split["insert_frame total"] == 200.0  # ms per scan
    assert split["registration: NDT kernel"] == 75.0
    assert split["registration: rest"] == 25.0
    assert split["scan prep"] == 25.0 and split["covariance"] == 0.0


def _seed(world: str, wall: float) -> dict:
    q = {"median": wall, "p90": wall + 1, "p99": wall + 2}
    return {"world": world, "timed": 100, "wall_ms": q, "thread_cpu_ms": q, "process_cpu_ms": q,
            "load_avg": {"start": 1.0, "end": 2.0}, "ate_trans_rmse_m": 0.0397, "ate_rot_rmse_deg": 0.1,
            "failures": 0, "stage_median_ms": {"prep_ms": None, "deskew_ms": 1.0, "map_ms": 0.2,
                                                "registration_ms": 3.5, "smoother_ms": 1.0, "rest_ms": 0.5},
            "profile": {"scan prep": 1.0}, "profile_scans": 300}


def test_render_writes_before_and_after_rows_with_their_commands():
    after = {"command": "python -m bench.update --seeds 2", "date": "d1", "machine": "m", "commit": "abc",
             "skip": 5, "seeds": [_seed("/w/s2", 6.0)]}
    before = dict(after, command="python -m bench.update --seeds 2 (old)", commit="old", seeds=[_seed("/w/s2", 12.0)])
    text = update.render(after, before, after["command"])
    assert "`python -m bench.update --seeds 2`" in text and "commit old" in text
    rows = [line for line in text.splitlines() if line.startswith("| s2 |")]
    assert len(rows) == 6  # times, stages, profile: before and after each
    assert "| s2 | before | None | 100 | 12.00 / 13.00 / 14.00 |" in rows[0]
    assert "| s2 | after | None | 100 | 6.00 / 7.00 / 8.00 |" in rows[1]
    assert "| - | 1.00 | 0.20 | 3.50 |" in rows[2]  # a stage the old code did not report: "-"
    assert "first 300 scans" in text


def test_a_missing_world_names_the_command_that_makes_it(tmp_path):
    root = Path(update.__file__).resolve().parent.parent
    res = subprocess.run([sys.executable, "-m", "bench.update", "--work", str(tmp_path), "--seeds", "9",
                          "--out", "-"], cwd=root, capture_output=True, text=True)
    assert res.returncode == 2
    assert "python -m bench.seeds --seeds 9" in res.stderr and str(tmp_path / "s9") in res.stderr


def test_render_marks_lidar_only_rows():
    s = dict(_seed("/w/s2", 6.0), no_imu=True)
    after = {"command": "python -m bench.update --seeds 2 --no-imu", "date": "d1", "machine": "m", "commit": "abc",
             "skip": 5, "seeds": [s]}
    rows = [line for line in update.render(after, None, after["command"]).splitlines()
            if line.startswith("| s2 LiDAR-only | after |")]
    assert len(rows) == 3  # times, stages, profile


def test_ab_edits_turn_one_change_off():
    """A of --ab smoother: LM's own stopping test (no one-iteration shortcut); A of --ab
    registration: an engine without align_from_prediction (the tracker then calls align)."""
    from types import SimpleNamespace

    import pytest

    class Engine:
        def align(self, *a):
            return "align"

        def align_from_prediction(self, *a):
            return "fast"

    window = SimpleNamespace(one_step_m=0.01, one_step_rad=0.0035)
    session = SimpleNamespace(tracker=SimpleNamespace(window=window, registration=Engine()))
    update._without("smoother")(session)
    assert window.one_step_m == 0.0 and window.one_step_rad == 0.0
    update._without("registration")(session)
    engine = session.tracker.registration
    assert not hasattr(engine, "align_from_prediction") and engine.align() == "align"
    with pytest.raises(ValueError):
        update._without("other")(session)
