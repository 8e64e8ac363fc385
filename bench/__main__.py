"""Run benchmarks and assemble docs/benchmarks.md.

    python -m bench all            # every benchmark, then assemble
    python -m bench ndt maps       # some of them, then assemble
    python -m bench assemble       # only rebuild docs/benchmarks.md (headline table + section index)
    python -m bench seeds --seeds 1,2,3   # one benchmark with its own options (after its name)

Each benchmark is a module ``bench.<name>`` with a ``main()`` that writes its own fragment
``docs/bench/<name>.md`` (machine, exact command, medians). Order follows ORDER.
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

from blockloc.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
FRAGMENTS = ROOT / "docs" / "bench"
ORDER = ["run", "datasets", "evaluation", "sim", "realism", "ndt", "maps", "global_init", "reloc", "real", "tracking",
         "tracking_engines", "scan_errors", "recording",
         "scaling", "campus", "campus_nominal", "campus_mounted", "campus_plants", "campus_budget", "campus_earlier", "campus_backends", "campus_engines", "cores", "city_full", "city_recorded", "city_4k", "city", "city-runs",
         "lifelong", "dynamic", "dynamic_build", "server", "summary"]  # summary last: it compares the fragments before it with the papers
#: Fragments made from other runs' outputs (their commands take those runs): not run by ``all``.
FROM_RUNS = {"campus_budget"}


def machine() -> str:
    try:
        import psutil

        mem = f"{psutil.virtual_memory().total / 2**30:.0f} GiB"
    except ImportError:
        mem = "?"
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, {mem}, Python {platform.python_version()}"


#: The day the realistic simulator (issue 15) replaced the earlier one: a fragment dated before it
#: measured the easier world, and the assembled file says so above it.
REALISTIC_SIM_SINCE = "2026-12-01"


def stale_note(text: str) -> str | None:
    """A warning line for a fragment whose first date is before :data:`REALISTIC_SIM_SINCE`."""
    m = re.search(r"\b(\d{4}-\d{2}-\d{2})\b", text)
    if m and m.group(1) < REALISTIC_SIM_SINCE:
        return (f"> Measured {m.group(1)}, on the earlier simulator (before the realistic world of "
                f"{REALISTIC_SIM_SINCE}); not re-run since: figures on simulated data are optimistic.")
    return None


#: The hand-kept table of headline figures (each copied from a section) that opens benchmarks.md.
HEADLINE = "headline"


def _headings(text: str, name: str) -> str:
    """The fragment's section titles (its ``## `` lines; some fragments hold several sections)."""
    titles = [line[3:].strip() for line in text.splitlines() if line.startswith("## ")]
    return "; ".join(titles) or name


def assemble() -> Path:
    """docs/benchmarks.md: the headline table, then one row per section linking its fragment
    (docs/bench/<name>.md holds the section itself, with its command and plots)."""
    parts = [
        "# Benchmarks",
        "",
        "Regenerate everything with `python -m bench all` (one section: `python -m bench <name>`).",
        f"Last assembled {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on: {machine()}.",
        "Each section names the exact command that produced it and when it ran; figures are medians",
        "unless stated otherwise.",
        "",
    ]
    head = FRAGMENTS / f"{HEADLINE}.md"
    if head.exists():
        # the fragment links its neighbours (x.md) and plots (x.png); this file is one level up
        text = re.sub(r"(\]\()([^/():]+\.(?:md|png)\))", r"\1bench/\2", head.read_text().rstrip())
        parts += [text, ""]
    names = [n for n in ORDER if (FRAGMENTS / f"{n}.md").exists()]
    names += sorted(p.stem for p in FRAGMENTS.glob("*.md") if p.stem not in ORDER and p.stem != HEADLINE)
    parts += ["## Sections", "", "| section | first date in it | file |", "|---|---|---|"]
    for name in names:
        text = (FRAGMENTS / f"{name}.md").read_text()
        m = re.search(r"\b(\d{4}-\d{2}-\d{2})\b", text)
        date = m.group(1) if m else "-"
        if stale_note(text):
            date += " (earlier simulator: figures on simulated data are optimistic)"
        parts.append(f"| {_headings(text, name)} | {date} | [bench/{name}.md](bench/{name}.md) |")
    out = ROOT / "docs" / "benchmarks.md"
    atomic_write_text(out, "\n".join(parts) + "\n")
    return out


def _commit() -> str:
    """HEAD's short hash, noting uncommitted changes to tracked files (taken before the run: the
    run itself rewrites docs/)."""
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        return rev + (" (with uncommitted changes)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"


def write_run_fragment(spent: dict, started, total_s: float, load0: float, commit: str = "") -> None:
    """docs/bench/run.md: how long the whole suite took, part by part (the issue asks to say so)."""
    from blockloc.cache import cache_root
    from blockloc.fileio import atomic_write_text

    lines = ["## The whole suite in one command", "",
             f"`python -m bench all`, started {time.strftime('%Y-%m-%d %H:%M UTC', started)} at commit "
             f"{commit or _commit()}, took **{total_s / 60:.0f} min** on {machine()} (load average {load0:.1f} at the "
             f"start, {os.getloadavg()[0]:.1f} at the end). Cache directory `{cache_root()}`"
             + (" (set by $BLOCKLOC_CACHE)" if os.environ.get("BLOCKLOC_CACHE") else "") + ": parts that find "
             "their simulated world or map there reuse it; an empty cache makes every part build its own.", "",
             "| part | wall time [min] | exit |", "|---|---|---|"]
    lines += [f"| {n} | {s / 60:.1f} | {rc} |" for n, (s, rc) in spent.items()]
    atomic_write_text(FRAGMENTS / "run.md", "\n".join(lines) + "\n\n")


def main(argv: list[str]) -> int:
    first_option = next((i for i, a in enumerate(argv) if a.startswith("-")), len(argv))
    names, options = argv[:first_option] or ["all"], argv[first_option:]
    if options and len(names) != 1 or options and names[0] in ("all", "assemble"):
        print("options go to one named benchmark: python -m bench NAME --option ...", file=sys.stderr)
        return 2
    if names == ["assemble"]:
        print(assemble())
        return 0
    everything = names == ["all"]
    if everything:
        names = [n for n in ORDER if (ROOT / "bench" / f"{n}.py").exists() and n not in FROM_RUNS]
    failed, spent = [], {}
    started, load0, t_all, commit = time.gmtime(), os.getloadavg()[0], time.time(), _commit()
    for name in names:
        t0 = time.time()
        print(f"== bench.{name}", flush=True)
        rc = subprocess.call([sys.executable, "-m", f"bench.{name}", *options], cwd=ROOT)
        spent[name] = (time.time() - t0, rc)
        print(f"== bench.{name}: exit {rc} after {spent[name][0]:.0f} s", flush=True)
        if rc:
            failed.append(name)
    if everything:
        write_run_fragment(spent, started, time.time() - t_all, load0, commit)
    print(assemble())
    if failed:
        print("failed:", ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
