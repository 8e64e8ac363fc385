"""Findings 8 and 9 (issue 40): every command that writes (``sim``, ``map build``, ``map tile``,
``map index``, ``track``, ``demo``, ``eval --plot``) replaces only a folder blockloc made, proven
by its marker's content and holding no foreign file, and checks its output before any work:
writable, not in use by another blockloc run. Each case is ``blockloc ...`` as a user types it."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import pytest

from .cases import Case, case, table
from .conftest import Running, cli_in_process, cli_process, live_holder, small_fs

#: What each writing command is run as ({out} is the folder under test).
COMMANDS = {
    "sim": ("sim", "--out", "{out}"),
    "map-build": ("map", "build", "--seq", "{sess}", "--out", "{out}", "--overwrite"),
    "map-tile": ("map", "tile", "{pcd}", "--tile-size", "5", "--out", "{out}", "--overwrite"),
    "map-index": ("map", "index", "{out}", "--gravity", "down"),
    "map-update": ("map", "update", "{out}", "--run", "{root}/no_run"),
    "map-rollback": ("map", "rollback", "{out}", "--to", "1"),
    "track": ("track", "--seq", "{sess}", "--map", "{map}", "--init", "gt", "--out", "{out}"),
    "demo": ("demo", "--out", "{out}"),
    "eval-plot": ("eval", "--gt", "{gt}", "--est", "{gt}", "--plot", "{out}"),
}
OPTION = {"map-index": "MAP", "map-update": "MAP", "map-rollback": "MAP", "eval-plot": "--plot"}
#: the commands that work on a map store in place (the test copies the tiny map there first)
IN_PLACE = ("map-index", "map-update", "map-rollback")


def _args(cmd: str, places: dict, out: Path) -> list[str]:
    return [a.format(out=out, **places) for a in COMMANDS[cmd]]


@pytest.fixture()
def places(tiny_world, tmp_path):
    import numpy as np

    from blockloc.maps.pcd import write_pcd

    write_pcd(tmp_path / "global.pcd", np.random.default_rng(0).uniform(-10, 10, (2000, 3)).astype(np.float32))
    return {"sess": tiny_world["session"], "map": tiny_world["map"], "pcd": tmp_path / "global.pcd",
            "gt": next(tiny_world["session"].glob("groundtruth_*.csv")), "root": tmp_path}


def _tree(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def _one_line(r, code: int = 2) -> str:
    assert r.code == code, (r.code, r.err)
    assert "Traceback" not in r.err
    assert len(r.err_lines) == 1, r.err_lines
    assert r.err_lines[0].startswith("error: ")
    return r.err_lines[0]


# ----------------------------------------------------------------------------- foreign folders
def _user_dir(root: Path, *extra: tuple[str, str]) -> Path:
    d = root / "thesis"
    d.mkdir()
    (d / "thesis.tex").write_text("years of work")
    for name, text in extra:
        (d / name).write_text(text)
    return d


def _store_with_a_user_file(root: Path, world) -> Path:
    d = root / "store"
    shutil.copytree(world["map"], d)
    (d / "notes.txt").write_text("my notes on this map")
    return d


#: case id -> (what the folder holds, how it is made)
FOREIGN = {
    "sim": ("thesis.tex and a sim.json of the user's", lambda root, world: _user_dir(
        root, ("sim.json", '{"preset": "mine"}'))),
    "map-build": ("thesis.tex and a manifest.json that is not JSON", lambda root, world: _user_dir(
        root, ("manifest.json", "not JSON at all"))),
    "map-build-store": ("a map store blockloc made, holding the user's notes.txt", _store_with_a_user_file),
    "map-tile": ("thesis.tex and a JSON manifest.json of another program", lambda root, world: _user_dir(
        root, ("manifest.json", '{"version": 1, "kind": "grid"}'))),
    "map-tile-store": ("a map store blockloc made, holding the user's notes.txt", _store_with_a_user_file),
    "track": ("thesis.tex and a metrics.json of the user's", lambda root, world: _user_dir(
        root, ("metrics.json", "{}"))),
    "demo": ("thesis.tex and a metrics.json of the user's", lambda root, world: _user_dir(
        root, ("metrics.json", '{"frames": 3}'))),
    "eval-plot": ("thesis.tex and the user's own trajectories.png", lambda root, world: _user_dir(
        root, ("trajectories.png", "my figure"))),
}

FOREIGN_CASES = table("test_foreign_folder_is_never_replaced", [
    Case(k, 8, f"`{' '.join(COMMANDS[k.removesuffix('-store')])}` into a folder holding {what}",
         "exit 2 before any work, one line naming the folder and " + ("notes.txt" if k.endswith("-store")
                                                                      else "'did not make'") + "; every file kept",
         needle="notes.txt" if k.endswith("-store") else "did not make")
    for k, (what, _) in FOREIGN.items()])


@pytest.mark.parametrize("c", FOREIGN_CASES, ids=lambda c: c.id)
def test_foreign_folder_is_never_replaced(c: Case, places, tiny_world):
    out = FOREIGN[c.id][1](places["root"], tiny_world)
    before = _tree(places["root"])
    line = _one_line(cli_in_process(*_args(c.id.removesuffix("-store"), places, out)))
    assert c.needle in line and str(out) in line, line
    assert _tree(places["root"]) == before


@case(8, "map build --overwrite twice into the same --out (each build adds its place index after the store "
      "is written), then map tile --overwrite over it", "replaced each time (exit 0); the marker lists the "
      "store's files; the place index added later is blockloc's too (its manifest lists it: no foreign file); "
      "no lock or temp file left")
def test_overwrite_replaces_its_own_store_again(places):
    from blockloc.outdir import MARKER_NAME, read_marker

    out = places["root"] / "m"
    for _ in range(2):
        r = cli_in_process("map", "build", "--seq", places["sess"], "--out", out, "--overwrite",
                           "--max-frames", "10")
        assert r.code == 0, r.err
    doc = read_marker(out)
    assert doc["kind"] == "map store" and "manifest.json" in doc["files"]
    assert {p.name for p in out.iterdir()} - {MARKER_NAME} <= set(doc["files"]) | {p.name for p in out.glob("place*")}
    r = cli_in_process("map", "tile", places["pcd"], "--tile-size", "5", "--out", out, "--overwrite")
    assert r.code == 0, r.err
    assert sorted(p.name for p in places["root"].iterdir()) == ["global.pcd", "m"]  # no lock or temp left


# ----------------------------------------------------------------------------- unwritable --out
UNWRITABLE_CASES = table("test_unwritable_out_fails_before_any_work", [
    Case(k, 9, f"{' '.join(COMMANDS[k][:2])} with its output in a read-only file system",
         f"exit 2 before any work, one line naming {OPTION.get(k, '--out')} and 'cannot write'",
         needle=OPTION.get(k, "--out")) for k in COMMANDS])


@pytest.mark.parametrize("c", UNWRITABLE_CASES, ids=lambda c: c.id)
def test_unwritable_out_fails_before_any_work(c: Case, places, tiny_world):
    src = places["root"] / "src"
    src.mkdir()
    if c.id in IN_PLACE:
        shutil.copytree(tiny_world["map"], src / "store")
    with small_fs(places["root"] / "ro", "4m", fill_from=src, read_only=True) as ro:
        out = ro / ("store" if c.id in IN_PLACE else "out")
        t0 = time.monotonic()
        line = _one_line(cli_in_process(*_args(c.id, places, out)))
        assert line.startswith(f"error: {c.needle} {out}") and "cannot write" in line, line
        assert time.monotonic() - t0 < 30  # refused at once: nothing was tracked, simulated or built


@case(9, "map plot MAP --out FILE.png with FILE in a read-only file system (a new file, and one there already)",
      "exit 2 before the map is read, one line naming --out and 'cannot write' (not a hidden temp file)")
def test_map_plot_into_a_read_only_place(places, tiny_world):
    src = places["root"] / "src"
    src.mkdir()
    (src / "old.png").write_bytes(b"an old figure")
    with small_fs(places["root"] / "ro", "4m", fill_from=src, read_only=True) as ro:
        for png in (ro / "map.png", ro / "old.png"):
            line = _one_line(cli_in_process("map", "plot", tiny_world["map"], "--out", png))
            assert line.startswith(f"error: --out {png}: cannot write in {ro}"), line
        assert (ro / "old.png").read_bytes() == b"an old figure"


@case(8, "map plot --out FILE and map changes --out FILE over a file of the user's (a figure matplotlib "
      "made, notes in JSON); then over their own earlier output", "the user's file: exit 2, one line naming "
      "--out, the file unchanged (map plot replaced any file before); blockloc's own: replaced, exit 0")
def test_single_file_outputs_replace_only_blockloc_files(tiny_world, tmp_path):
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    fig = plt.figure()
    plt.plot([0, 1], [1, 0])
    fig.savefig(tmp_path / "mine.png")
    plt.close(fig)
    mine = (tmp_path / "mine.png").read_bytes()
    line = _one_line(cli_in_process("map", "plot", tiny_world["map"], "--out", tmp_path / "mine.png"))
    assert line.startswith(f"error: --out {tmp_path / 'mine.png'}: a file blockloc did not write"), line
    assert (tmp_path / "mine.png").read_bytes() == mine
    for _ in range(2):  # its own figure is replaced
        r = cli_in_process("map", "plot", tiny_world["map"], "--out", tmp_path / "map.png")
        assert r.code == 0, r.err
    shutil.copytree(tiny_world["session"], tmp_path / "sess")
    r = cli_in_process("track", "--seq", tmp_path / "sess", "--map", tiny_world["map"], "--init", "gt",
                       "--config", tiny_world["config"], "--out", tmp_path / "run")
    assert r.code == 0, r.err
    (tmp_path / "notes.json").write_text('{"my": "notes"}')
    line = _one_line(cli_in_process("map", "changes", "--map", tiny_world["map"], "--run", tmp_path / "run",
                                    "--out", tmp_path / "notes.json"))
    assert line.startswith(f"error: --out {tmp_path / 'notes.json'}: a file blockloc did not write"), line
    assert (tmp_path / "notes.json").read_text() == '{"my": "notes"}'
    for _ in range(2):
        r = cli_in_process("map", "changes", "--map", tiny_world["map"], "--run", tmp_path / "run",
                           "--out", tmp_path / "changes_copy.json")
        assert r.code == 0, r.err


# ----------------------------------------------------------------------------- locked --out
LOCKED_CASES = table("test_output_in_use_is_refused", [
    Case(k, 9, f"{' '.join(COMMANDS[k][:2])} while a live blockloc process holds the output's lock",
         "exit 2 before any work, one line naming the folder and the holder's PID; the lock kept",
         needle="in use by another blockloc run") for k in COMMANDS])


@pytest.mark.parametrize("c", LOCKED_CASES, ids=lambda c: c.id)
def test_output_in_use_is_refused(c: Case, places, tiny_world):
    out = places["root"] / "out"
    if c.id in IN_PLACE:
        shutil.copytree(tiny_world["map"], out)
    lock = places["root"] / ".out.blockloc-lock"
    with live_holder() as pid:
        lock.write_text(f"pid {pid}\n")
        before = _tree(places["root"])
        line = _one_line(cli_in_process(*_args(c.id, places, out)))
        assert f"{out}: in use by another blockloc run (process {pid})" in line, line
        assert _tree(places["root"]) == before
    # the holder is gone: the next run takes the lock over (checked on the cheapest command)
    if c.id == "eval-plot":
        r = cli_in_process(*_args(c.id, places, out))
        assert r.code == 0, r.err
        assert not lock.exists() and (out / "trajectories.png").is_file()


@case(9, "two `blockloc track` runs with the same --out at once", "the second refuses: exit 2, one line "
      "naming --out and the first run's PID; the first run ends normally (exit 0)")
def test_two_runs_on_one_out(tiny_world, tmp_path):
    out = tmp_path / "res"
    first = Running("track", "--seq", tiny_world["long"], "--map", tiny_world["map"], "--init", "gt",
                    "--config", tiny_world["config"], "--out", out)
    first.wait_for(lambda: (out / "poses.tum").is_file())
    r = cli_in_process("track", "--seq", tiny_world["session"], "--map", tiny_world["map"], "--init", "gt",
                       "--config", tiny_world["config"], "--out", out)
    line = _one_line(r)
    assert line.startswith(f"error: --out {out}: in use by another blockloc run (process {first.proc.pid})"), line
    first.proc.wait(600)
    assert first.proc.returncode == 0, first.err[-2000:]
    assert json.loads((out / "metrics.json").read_text())["frames"] == 120
    assert not (tmp_path / ".res.blockloc-lock").exists()


@case(9, "track --out on a file system with less free space than the run needs (a 1 MiB tmpfs; "
      "the recording of 40 frames needs ~8 MiB by the estimate)", "exit 2 before tracking, one line naming "
      "--out, the free and the needed MiB")
def test_too_little_free_space_is_refused(tiny_world, tmp_path):
    with small_fs(tmp_path / "small", "1m") as fs:
        line = _one_line(cli_in_process("track", "--seq", tiny_world["session"], "--map", tiny_world["map"],
                                        "--init", "gt", "--config", tiny_world["config"], "--out", fs / "res"))
        assert f"--out {fs / 'res'}: " in line and "MiB free on its file system, the run needs about" in line, line
        assert not (fs / "res" / "poses.tum").exists()


# ----------------------------------------------------------------------------- the latest link
@case(12, "a user's own symlink `latest` (to their thesis folder) beside track's --out; then a `latest` "
      "blockloc made", "the user's link is left pointing where it pointed (a warning names it); a link "
      "blockloc made (to a results folder beside it) is moved to the new run")
def test_latest_link_is_repointed_only_when_blockloc_made_it(tiny_world, tmp_path):
    runs = tmp_path / "runs"
    runs.mkdir()
    thesis = _user_dir(tmp_path)
    (runs / "latest").symlink_to(thesis)
    track = ("track", "--seq", tiny_world["session"], "--map", tiny_world["map"], "--init", "gt", "--config",
             tiny_world["config"], "--max-frames", "3", "--out")
    r = cli_process(*track, runs / "a")
    assert r.code == 0, r.err
    assert (runs / "latest").readlink() == thesis
    assert "latest: not updated (a link blockloc did not make" in r.err
    (runs / "latest").unlink()
    for name in ("a", "b"):
        assert cli_in_process(*track, runs / name).code == 0
        assert (runs / "latest").readlink() == Path(name)
