"""Campus, every map backend side by side over the session's first stretch (Table II on campus).

    python -m bench.campus_backends [--minutes 10]

``bench.campus`` with block, grid, srt and global in lockstep, its own checkpoint directory and
fragment docs/bench/campus_backends.md; extra arguments are passed through (e.g. ``--map``).
"""

from __future__ import annotations

import sys

from bench.campus import ROOT, main as campus_main


def main(argv: list[str] | None = None) -> int:
    from blockloc.cache import cache_root

    argv = list(sys.argv[1:] if argv is None else argv)
    base = ["--backends", "block,grid,srt,global", "--out", str(ROOT / "docs" / "bench" / "campus_backends.md"),
            "--state", str(cache_root() / "bench" / "campus_run_4backends")]
    if "--minutes" not in argv:
        base += ["--minutes", "10"]
    return campus_main(base + argv)


if __name__ == "__main__":
    sys.exit(main())
