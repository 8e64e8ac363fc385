"""Run the fault-injection suite and write ``docs/robustness.md``: every case of
:mod:`tests.faults.cases`' registry with what is injected, what is asserted and its outcome,
optionally beside its outcome on an earlier revision (the suite run against that revision's code).

    python -m tests.faults.report                  # from the repository root; ~5 min on 2 busy cores
    python -m tests.faults.report --before REV     # also run it on REV's blockloc (twice the time)
"""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

from . import cases as registry

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "robustness.md"


def load_registry() -> list[tuple[str, registry.Case]]:
    """Import every test module of the suite (their tables and ``@case`` marks fill the registry)."""
    pkg = importlib.import_module(__package__)  # tests.faults, or faults as pytest names it
    for mod in pkgutil.iter_modules(pkg.__path__):
        if mod.name.startswith("test_"):
            importlib.import_module(f"{__package__}.{mod.name}")
    return list(registry.REGISTRY)


def run_suite(xml: Path, root: Path = REPO) -> float:
    """Run the suite of ``root`` (a checkout) with a JUnit report; returns its wall time, s."""
    import os

    t0 = time.monotonic()
    env = dict(os.environ, PYTHONPATH=str(root))
    subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider", f"--junitxml={xml}",
                    "tests/faults"], cwd=root, env=env, check=False)
    return time.monotonic() - t0


def run_suite_on(rev: str, xml: Path, tmp: Path) -> None:
    """This suite run against the code of git revision ``rev`` (its tree, with today's tests/faults)."""
    import shutil

    tree = tmp / "before"
    tree.mkdir()
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
    shutil.rmtree(tree / "tests" / "faults", ignore_errors=True)
    shutil.copytree(REPO / "tests" / "faults", tree / "tests" / "faults",
                    ignore=shutil.ignore_patterns("__pycache__"))
    run_suite(xml, tree)


def outcomes(xml: Path) -> dict[str, str]:
    """pytest test name (``test_x[id]``) -> passed | failed | skipped."""
    out = {}
    for tc in ET.parse(xml).getroot().iter("testcase"):
        kinds = {child.tag for child in tc}
        out[tc.get("name")] = ("failed" if kinds & {"failure", "error"} else
                               "skipped" if "skipped" in kinds else "passed")
    return out


def outcome_of(name: str, results: dict[str, str]) -> str:
    """A registered name's outcome; one registered without a parameter id covers all its ids."""
    found = [v for k, v in results.items() if k == name or ("[" not in name and k.startswith(name + "["))]
    if not found:
        return "not run"
    for kind in ("failed", "skipped"):
        if kind in found:
            return kind
    return "passed"


def render(entries, results: dict[str, str], wall_s: float, before: dict[str, str] | None = None,
           before_rev: str | None = None) -> str:
    by_finding = defaultdict(list)
    for name, c in entries:
        by_finding[c.finding].append((name, c, outcome_of(name, results)))
    total = len(entries)
    passed = sum(outcome_of(n, results) == "passed" for n, _ in entries)
    unregistered = sorted(n for n in results if not any(n == r or ("[" not in r and n.startswith(r + "["))
                                                         for r, _ in entries))
    lines = [
        "# Robustness: the fault-injection suite",
        "",
        "Every fault of issues 16 and 40 (\"never lose a user's work\") injected into a real `blockloc` run on tiny",
        "inputs (an NCLT-layout session of 40 or 120 scans written with `write_session`, its scan-folder",
        "twin, a 7-block store), and what the suite asserts about it: the exit code, one line naming the",
        "file or option, no traceback, no user file deleted, partial results kept. The suite is",
        "`tests/faults/` (part of `python -m pytest`); this page is generated from its case tables and a run:",
        "",
        "```bash",
        "python -m tests.faults.report                  # runs tests/faults, rewrites docs/robustness.md",
        "python -m tests.faults.report --before REV     # adds the column \"before\": the suite on REV's code",
        "```",
        "",
        f"Last run: {passed} of {total} cases passed, suite wall time {wall_s:.0f} s (development machine,",
        "2 cores shared with other jobs: a noisy figure).",
        "",
    ]
    lines += OWNERSHIP
    if before is not None:
        failed_before = sum(outcome_of(n, before) != "passed" for n, _ in entries)
        lines += [f"*before*: the same suite against the code of `{before_rev}` (`--before {before_rev}`): "
                  f"{failed_before} of {total} cases did not pass there. A case that passed there verifies "
                  "a fix made earlier (issues 13, 16 and 20, for findings 1-7).", ""]
    head = "| case | injected | asserted | outcome |" + (" before |" if before is not None else "")
    rule = "|---|---|---|---|" + ("---|" if before is not None else "")
    for finding in sorted(by_finding):
        lines += [f"## Finding {finding}: {registry.FINDINGS[finding]}", "", head, rule]
        for name, c, outcome in by_finding[finding]:
            what = f"{c.what}: `{' '.join(('blockloc',) + c.args)}`" if c.args else c.what
            expect = c.expect + (f"; message has `{c.needle}`" if c.needle else "")
            row = f"| `{name.removeprefix('test_')}` | {_cell(what)} | {_cell(expect)} | {outcome} |"
            if before is not None:
                row += f" {outcome_of(name, before)} |"
            lines.append(row)
        lines.append("")
    if unregistered:
        lines += ["## Tests not in the registry", ""] + [f"- `{n}`" for n in unregistered] + [""]
    return "\n".join(lines)


