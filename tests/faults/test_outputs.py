"""Findings 1 and 6: what blockloc writes. It replaces only what it made (a store by a store),
its output directories get the mode a plain ``mkdir`` would give them, and what the demo and the
README's commands write is ignored by git."""

from __future__ import annotations

import os
import shutil
import subprocess

import numpy as np
import pytest

from .cases import case
from .conftest import REPO, cli_in_process


@pytest.fixture()
def umask():
    """Set a umask for the test, restore it after; yields a setter."""
    old = os.umask(0o022)
    yield lambda m: os.umask(m)
    os.umask(old)


def mode(path) -> int:
    return os.stat(path).st_mode & 0o777


@pytest.mark.parametrize("mask", [0o022, 0o002, 0o077])
@case(6, "output directories under umask 022 / 002 / 077 (atomic_dir, MapWriter, write_session, "
      "the simulator's writer)", "each gets 0777 & ~umask, as mkdir would (mkdtemp made them 0700)")
def test_output_directories_get_the_umask_mode(mask, umask, tmp_path):
    from blockloc.fileio import atomic_dir
    from blockloc.maps.store import MapWriter
    from blockloc.sim.writer import generate_dataset
    from . import tiny

    umask(mask)
    want = 0o777 & ~mask
    with atomic_dir(tmp_path / "results", "results folder") as tmp:
        (tmp / "metrics.json").write_text("{}")
    with MapWriter(tmp_path / "store", "grid", params={"tile_size_m": 10.0}) as w:
        w.add("5.0_5.0", np.random.default_rng(0).uniform(0, 10, (100, 3)).astype(np.float32))
        w.commit()
    session = tiny.write_tiny_session(tmp_path / "session", n_frames=2)
    sim = generate_dataset("tiny", 1, tmp_path / "sim", max_frames=1, sessions=("map",), azimuth_steps=32)
    for path in (tmp_path / "results", tmp_path / "store", session, session / "velodyne_sync", sim, sim / "map"):
        assert mode(path) == want, (path, oct(mode(path)), oct(want))


@case(1, "map tile --overwrite over a map store blockloc made; then over a results folder",
      "the store is replaced (exit 0); a results folder is not a map store: exit 2, kept")
def test_overwrite_replaces_only_a_map_store(tmp_path):
    from blockloc.maps.pcd import write_pcd
    from blockloc.maps.store import open_map

    rng = np.random.default_rng(0)
    write_pcd(tmp_path / "a.pcd", rng.uniform(0, 10, (500, 3)).astype(np.float32))
    write_pcd(tmp_path / "b.pcd", rng.uniform(0, 20, (800, 3)).astype(np.float32))
    out = tmp_path / "tiles"
    assert cli_in_process("map", "tile", tmp_path / "a.pcd", "--tile-size", "5", "--out", out).code == 0
    r = cli_in_process("map", "tile", tmp_path / "b.pcd", "--tile-size", "5", "--out", out)
    assert r.code == 2 and "--overwrite" in r.err_lines[0]
    r = cli_in_process("map", "tile", tmp_path / "b.pcd", "--tile-size", "5", "--out", out, "--overwrite")
    assert r.code == 0, r.err
    assert open_map(out).total_points == 800
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pcd", "b.pcd", "tiles"]  # no old copy left
    results = tmp_path / "run"
    results.mkdir()
    (results / "metrics.json").write_text('{"frames": 1, "processed": 1, "estimated": 1}')
    (results / "poses.tum").write_text("# a run's poses\n")
    r = cli_in_process("map", "tile", tmp_path / "a.pcd", "--tile-size", "5", "--out", results, "--overwrite")
    assert r.code == 2 and "not a map store" in r.err_lines[0]
    assert (results / "poses.tum").read_text() == "# a run's poses\n"


@case(1, "track --out over the results folder of an earlier run", "allowed (blockloc made it: "
      "metrics.json); the new run's files replace the old ones")
def test_track_may_reuse_its_own_results_folder(tiny_world, tmp_path):
    out = tmp_path / "res"
    shutil.copytree(tiny_world["session"], tmp_path / "sess")
    for _ in range(2):
        r = cli_in_process("track", "--seq", tmp_path / "sess", "--map", tiny_world["map"], "--init", "gt",
                           "--config", tiny_world["config"], "--out", out, "--max-frames", "3")
        assert r.code == 0, r.err
    rows = [ln for ln in (out / "poses.tum").read_text().splitlines() if not ln.startswith("#")]
    assert len(rows) == 3


