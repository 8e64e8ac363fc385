"""Finding 11, lifelong maps: ``map changes --run`` and ``map update --run`` take a run only with
the map it was tracked in (a map is never changed by evidence from another map's frame). Each
case is a real ``blockloc track`` subprocess on the tiny world, then the commands as typed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from . import tiny
from .cases import case
from .conftest import cli_process


def _files(folder: Path) -> dict:
    """Every file under ``folder`` with its bytes."""
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_error(r) -> str:
    lines = r.err_lines
    assert r.code == 2 and len(lines) == 1 and lines[0].startswith("error: "), r.err
    assert "Traceback" not in r.err
    return lines[0]


@case(11, "map changes --map OTHER --run RUN and map update OTHER --run RUN where RUN was tracked in another "
      "map (as docs/own_data.md: --map maps/walk, relative); the same with a run from before runs recorded "
      "their map's identity; then the run's own map moved and renamed, and updated",
      "exit 2 before any work, one line naming the run, the map it was tracked in and the one given; "
      "OTHER and the run folder (run.mcap, report.html) unchanged; the moved, renamed, updated map: exit 0; "
      "an old run whose map cannot be found: a warning, exit 0")
def test_a_run_tracked_in_another_map_is_refused(tiny_world, tmp_path, monkeypatch):
    work = tmp_path / "work"
    (work / "maps").mkdir(parents=True)
    shutil.copytree(tiny_world["map"], work / "maps" / "walk")
    other = tiny.build_tiny_map(tiny_world["session"], tmp_path / "other")  # another drive's map, same frame
    r = cli_process("track", "--seq", tiny_world["session"], "--map", "maps/walk", "--init", "gt", "--config",
                    tiny_world["config"], "--out", "runs/walk", cwd=work)
    assert r.code == 0, r.err
    run = work / "runs" / "walk"
    metrics = (run / "metrics.json").read_text()
    doc = json.loads(metrics)
    assert doc["map"] == "maps/walk" and doc["map_path"] == str(work / "maps" / "walk") and doc["map_id"]
    run_before, other_before = _files(run), _files(other)
    refused = (f"error: --run {run}: tracked in {work / 'maps' / 'walk'}, not {other} (expected a run tracked in "
               "this map, or in a copy or another version of it)")
    assert _one_error(cli_process("map", "changes", "--map", other, "--run", run)) == refused
    assert _one_error(cli_process("map", "update", other, "--run", run)) == refused
    # a run from before runs recorded their map's identity: its map as given to track, from here
    old = dict(doc)
    del old["map_path"], old["map_id"]
    (run / "metrics.json").write_text(json.dumps(old))
    line = _one_error(cli_process("map", "update", other, "--run", run, cwd=work))
    assert line.startswith(f"error: --run {run}: tracked in maps/walk, not {other} "), line
    (run / "metrics.json").write_text(metrics)
    assert _files(run) == run_before and _files(other) == other_before  # nothing detected, drawn or written
    # the run's own map, moved and renamed: still its map, and still after an update of it
    moved = tmp_path / "elsewhere" / "site_map"
    moved.parent.mkdir()
    shutil.move(work / "maps" / "walk", moved)
    r = cli_process("map", "changes", "--map", moved, "--run", run)
    assert r.code == 0 and "WARNING" not in r.err, r.err
    r = cli_process("map", "update", moved, "--run", run, "--run", run)
    assert r.code == 0 and "version 2" in r.out, r.err
    r = cli_process("map", "changes", "--map", moved, "--run", run)
    assert r.code == 0 and "WARNING" not in r.err, r.err
    # the old run's map is gone from where it recorded it: nothing to compare with, it is taken
    (run / "metrics.json").write_text(json.dumps(old))
    r = cli_process("map", "changes", "--map", other, "--run", run, cwd=work)
    assert r.code == 0, r.err
    assert f"{run}: tracked in maps/walk, which cannot be compared with {other} here" in r.err, r.err


@case(11, "track --seq FOLDER --poses FILE where the scans have no stamps of their own (the trajectory gives "
      "them, as docs/own_data.md's walk), then map changes --run RUN and map update MAP --run RUN from another "
      "directory; then the trajectory moved away; then a run from before runs recorded their --poses",
      "the scans reopened with the run's trajectory: exit 0, no 'no scan stamps' warning, every trusted frame "
      "used; the trajectory gone: exit 2, one line naming the run and the file; the old run: as before, exit 0")
def test_changes_and_update_reopen_the_runs_poses(tiny_world, tmp_path):
    folder = shutil.copytree(tiny_world["folder"], tmp_path / "walk")
    for i, scan in enumerate(sorted((folder / "scans").iterdir())):  # names that are not times
        scan.rename(scan.with_name(f"{i:06d}.pcd"))
    traj = tmp_path / "poses" / "walk.tum"
    traj.parent.mkdir()
    (folder / "poses.tum").rename(traj)
    m = shutil.copytree(tiny_world["map"], tmp_path / "map")
    r = cli_process("track", "--seq", "walk", "--poses", "poses/walk.tum", "--map", "map", "--init", "gt",
                    "--config", tiny_world["config"], "--out", "run", cwd=tmp_path)
    assert r.code == 0 and "no scan stamps" not in r.err, r.err
    run = tmp_path / "run"
    metrics = (run / "metrics.json").read_text()
    assert json.loads(metrics)["poses_arg"] == str(traj)
    r = cli_process("map", "changes", "--map", m, "--run", run)
    assert r.code == 0 and "WARNING" not in r.err, r.err
    doc = json.loads((run / "changes.json").read_text())
    assert doc["frames_trusted"] == doc["scans_used"] > 0 and doc["scans_rejected"] == 0, doc
    r = cli_process("map", "update", m, "--run", run)
    assert r.code == 0 and "WARNING" not in r.err, r.err
    # the trajectory moved away: the scans' stamps cannot be had; nothing detected
    traj.rename(tmp_path / "moved.tum")
    line = _one_error(cli_process("map", "changes", "--map", m, "--run", run))
    assert line == (f"error: --run {run}: the trajectory it was tracked with (--poses {traj}) is not there any "
                    "more (expected it where the run's metrics.json records it)"), line
    # a run from before runs recorded their --poses: opened as before
    old = json.loads(metrics)
    del old["poses_arg"]
    (run / "metrics.json").write_text(json.dumps(old))
    r = cli_process("map", "changes", "--map", m, "--run", run)
    assert r.code == 0, r.err
