"""Finding 4 (and the cheap cases of 1, 2 and 6): every bad invocation ends in one line naming
the option or file, exit 2, no traceback, and before any work; ``--help`` shows real metavars;
every command and option the README names exists."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from .cases import Case, case, table
from .conftest import REPO, cli_in_process

S = "{sess}"  # placeholders filled from the tiny world (see ``_fill``)
M = "{map}"

BAD_INVOCATIONS = table("test_bad_invocation", [
    Case("track-missing-seq", 4, "track without --seq", "exit 2, names --seq", ("track",), needle="--seq"),
    Case("track-unknown-option", 4, "an option track does not have", "exit 2, names it and a close one",
         ("track", "--seq", S, "--frame", "1"), needle="--frame"),
    Case("init-frame-not-int", 4, "--frame abc", "exit 2, names --frame",
         ("init", "--seq", S, "--map", M, "--frame", "abc"), needle="--frame"),
    Case("init-frame-negative", 4, "--frame -1", "exit 2, names --frame",
         ("init", "--seq", S, "--map", M, "--frame", "-1"), needle="--frame"),
    Case("init-frame-out-of-range", 4, "--frame past the last scan", "exit 2, names --frame and the range",
         ("init", "--seq", S, "--map", M, "--frame", "99", "--pose-hint", "0,0"), needle="--frame 99"),
    Case("init-window-negative", 4, "--window -5", "exit 2, names --window",
         ("init", "--seq", S, "--map", M, "--frame", "0", "--window", "-5"), needle="--window"),
    Case("init-yaw-window-too-wide", 4, "--yaw-window 400", "exit 2, names --yaw-window",
         ("init", "--seq", S, "--map", M, "--frame", "0", "--yaw-window", "400"), needle="--yaw-window"),
    Case("init-pose-hint-not-numbers", 4, "--pose-hint 1,a", "exit 2, names --pose-hint",
         ("init", "--seq", S, "--map", M, "--frame", "0", "--pose-hint", "1,a"), needle="--pose-hint"),
    Case("track-max-frames-not-int", 4, "--max-frames abc", "exit 2, names --max-frames",
         ("track", "--seq", S, "--map", M, "--max-frames", "abc"), needle="--max-frames"),
    Case("track-max-frames-zero", 4, "--max-frames 0", "exit 2, names --max-frames",
         ("track", "--seq", S, "--map", M, "--max-frames", "0"), needle="--max-frames"),
    Case("track-init-bogus", 4, "--init bogus", "exit 2, names --init",
         ("track", "--seq", S, "--map", M, "--init", "bogus"), needle="--init 'bogus'"),
    Case("track-init-pose-bad", 4, "--init-pose 1,a", "exit 2, names --init-pose",
         ("track", "--seq", S, "--map", M, "--init-pose", "1,a"), needle="--init-pose"),
    Case("track-init-and-init-pose", 4, "--init gt with --init-pose", "exit 2, names both",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--init-pose", "1,2"), needle="--init-pose"),
    Case("track-set-malformed", 4, "--set without KEY=VALUE", "exit 2, names --set",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--set", "bogus"), needle="--set"),
    Case("track-set-out-of-range", 6, "--set map.voxel_size_m=-1", "exit 2, names the key and its range",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--set", "map.voxel_size_m=-1"),
         needle="map.voxel_size_m: expected a value >= 0"),
    Case("track-set-integer-fraction", 6, "--set registration.max_iterations=2.5e0",
         "exit 2, names the key: an integer field refuses a fraction in any notation",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--set", "registration.max_iterations=2.5e0"),
         needle="registration.max_iterations: expected an integer, got '2.5e0'"),
    Case("track-set-notation-out-of-range", 6, "--set tracking.min_fitness=5e0",
         "exit 2, names the key and its range, the value read as 5.0 (was 'expected a number, got '5e0'')",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--set", "tracking.min_fitness=5e0"),
         needle="tracking.min_fitness: expected a value in [0, 1], got 5.0"),
    Case("track-set-nan-text", 6, "--set tracking.min_fitness=nan", "exit 2, names the key: a finite number",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--set", "tracking.min_fitness=nan"),
         needle="tracking.min_fitness: expected a finite number, got 'nan'"),
    Case("track-config-missing", 4, "--config naming no file", "exit 2, names the file and the presets",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--config", "{root}/nosuch.yaml"),
         needle="nosuch.yaml: no such config file"),
    Case("track-config-negative-size", 6, "a config file with map.voxel_size_m: -1",
         "exit 2, names the file, the key and the range",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--config", "{root}/bad_voxel.yaml"),
         needle="bad_voxel.yaml: map.voxel_size_m: expected a value >= 0, got -1.0"),
    Case("track-config-nan-rate", 6, "a config file with imu.rate_hz: .nan", "exit 2, names the key",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--config", "{root}/bad_rate.yaml"),
         needle="imu.rate_hz: expected a finite number"),
    Case("track-config-zero-count", 6, "a config file with registration.max_iterations: 0",
         "exit 2, names the key", ("track", "--seq", S, "--map", M, "--init", "gt", "--config",
                                   "{root}/bad_count.yaml"),
         needle="registration.max_iterations: expected a value >= 1"),
    Case("track-config-probability", 6, "a config file with registration.outlier_ratio: 1.5",
         "exit 2, names the key", ("track", "--seq", S, "--map", M, "--init", "gt", "--config",
                                   "{root}/bad_ratio.yaml"),
         needle="registration.outlier_ratio: expected a value in (0, 1)"),
    Case("map-build-config-binary", 6, "--config naming a binary PCD (a scan given as the config)",
         "exit 2, names the file, a YAML config expected (was UnicodeDecodeError naming no file, exit 1)",
         ("map", "build", "--seq", S, "--out", "{root}/m", "--config", "{pcd}"),
         needle="global.pcd: binary bytes (not UTF-8 text at byte "),
    Case("map-build-config-empty", 6, "--config naming an empty file", "exit 2, names the file, a YAML "
         "config expected (was silently the defaults)", ("map", "build", "--seq", S, "--out", "{root}/m",
                                                         "--config", "{root}/empty.yaml"),
         needle="empty.yaml: empty, expected a YAML config file"),
    Case("map-build-config-list", 6, "--config naming a YAML list", "exit 2, names the file, a mapping "
         "expected", ("map", "build", "--seq", S, "--out", "{root}/m", "--config", "{root}/list.yaml"),
         needle="list.yaml: a list at the top level, expected a mapping of sections (a YAML config file"),
    Case("map-build-config-directory", 6, "--config naming a directory", "exit 2, names it, a YAML config "
         "file expected", ("map", "build", "--seq", S, "--out", "{root}/m", "--config", "{userdir}"),
         needle="thesis: a directory, expected a YAML config file"),
    Case("track-backend-bogus", 4, "--map-backend bogus", "exit 2, names the value and the choices",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--map-backend", "bogus"), needle="'bogus'"),
    Case("track-seq-missing-path", 2, "--seq naming nothing", "exit 2, names it",
         ("track", "--seq", "{root}/nosuch", "--map", M, "--init", "gt"), needle="nosuch"),
    Case("track-seq-is-a-map-store", 4, "--seq naming a map store (the map given as the scans)",
         "exit 2, says it is a map store and to give it with --map (it was read as a scan folder without "
         "stamps)", ("track", "--seq", M, "--map", M, "--init", "gt"), needle="a map store, not a sequence"),
    Case("track-map-missing", 2, "--map naming nothing", "exit 2, names it",
         ("track", "--seq", S, "--map", "{root}/nomap", "--init", "gt"), needle="nomap: no such map directory"),
    Case("map-info-of-a-file", 2, "map info FILE", "exit 2, names the file",
         ("map", "info", "{file}"), needle="notes.txt: not a map directory"),
    Case("map-info-missing-argument", 4, "map info without MAP", "exit 2, names MAP", ("map", "info"),
         needle="missing MAP"),
    Case("map-tile-missing-argument", 4, "map tile without GLOBAL_PCD", "exit 2, names GLOBAL_PCD",
         ("map", "tile"), needle="missing GLOBAL_PCD"),
    Case("map-tile-size-not-number", 4, "--tile-size abc", "exit 2, names --tile-size",
         ("map", "tile", "{pcd}", "--tile-size", "abc", "--out", "{root}/t"), needle="--tile-size"),
    Case("map-tile-size-zero", 4, "--tile-size 0", "exit 2, names --tile-size",
         ("map", "tile", "{pcd}", "--tile-size", "0", "--out", "{root}/t"), needle="--tile-size 0"),
    Case("map-build-no-input", 4, "map build with neither --seq nor --from-pcd", "exit 2, names both",
         ("map", "build", "--out", "{root}/m"), needle="--seq"),
    Case("map-build-kind-bogus", 4, "--kind bogus", "exit 2, names --kind",
         ("map", "build", "--seq", S, "--out", "{root}/m", "--kind", "bogus"), needle="--kind 'bogus'"),
    Case("map-build-block-size-zero", 4, "--block-size 0", "exit 2, names --block-size",
         ("map", "build", "--seq", S, "--out", "{root}/m", "--block-size", "0"), needle="--block-size 0"),
    Case("map-build-voxel-negative", 4, "--voxel -1", "exit 2, names --voxel (it built a map before)",
         ("map", "build", "--seq", S, "--out", "{root}/m", "--voxel", "-1"), needle="--voxel"),
    Case("map-build-max-frames-zero", 4, "--max-frames 0", "exit 2, names --max-frames",
         ("map", "build", "--seq", S, "--out", "{root}/m", "--max-frames", "0"), needle="--max-frames"),
    Case("map-build-from-pcd-without-poses", 4, "--from-pcd without --poses", "exit 2, names --poses",
         ("map", "build", "--from-pcd", "{pcd}", "--out", "{root}/m"), needle="--poses"),
    Case("map-serve-port-out-of-range", 4, "--port 99999", "exit 2, names --port (was a 10 s timeout)",
         ("map", "serve", M, "--port", "99999"), needle="--port"),
    Case("sim-seed-not-int", 4, "--seed x", "exit 2, names --seed", ("sim", "--seed", "x", "--out", "{root}/s"),
         needle="--seed"),
    Case("sim-missing-out", 4, "sim without --out", "exit 2, names --out", ("sim",), needle="--out"),
    Case("sim-preset-bogus", 4, "--preset bogus", "exit 2, names the preset and the choices",
         ("sim", "--preset", "bogus", "--out", "{root}/s"), needle="'bogus'"),
    Case("sim-azimuth-steps-too-few", 4, "--azimuth-steps 3", "exit 2, names --azimuth-steps",
         ("sim", "--azimuth-steps", "3", "--out", "{root}/s"), needle="--azimuth-steps"),
    Case("eval-gt-missing", 2, "--gt naming nothing", "exit 2, names the file",
         ("eval", "--gt", "{root}/nosuch.csv", "--est", "{root}/nosuch.tum"), needle="nosuch.csv"),
    Case("eval-max-time-diff-not-number", 4, "--max-time-diff abc", "exit 2, names --max-time-diff",
         ("eval", "--gt", "{gt}", "--est", "{gt}", "--max-time-diff", "abc"), needle="--max-time-diff"),
    Case("eval-rpe-deltas-bad", 4, "--rpe-deltas x", "exit 2, names --rpe-deltas",
         ("eval", "--gt", "{gt}", "--est", "{gt}", "--rpe-deltas", "x"), needle="--rpe-deltas"),
    Case("demo-max-frames-zero", 4, "demo --max-frames 0", "exit 2 before any work (it ran a whole demo)",
         ("demo", "--max-frames", "0"), needle="--max-frames"),
    Case("unknown-command", 4, "blockloc nosuchcommand", "exit 2, names it", ("nosuchcommand",),
         needle="nosuchcommand"),
    Case("unknown-global-option", 4, "blockloc --bogus", "exit 2, names it", ("--bogus",), needle="--bogus"),
    # --out / --plot checked before any work (finding 2: --out naming a file failed after tracking)
    Case("track-out-is-a-file", 2, "track --out naming an existing file", "exit 2 before any work, file kept",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--out", "{file}"), needle="--out"),
    Case("track-out-under-a-file", 2, "track --out FILE/sub", "exit 2 before any work, names the file",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--out", "{file}/sub"), needle="notes.txt is a file"),
    Case("demo-out-is-a-file", 2, "demo --out naming an existing file", "exit 2 before any work",
         ("demo", "--out", "{file}"), needle="--out"),
    Case("sim-out-is-a-file", 2, "sim --out naming an existing file", "exit 2 before any work",
         ("sim", "--out", "{file}"), needle="--out"),
    Case("map-build-out-is-a-file", 2, "map build --out FILE --overwrite", "exit 2, the file kept",
         ("map", "build", "--seq", S, "--out", "{file}", "--overwrite"), needle="not a directory"),
    Case("eval-plot-is-a-file", 2, "eval --plot naming a file", "exit 2 before any work (was FileExistsError)",
         ("eval", "--gt", "{gt}", "--est", "{gt}", "--plot", "{file}"), needle="--plot"),
    Case("map-plot-out-is-a-directory", 2, "map plot --out DIR", "exit 2, names --out (was ValueError)",
         ("map", "plot", M, "--out", "{userdir}"), needle="is a directory"),
    Case("map-plot-out-without-suffix", 2, "map plot --out NAME without an image suffix",
         "exit 2, names --out", ("map", "plot", M, "--out", "{root}/mapfig"), needle="image file name"),
    # replace only what blockloc made (finding 1)
    Case("sim-out-user-directory", 1, "sim --out DIR holding thesis.tex", "exit 2, names DIR, thesis.tex kept",
         ("sim", "--out", "{userdir}"), needle="a directory blockloc did not make"),
    Case("map-build-overwrite-user-directory", 1, "map build --overwrite into DIR holding thesis.tex",
         "exit 2, names DIR, thesis.tex kept", ("map", "build", "--seq", S, "--out", "{userdir}", "--overwrite"),
         needle="did not make"),
    Case("map-tile-overwrite-user-directory", 1, "map tile --overwrite into DIR holding thesis.tex",
         "exit 2, names DIR, thesis.tex kept",
         ("map", "tile", "{pcd}", "--tile-size", "5", "--out", "{userdir}", "--overwrite"), needle="did not make"),
    Case("track-out-user-directory", 1, "track --out DIR holding thesis.tex", "exit 2 before any work",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--out", "{userdir}"), needle="did not make"),
    Case("demo-out-user-directory", 1, "demo --out DIR holding thesis.tex", "exit 2 before any work",
         ("demo", "--out", "{userdir}"), needle="did not make"),
    # ... nor another kind of blockloc's own output
    Case("sim-out-map-store", 1, "sim --out a map store", "exit 2: not a simulated dataset, the store kept",
         ("sim", "--out", "{store}"), needle="not a simulated dataset"),
    Case("track-out-map-store", 1, "track --out a map store", "exit 2 before any work: not a results folder",
         ("track", "--seq", S, "--map", M, "--init", "gt", "--out", "{store}"), needle="not a results folder"),
    Case("map-build-overwrite-results", 1, "map build --overwrite into a results folder (poses of a run)",
         "exit 2: not a map store (it replaced any blockloc output)",
         ("map", "build", "--seq", S, "--out", "{results}", "--overwrite"), needle="not a map store"),
])


@pytest.fixture()
def places(tiny_world, tmp_path):
    """The placeholders' values: the tiny world's session and map, a scratch root, a user's file
    and directory, a small global PCD, a ground-truth file and the bad config files."""
    import numpy as np

    from blockloc.maps.pcd import write_pcd
    from . import tiny

    user = tmp_path / "thesis"
    user.mkdir()
    (user / "thesis.tex").write_text("years of work")
    (tmp_path / "notes.txt").write_text("mine")
    rng = np.random.default_rng(0)
    write_pcd(tmp_path / "global.pcd", rng.uniform(-10, 10, (2000, 3)).astype(np.float32))
    tiny.write_config(tmp_path / "bad_voxel.yaml", map={"voxel_size_m": -1})
    (tmp_path / "bad_rate.yaml").write_text("imu:\n  rate_hz: .nan\n")
    (tmp_path / "bad_count.yaml").write_text("registration:\n  max_iterations: 0\n")
    (tmp_path / "bad_ratio.yaml").write_text("registration:\n  outlier_ratio: 1.5\n")
    (tmp_path / "empty.yaml").write_text("")
    (tmp_path / "list.yaml").write_text("- map\n- tracking\n")
    import shutil

    shutil.copytree(tiny_world["map"], tmp_path / "store")
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "metrics.json").write_text('{"frames": 1, "processed": 1, "estimated": 1}')
    (tmp_path / "results" / "poses.tum").write_text("# a run's poses\n")
    return {"sess": tiny_world["session"], "map": tiny_world["map"], "root": tmp_path,
            "store": tmp_path / "store", "results": tmp_path / "results",
            "file": tmp_path / "notes.txt", "userdir": user, "pcd": tmp_path / "global.pcd",
            "gt": next(tiny_world["session"].glob("groundtruth_*.csv"))}


def _fill(args, places) -> list[str]:
    return [a.format(**places) for a in args]


def _tree(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


@pytest.mark.parametrize("c", BAD_INVOCATIONS, ids=lambda c: c.id)
def test_bad_invocation(c: Case, places):
    before = _tree(places["root"])
    r = cli_in_process(*_fill(c.args, places))
    assert r.code == c.code, (r.code, r.err)
    assert "Traceback" not in r.err
    assert len(r.err_lines) == 1, r.err_lines  # one line
    line = r.err_lines[0]
    assert line.startswith("error: ")
    assert c.needle in line, line
    assert _tree(places["root"]) == before  # nothing deleted, nothing written: no work was done


@case(4, "`--debug` after the command (`blockloc map changes --map NOMAP --run DIR --debug`), where the "
      "error line's hint '(rerun with --debug for a traceback)' leads a user", "the traceback, as with "
      "`blockloc --debug map changes ...` (was 'error: no such option --debug', exit 2); without it one line")
def test_debug_anywhere_on_the_command_line(tmp_path):
    from .conftest import cli_process

    changes = ("map", "changes", "--map", tmp_path / "nomap", "--run", tmp_path)
    for args in ((*changes, "--debug"), ("--debug", *changes), ("map", "--debug", *changes[1:])):
        r = cli_process(*args)
        assert r.code == 1 and "no such option" not in r.err, (args, r.err)
        assert "Traceback" in r.err and r.err.rstrip().endswith("nomap: no such map directory"), (args, r.err)
    r = cli_process(*changes)
    assert r.code == 2 and r.err == f"error: {tmp_path / 'nomap'}: no such map directory\n"


# ----------------------------------------------------------------------------- --help
COMMANDS = [(), ("eval",), ("sim",), ("map",), ("map", "build"), ("map", "tile"), ("map", "info"),
            ("map", "plot"), ("map", "serve"), ("map", "index"), ("map", "changes"), ("map", "update"),
            ("map", "rollback"), ("init",), ("track",), ("demo",), ("view",), ("node",), ("play",)]


USAGE_METAVARS = {("map", "tile"): "GLOBAL_PCD", ("map", "info"): "MAP", ("map", "plot"): "MAP",
                  ("map", "serve"): "MAP", ("map", "index"): "MAP", ("map", "update"): "MAP",
                  ("map", "rollback"): "MAP", ("view",): "DIR"}


@case(4, "--help of every command", "exit 0; real metavars: no <bool> or <int> on an option, no "
      "{parameter_name} in the usage line (typer 0.29 braces a required argument's metavar: {MAP})")
def test_help_shows_real_metavars():
    for cmd in COMMANDS:
        r = cli_in_process(*cmd, "--help")
        assert r.code == 0, (cmd, r.err)
        text = r.out
        usage = next(ln for ln in text.splitlines() if ln.startswith("Usage:"))
        assert "<bool>" not in text, (cmd, text)
        assert not re.search(r"^\s+--[\w-]+(, -\w)? <\w+>", text, re.M), (cmd, text)  # options: metavars
        assert not re.search(r"\{[a-z_]+\}", usage), (cmd, usage)  # a parameter's name, not its metavar
        if cmd in USAGE_METAVARS:
            assert re.search(rf"\{{?{USAGE_METAVARS[cmd]}\}}?$", usage), (cmd, usage)
        # every option that takes a value shows an upper-case metavar after its name
        for m in re.finditer(r"^\s+(--[\w-]+) ([A-Z][A-Z0-9_,.\[\]|-]*)\s", text, re.M):
            assert m.group(2) not in ("TEXT", "INTEGER", "FLOAT", "PATH"), (cmd, m.group(0))


# ----------------------------------------------------------------------------- the README
def readme_commands(text: str) -> tuple[list[list[str]], list[str]]:
    """(blockloc command lines as argument lists, options named alone) in the README: the lines
    of ```bash blocks and inline `blockloc ...` spans; inline `--option ...` spans."""
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        lines += block.splitlines()
    spans = re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))
    lines += [s for s in spans if s.startswith("blockloc ")]
    commands = []
    for line in lines:
        for part in re.split(r"&&|;|\|", line.split(" #")[0]):
            words = shlex.split(part.replace("*", "X"))
            if words and words[0] == "blockloc":
                commands.append(words[1:])
    options = [s.split()[0] for s in spans if s.startswith("--")]
    return commands, options


def _command_path(words: list[str]) -> tuple[str, ...]:
    groups = {(): {"eval", "sim", "map", "init", "track", "demo", "view", "node", "play"},
              ("map",): {"build", "tile", "info", "plot", "serve", "index", "changes", "update", "rollback"}}
    path: tuple[str, ...] = ()
    for w in words:
        if w in groups.get(path, ()):
            path += (w,)
        else:
            break
    return path


@case(4, "every command and option the README names", "each README command's --help exits 0 and "
      "lists every option the command line uses; every option named alone exists in some command")
def test_readme_commands_and_options_exist():
    commands, options = readme_commands((REPO / "README.md").read_text())
    assert len(commands) >= 8 and options  # the parser found the README's commands
    helps = {}
    for words in commands:
        path = _command_path(words)
        if path not in helps:
            r = cli_in_process(*path, "--help")
            assert r.code == 0, (path, r.err)
            helps[path] = r.out
        for w in words:
            if w.startswith("--"):
                assert re.search(rf"(^|\s){re.escape(w.split('=')[0])}\b", helps[path], re.M), (words, w)
    for path in COMMANDS:
        helps.setdefault(path, cli_in_process(*path, "--help").out)
    every = "\n".join(helps.values())
    for opt in options:
        assert re.search(rf"(^|\s){re.escape(opt)}\b", every, re.M), opt