@case(1, "the README's sequence run twice into the same folders: track --out RUN, eval --plot RUN/eval, "
      "then both again", "allowed: every file is blockloc's (error_breakdown.png, the plot folder inside the run)")
def test_the_readme_sequence_may_run_twice_into_its_own_folders(tiny_world, tmp_path):
    out = tmp_path / "runs" / "small"
    shutil.copytree(tiny_world["session"], tmp_path / "sess")
    gt = sorted((tmp_path / "sess").glob("groundtruth_*.csv"))[0]
    for _ in range(2):
        r = cli_in_process("track", "--seq", tmp_path / "sess", "--map", tiny_world["map"], "--init", "gt",
                           "--config", tiny_world["config"], "--set", "evaluation.plots=true", "--out", out)
        assert r.code == 0, r.err
        assert (out / "error_breakdown.png").is_file()  # what the first fix missed: a real run writes it
        r = cli_in_process("eval", "--gt", gt, "--est", out / "poses.tum", "--plot", out / "eval")
        assert r.code == 0, r.err
        assert (out / "eval" / "error_breakdown.png").is_file()
    # a file of the user's inside the plot folder still makes the run folder foreign
    (out / "eval" / "notes.txt").write_text("mine")
    r = cli_in_process("track", "--seq", tmp_path / "sess", "--map", tiny_world["map"], "--init", "gt",
                       "--config", tiny_world["config"], "--out", out)
    assert r.code == 2 and "eval/notes.txt" in r.err_lines[0], r.err
    assert (out / "eval" / "notes.txt").read_text() == "mine"


@case(4, "track --seq with a relative path, then `map changes --run RUN` and `map update MAP --run RUN` "
      "without --seq from another directory; then a run whose recorded sequence is gone",
      "both open the run's own scans (exit 0); the gone one: exit 2, one line naming the run and --seq")
def test_changes_and_update_find_the_runs_own_sequence(tiny_world, tmp_path, monkeypatch):
    import json

    shutil.copytree(tiny_world["session"], tmp_path / "sess")
    shutil.copytree(tiny_world["map"], tmp_path / "map")
    monkeypatch.chdir(tmp_path)
    r = cli_in_process("track", "--seq", "sess", "--map", "map", "--init", "gt", "--config", tiny_world["config"],
                       "--out", "run")
    assert r.code == 0, r.err
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    r = cli_in_process("map", "changes", "--map", tmp_path / "map", "--run", tmp_path / "run")
    assert r.code == 0, r.err
    assert json.loads((tmp_path / "run" / "changes.json").read_text())["frames_trusted"] > 0
    r = cli_in_process("map", "update", tmp_path / "map", "--run", tmp_path / "run")
    assert r.code == 0, r.err
    metrics = tmp_path / "run" / "metrics.json"
    doc = json.loads(metrics.read_text())
    doc["sequence_arg"] = str(tmp_path / "moved")
    metrics.write_text(json.dumps(doc))
    r = cli_in_process("map", "changes", "--map", tmp_path / "map", "--run", tmp_path / "run")
    assert r.code == 2 and len(r.err_lines) == 1 and "--seq" in r.err_lines[0] and "moved" in r.err_lines[0], r.err


@case(6, "what `blockloc demo` and the README's commands write into a clone (results/, runs/, "
      "sim_out/, maps/, map.png)", "ignored by git (.gitignore)")
def test_outputs_are_ignored_by_git(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("no git")
    # the repository's .gitignore in a fresh repository (this tree need not be a checkout)
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    shutil.copy(REPO / ".gitignore", tmp_path / ".gitignore")
    paths = ["results/demo_20260101-000000/metrics.json", "runs/small/poses.tum", "sim_out/sim.json",
             "maps/small/manifest.json", "map.png"]
    r = subprocess.run(["git", "-C", str(tmp_path), "check-ignore", "--no-index", *paths], capture_output=True,
                       text=True)
    assert sorted(r.stdout.split()) == sorted(paths), r.stdout + r.stderr
