"""bench.campus's distance bound and per-step times, and bench.campus_seeds' per-seed section."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from blockloc.geometry import Trajectory


class _Line:
    """A sequence driving along x at 2 m/s for 10 s: ground truth at 100 Hz, frames at 10 Hz."""

    def ground_truth(self):
        t = np.arange(1001) * 0.01
        poses = np.tile(np.eye(4), (len(t), 1, 1))
        poses[:, 0, 3] = 2.0 * t
        return Trajectory(t, poses)

    def frame_stamps(self):
        return np.arange(100) * 0.1


def test_frames_for_km_counts_frames_up_to_the_distance_from_start():
    from bench.campus import frames_for_km

    seq = _Line()  # 0.2 m a frame
    assert frames_for_km(seq, 0, 0.001) == 6  # frames 0..5: 1.0 m reached at frame 5
    assert frames_for_km(seq, 50, 0.001) == 6  # measured from --start, not from the session's start
    assert frames_for_km(seq, 90, 1.0) == 10  # the rest of the session when it never gets there


def test_a_rewritten_campus_fragment_keeps_the_seeds_section():
    from bench.campus import _kept_sections
    from bench.campus_seeds import TITLE, replace_section

    old = "## Campus tracking\n\nold run\n\n## " + TITLE + "\n\n| seed |\n| 1 |\n\n## Campus older\n\nx\n"
    assert _kept_sections(old) == "## " + TITLE + "\n\n| seed |\n| 1 |\n"
    new = replace_section(old, TITLE, "## " + TITLE + "\n\nnew table\n")
    assert new == "## Campus tracking\n\nold run\n\n## " + TITLE + "\n\nnew table\n\n## Campus older\n\nx\n"
    assert replace_section("## A\n\na\n", TITLE, "## " + TITLE + "\n\nt\n") == "## A\n\na\n\n## " + TITLE + "\n\nt\n"


def _state(tmp_path: Path, seed: int, offset_m: float, failures: int) -> Path:
    """A bench.campus checkpoint of ``sim:tiny/loc@seed`` whose block backend sits ``offset_m`` to
    the side of the ground truth at every frame."""
    from bench._track import STATUS_CODES
    from blockloc.app.catalog import open_sequence

    seq = open_sequence(f"sim:tiny/loc@{seed}")
    stamps = seq.frame_stamps()[:40]
    poses = seq.ground_truth().interpolate(stamps)
    poses[:, :3, 3] += poses[:, :3, 1] * offset_m  # body y: across the direction of travel
    n = len(stamps)
    d = tmp_path / f"s{seed}"
    d.mkdir()
    np.savez(d / "block.npz", index=np.arange(n), stamps=stamps, poses=poses, core_ms=np.full(n, 8.0),
             update_ms=np.full(n, 9.0), map_ms=np.full(n, 0.5), registration_ms=np.full(n, 5.0),
             switched=np.zeros(n, bool), status=np.full(n, STATUS_CODES["ok"]), window=np.full(n, 10),
             step_wall_ms=np.full(n, 12.0), step_cpu_ms=np.full(n, 10.0),
             counters=np.array(json.dumps({"failures": failures, "recoveries": 0, "switches": 0, "rejected": 1,
                                           "imu_only": 0})),
             map_stats=np.array(json.dumps({"resident_mb": 1.0})))
    (d / "progress.json").write_text(json.dumps({
        "command": f"python -m bench.campus --seed {seed}", "sequence": f"sim:tiny/loc@{seed}", "exact": [],
        "backends": ["block"], "map": "MAP", "map_desc": "1 block", "start": 0, "frames_done": n, "wall_s": 60.0,
        "cpu_s": 50.0, "started": "t0", "updated": "t1", "load_start": 1.0, "load_now": 2.0, "load_mean": 1.5,
        "finished": True}))
    return d


def test_seeds_section_gives_each_seed_its_row_and_the_median_and_worst(tmp_path):
    from bench.campus_seeds import main

    a, b = _state(tmp_path, 1, 0.02, failures=0), _state(tmp_path, 3, 0.05, failures=1)
    out = tmp_path / "campus.md"
    out.write_text("## Campus tracking\n\nkept\n")
    assert main(["--state", f"{b},{a}", "--out", str(out)]) == 0
    text = out.read_text()
    assert text.startswith("## Campus tracking\n\nkept\n\n## Campus over three seeds")
    rows = [line for line in text.splitlines() if line.startswith("| 1 |") or line.startswith("| 3 |")]
    assert [r.split(" | ")[0] for r in rows] == ["| 1", "| 3"]  # sorted by seed
    cells = rows[0].split(" | ")
    assert cells[3] == "0.020" and cells[6] == "0"  # ATE of the 2 cm offset; failures
    assert cells[10] == "2.0"  # all of it across the track, in cm
    assert cells[-3:-1] == ["8.0", "12.0 / 10.0"]  # core wall; step wall / CPU
    assert "`python -m bench.campus --seed 3`" in text
    assert "ATE median 0.035 m, worst 0.050 m (seed 3)" in text
    assert "median ATE <= 0.03 m: 0.035 m — **missed** (on 2 seed(s) only, 3 asked)" in text
    assert "- no failures: 1 — **missed**." in text


def test_seeds_section_refuses_a_directory_that_is_not_a_run(tmp_path, capsys):
    from bench.campus_seeds import main

    with pytest.raises(SystemExit):
        main(["--state", str(tmp_path)])
    assert "not a bench.campus --state directory" in capsys.readouterr().err