#: How the fixes of issue 40 work (written by hand: the cases below test it).
OWNERSHIP = [
    "## How blockloc knows what it made (issue 40)",
    "",
    "- **Marker.** Every directory blockloc writes carries `.blockloc-output.json`: a JSON object with",
    "  blockloc's own key (`\"blockloc_output\": 1`), the `kind` (map store, simulated dataset, results",
    "  folder, session, plot folder) and, for a directory written whole, the `files` it wrote",
    "  (`blockloc/outdir.py`). The *content* is checked; no file name proves anything (a folder holding",
    "  `thesis.tex` and any `manifest.json` used to be replaced whole).",
    "- **Replace only that.** `--overwrite` (and `sim`, `track`, `demo`, `eval --plot`) replace or write",
    "  into a folder only when it is absent, empty, or blockloc's of the command's kind *and* holds no file",
    "  blockloc did not write; otherwise one line names the folder and up to five foreign files, and",
    "  nothing is deleted. A map store's place index added later (`map index`) is blockloc's: its manifest",
    "  lists it.",
    "- **Folders from before the marker** stay replaceable only when their format proves them blockloc's:",
    "  a map store by a manifest with blockloc's `version`, `kind` (block/grid) and `entries` (each with",
    "  `file` and `sha256`) -- what it may hold is then what that manifest lists; a results folder by a",
    "  `metrics.json` object with `frames`, `processed` and `estimated` (its files: the names a run writes);",
    "  a simulated dataset by `sim.json` with `preset`, `seed` and `sessions` (its sessions' trees are",
    "  taken as blockloc's without further proof); a session by `blockloc_session.json` with its extrinsics.",
    "  A user who wrote such a file by hand can still fool this; a store whose manifest is foreign is not",
    "  replaced.",
    "- **Before any work** each writing command checks its output: writable (a probe file is made and",
    "  removed: permission bits say nothing to root or to a read-only mount), free space for what it will",
    "  write, and not in use: a lock file `.NAME.blockloc-lock` beside the output holds the PID of the run",
    "  using it; a second run refuses naming that PID; a lock whose process is gone (or whose PID now runs",
    "  something that is not blockloc) is taken over.",
    "- **Free-space estimates** (coarse, per command): `track`/`demo` 1 MiB + 2 kB a frame + 200 kB a frame",
    "  recorded (the tiny drive's recording measured 1,824,362 bytes for 40 frames of 5000 points, 45 kB a",
    "  frame: `blockloc track --seq <tiny 40-scan session> --map <its map> --init gt --config <tiny config>`,",
    "  one run; 200 kB leaves room for scans ~4x larger); `map build`/`map tile` 16 MiB or twice the input",
    "  PCD; `sim` 16 MiB; `map index` a quarter of the store; `eval --plot` 1 MiB.",
    "- **Mid-run.** Rows of `poses.tum` and `diagnostics.csv` are appended with one write each; a row that",
    "  cannot be written whole is cut off again. A results folder keeps 1 MiB allocated (`.reserve`), freed",
    "  when a write fails so that `metrics.json`, the KITTI poses and `report.html` still fit. The run stops",
    "  with one line naming the file, the cause, the frames done, whether the metrics were written and any",
    "  `*.partial` left; exit 1. A results folder removed mid-run is noticed at the next row (its files are",
    "  unlinked) and written anew with the metrics and the whole trajectory held in memory.",
    "- **Not covered:** permissions changed mid-run are not injected (the suite runs as root, and a",
    "  read-only remount is refused while the run holds files open); the free-space estimate of `map build",
    "  --seq` and `sim` is a floor, not a function of the drive.",
    "",
]


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m tests.faults.report", description=__doc__.splitlines()[0])
    ap.add_argument("--before", metavar="REV", help="also run the suite on the code of this git revision")
    ap.add_argument("--before-xml", metavar="FILE", help="the JUnit report of such a run (instead of running it)")
    args = ap.parse_args(argv)
    entries = load_registry()
    before = None
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "faults.xml"
        wall = run_suite(xml)
        results = outcomes(xml)
        if args.before_xml:
            before = outcomes(Path(args.before_xml))
        elif args.before:
            run_suite_on(args.before, Path(tmp) / "before.xml", Path(tmp))
            before = outcomes(Path(tmp) / "before.xml")
    DOC.write_text(render(entries, results, wall, before, args.before))
    print(f"wrote {DOC}: {len(entries)} cases")


if __name__ == "__main__":
    main()
