"""Run benchmarks and assemble docs/benchmarks.md.

    python -m bench all            # every benchmark, then assemble
    python -m bench ndt maps       # some of them, then assemble
    python -m bench assemble       # only rebuild docs/benchmarks.md from docs/bench/*.md

Each benchmark is a module ``bench.<name>`` with a ``main()`` that writes its own fragment
``docs/bench/<name>.md`` (machine, exact command, medians). Order follows ORDER.
"""

from __future__ import annotations

import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FRAGMENTS = ROOT / "docs" / "bench"
ORDER = ["datasets", "evaluation", "sim", "ndt", "maps", "global_init", "tracking", "scaling", "campus", "campus_keyframes", "campus_backends",
         "server", "summary"]  # summary last: it compares the fragments before it with the papers


def machine() -> str:
    import os

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


def assemble() -> Path:
    parts = [
        "# Benchmarks",
        "",
        "Regenerate everything with `python -m bench all` (one section: `python -m bench <name>`).",
        f"Last assembled {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on: {machine()}.",
        "Each section names the exact command that produced it and when it ran; figures are medians",
        "unless stated otherwise.",
        "",
    ]
    names = [n for n in ORDER if (FRAGMENTS / f"{n}.md").exists()]
    names += sorted(p.stem for p in FRAGMENTS.glob("*.md") if p.stem not in ORDER)
    for name in names:
        parts.append((FRAGMENTS / f"{name}.md").read_text().rstrip() + "\n")
    out = ROOT / "docs" / "benchmarks.md"
    tmp = out.with_suffix(".md.tmp")
    tmp.write_text("\n".join(parts))
    tmp.replace(out)
    return out


def main(argv: list[str]) -> int:
    names = argv or ["all"]
    if names == ["assemble"]:
        print(assemble())
        return 0
    if names == ["all"]:
        names = [n for n in ORDER if (ROOT / "bench" / f"{n}.py").exists()]
    failed = []
    for name in names:
        t0 = time.time()
        print(f"== bench.{name}", flush=True)
        rc = subprocess.call([sys.executable, "-m", f"bench.{name}"], cwd=ROOT)
        print(f"== bench.{name}: exit {rc} after {time.time() - t0:.0f} s", flush=True)
        if rc:
            failed.append(name)
    print(assemble())
    if failed:
        print("failed:", ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
