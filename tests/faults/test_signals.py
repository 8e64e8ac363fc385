"""Finding 3: Ctrl-C and SIGTERM are honest. Real signals to real ``blockloc`` processes: a map
build or a simulation stops, removes its temp directory, prints one line and exits 130 / 143; a
tracking run stops after the current frame, keeps its partial results marked ``interrupted`` and
exits 130 / 143; a killed build's leftovers are removed by the next build."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from .cases import Case, case, table
from .conftest import Outcome, Running, cli_process

CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}
SIGNALS = [pytest.param(signal.SIGINT, id="SIGINT"), pytest.param(signal.SIGTERM, id="SIGTERM")]


@pytest.fixture(scope="module")
def big_pcd(tmp_path_factory) -> Path:
    """A global PCD that takes `map tile` seconds to write (2500 tiles of 4 m)."""
    from blockloc.maps.pcd import write_pcd

    rng = np.random.default_rng(0)
    n = 400_000
    path = tmp_path_factory.mktemp("big") / "global.pcd"
    write_pcd(path, np.c_[rng.uniform(-100, 100, (n, 2)), rng.uniform(0, 3, n)].astype(np.float32))
    return path


def leftovers(parent: Path, name: str) -> list[str]:
    """Hidden temp directories of an output ``name`` in ``parent``."""
    return sorted(p.name for p in parent.iterdir() if p.name.startswith(f".{name}."))


def assert_stopped(r: Outcome, signum: int) -> str:
    """Exit 130 / 143, no traceback, one message line (naming the signal); returns it."""
    assert r.code == CODES[signum], (r.code, r.err[-800:])
    assert "Traceback" not in r.err
    lines = [ln for ln in r.err_lines if "received: stopping after the current frame" not in ln]
    assert len(lines) == 1, lines
    return lines[0]


STOPS = table("test_signal_stops_and_cleans_up", [
    Case("map-tile-SIGINT", 3, "SIGINT while `map tile` writes its tiles",
         "exit 130, 'interrupted (SIGINT)', the .NAME.building-* dir removed, no --out"),
    Case("map-tile-SIGTERM", 3, "SIGTERM while `map tile` writes its tiles",
         "exit 143, one line, the temp dir removed (SIGTERM killed it and left the dir)"),
    Case("map-build-SIGINT", 3, "SIGINT while `map build` extracts keyframes",
         "exit 130 (was 0, no message), one line, no --out and no temp dir"),
    Case("map-build-SIGTERM", 3, "SIGTERM while `map build` extracts keyframes",
         "exit 143, one line, no --out and no temp dir"),
    Case("sim-SIGINT", 3, "SIGINT while `blockloc sim` simulates", "exit 130, one line, .NAME.tmp-* removed"),
    Case("sim-SIGTERM", 3, "SIGTERM while `blockloc sim` simulates",
         "exit 143, one line, .NAME.tmp-* removed (SIGTERM killed it and left the dir)"),
])


@pytest.mark.parametrize("c", STOPS, ids=lambda c: c.id)
def test_signal_stops_and_cleans_up(c: Case, tiny_world, big_pcd, tmp_path):
    signum = signal.SIGINT if c.id.endswith("SIGINT") else signal.SIGTERM
    out = tmp_path / "out"
    (tmp_path / "thesis.tex").write_text("a user's file beside the output")
    # signalled mid-work: after the first item its progress reports (and, for the writers, once
    # their temp directory exists)
    if c.id.startswith("map-tile"):
        run = Running("map", "tile", big_pcd, "--tile-size", "4", "--out", out)
        run.wait_for(lambda: leftovers(tmp_path, "out") and re.search(r"tiles: [1-9]\d*/\d+", run.err))
    elif c.id.startswith("map-build"):
        run = Running("map", "build", "--seq", tiny_world["long"], "--config", tiny_world["config"], "--out", out)
        # the build's tasks, once the drive is planned and its first keyframes are read
        run.wait_for(lambda: re.search(r"map build tasks: [1-9]\d*/\d{2,} ", run.err))
    else:
        run = Running("sim", "--preset", "tiny", "--azimuth-steps", "64", "--out", out)
        run.wait_for(lambda: leftovers(tmp_path, "out") and re.search(r"sim tiny: [1-9]\d*/", run.err))
    line = assert_stopped(run.signal(signum), signum)
    assert line == f"interrupted ({signal.Signals(signum).name})"
    assert not out.exists()
    assert leftovers(tmp_path, "out") == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["thesis.tex"]


@pytest.mark.parametrize("signum", SIGNALS)
def test_track_stopped_keeps_partial_results(signum, tiny_world, tmp_path):
    out = tmp_path / "res"
    run = Running("track", "--seq", tiny_world["long"], "--map", tiny_world["map"], "--init", "gt",
                  "--config", tiny_world["config"], "--out", out)
    run.wait_for(lambda: (out / "poses.tum").is_file() and len((out / "poses.tum").read_text().splitlines()) > 4)
    r = run.signal(signum)
    line = assert_stopped(r, signum)
    m = json.loads((out / "metrics.json").read_text())
    assert m["interrupted"] is True
    rows = [ln for ln in (out / "poses.tum").read_text().splitlines() if ln and not ln.startswith("#")]
    name = signal.Signals(signum).name
    assert re.fullmatch(rf"interrupted by {name} after {m['frames']} of 120 frames; partial results in "
                        rf"{re.escape(str(out))}", line), line
    # the first line says which signal arrived and what happens now
    assert f"{name} received: stopping after the current frame" in r.err
    assert 3 <= len(rows) == m["frames"] < 120
    assert (out / "diagnostics.csv").is_file() and (out / "config.yaml").is_file()


table("test_track_stopped_keeps_partial_results", [
    Case("SIGINT", 3, "SIGINT during `blockloc track`",
         "exit 130 (was 0), 'SIGINT received: stopping after the current frame', then 'interrupted by "
         "SIGINT after N of 120 frames; partial results in DIR', metrics.json 'interrupted': true, poses.tum "
         "has the N frames"),
    Case("SIGTERM", 3, "SIGTERM during `blockloc track`",
         "exit 143 (was killed without metrics), 'SIGTERM received: stopping after the current frame' "
         "(was the same words as for Ctrl-C), 'interrupted by SIGTERM after ...', same partial results"),
])


@case(3, "`map tile` killed with SIGKILL (its .NAME.building-* dir left behind), then another build "
      "into the same parent; and a building dir whose process still runs",
      "the next build removes the dead build's dir (a warning names it) and its lock file, and keeps the "
      "live one's")
def test_killed_build_is_cleaned_by_the_next(big_pcd, tmp_path):
    run = Running("map", "tile", big_pcd, "--tile-size", "4", "--out", tmp_path / "a")
    run.wait_for(lambda: any(".building-" in n for n in leftovers(tmp_path, "a")))
    r = run.signal(signal.SIGKILL)
    assert r.code == -signal.SIGKILL
    stale = [n for n in leftovers(tmp_path, "a") if ".building-" in n]
    assert len(stale) == 1 and stale[0].startswith(".a.building-")
    assert (tmp_path / ".a.blockloc-lock").is_file()  # its lock, which nothing could remove
    live = tmp_path / ".c.building-live"
    live.mkdir()
    (live / ".incomplete").write_text(f"build started now pid {os.getpid()}\n")  # this test's process
    small = tmp_path / "small.pcd"
    from blockloc.maps.pcd import write_pcd

    write_pcd(small, np.random.default_rng(1).uniform(0, 10, (500, 3)).astype(np.float32))
    r = cli_process("map", "tile", small, "--tile-size", "5", "--out", tmp_path / "b")
    assert r.code == 0, r.err
    assert stale[0] in r.err and "interrupted build" in r.err
    assert leftovers(tmp_path, "a") == [] and live.is_dir()  # the dead run's lock is gone too


@case(3, "SIGINT to a process whose parent ignores SIGINT (a background job of a script, nohup)",
      "the signal stays ignored: the command runs to its end (exit 0)")
def test_ignored_sigint_stays_ignored(tmp_path):
    code = ("import signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
            "from blockloc.commands.common import install_signal_handlers; install_signal_handlers(); "
            "import os; os.kill(os.getpid(), signal.SIGINT); print('still here')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2])))
    assert r.returncode == 0 and r.stdout.strip() == "still here", r.stderr


@case(3, "a signal whose exception the interrupted code swallows (as a C module's import does, "
      "turning it into ImportError, or a catch-all fallback)", "the command still exits 130 with "
      "'interrupted (SIGINT)', and the next progress step raises it again")
def test_swallowed_signal_still_exits_130(tmp_path):
    script = tmp_path / "swallow.py"
    script.write_text(
        "import os, signal, sys, time\n"
        "from blockloc import cli\n"
        "from blockloc.commands.common import progress\n"
        "@cli.app.command('swallow')\n"
        "def swallow():\n"
        "    try:\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        time.sleep(1)\n"
        "    except BaseException:\n"
        "        pass  # swallowed\n"
        "    with progress('steps', 3) as cb:\n"
        "        try:\n"
        "            cb(1)\n"
        "        except BaseException as exc:\n"
        "            print('raised again:', type(exc).__name__)\n"
        "    print('went on')\n"
        "sys.argv = ['blockloc', 'swallow']\n"
        "cli.main()\n")
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2])))
    assert r.returncode == 130, r.stderr
    assert r.stdout.splitlines() == ["raised again: Stopped", "went on"]
    assert r.stderr.strip().splitlines()[-1] == "interrupted (SIGINT)"
