"""bench._dynamic: the raw map, our remover and DUFOMap scored on one DynamicMap folder."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from bench._dynamic import METHODS, run_dynamic_comparison
from blockloc.datasets.dynamicmap import DynamicMapWriter

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "maps"))
from test_dynamic_removal import _scene  # noqa: E402  (the walker-and-wall drive)


@pytest.fixture
def folder(tmp_path):
    w = DynamicMapWriter(tmp_path / "seq")
    for origin, pts, dyn in _scene():
        T = np.eye(4)
        T[:3, 3] = origin
        w.add_scan(pts, T, dyn)
    w.finish()
    return tmp_path / "seq"


def test_rows_for_raw_and_ours(folder, tmp_path):
    rows = run_dynamic_comparison(folder, tmp_path / "out", methods=("raw map", "blockloc (voxel evidence)"),
                                  up=(0.0, 0.0, 1.0))
    raw, ours = rows
    assert raw["method"] == "raw map" and raw["sa"] == 100.0 and raw["da"] == 0.0
    assert ours["sa"] > 99.0 and ours["da"] > 70.0 and ours["aa"] > 80.0
    assert raw["dynamic_points"] == ours["dynamic_points"] == 3 * 16 * 34
    assert ours["wall_s"] >= 0 and ours["cpu_s"] >= 0
    assert (tmp_path / "out" / "blockloc_output.pcd").is_file() and (tmp_path / "out" / "raw_output.pcd").is_file()


def test_dufomap_row(folder):
    pytest.importorskip("dufomap", reason="dufomap is a bench extra: pip install -e .[bench]")
    (row,) = run_dynamic_comparison(folder, None, methods=("DUFOMap",), up=(0.0, 0.0, 1.0))
    assert row["method"] == "DUFOMap" and set(METHODS) >= {"DUFOMap"}
    assert row["sa"] > 90.0 and row["da"] > 50.0  # it sees through where the walker stood, too


def test_bench_dynamic_command(tmp_path):
    """`python -m bench.dynamic` as README names it, on two scans of the tiny world."""
    import subprocess

    pytest.importorskip("dufomap", reason="dufomap is a bench extra: pip install -e .[bench]")
    root = Path(__file__).resolve().parent.parent.parent
    out = tmp_path / "dynamic.md"
    r = subprocess.run([sys.executable, "-m", "bench.dynamic", "--preset", "tiny", "--seed", "3", "--starts", "5",
                        "--frames", "2", "--step", "1", "--work", str(tmp_path / "w"), "--out", str(out)],
                       cwd=root, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    assert "sim:tiny/map_m12@3" in text and "| raw map | 100.00 | 0.00 |" in text
    assert "| DUFOMap |" in text and "| blockloc (voxel evidence) |" in text
    assert (tmp_path / "w" / "tiny_map_m12_s3_5_2x1" / "gt_cloud.pcd").is_file()


def test_bench_dynamic_build_command(tmp_path):
    """`python -m bench.dynamic_build`: the build's filter scored against the simulator's labels
    on the tiny world's 12-month mapping drive (its first 100 frames; no tracking part)."""
    import re
    import subprocess

    root = Path(__file__).resolve().parent.parent.parent
    out = tmp_path / "dynamic_build.md"
    r = subprocess.run([sys.executable, "-m", "bench.dynamic_build", "--preset", "tiny", "--seed", "1", "--frames",
                        "100", "--track-frames", "0", "--work", str(tmp_path / "w"), "--out", str(out)],
                       cwd=root, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    assert "sim:tiny/map_m12@1" in text
    row = next(line for line in text.splitlines() if re.match(r"\| [\d,]+ \| [\d,]+ \|", line))
    static, moving, sa, da = (float(c.replace(",", "")) for c in row.strip("|").split("|")[:4])
    assert moving > 1000 and static > 10 * moving
    assert sa > 90.0 and da > 50.0  # most moving points out, nearly every static point kept
