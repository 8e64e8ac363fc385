"""How much of a second core a second process gets on this machine: the same single-threaded
work timed alone and as two processes at once (CPU time per process). A shared or
hyper-threaded host, or memory bandwidth shared by the two, shows here as CPU time that grows when
the twin runs. This bounds any two-worker speed-up (issue 19's local:2 vs serial).

    python -m bench.cores [--repeats 3]

Two kinds of work: a pure-Python loop (compute, no memory traffic) and a numpy voxel-hash pass
over 2M points (memory-bound, like deskewing and voxel-summing a scan). Writes docs/bench/cores.md.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "cores.md"


def python_loop(n: int = 40_000_000) -> None:
    s = 0
    for i in range(n):
        s += i * i % 7


def numpy_voxel_hash(reps: int = 120) -> None:
    import numpy as np

    pts = np.random.default_rng(0).standard_normal((2_000_000, 3))
    for _ in range(reps):
        v = np.floor(pts / 0.2).astype(np.int64)
        key = (v[:, 0] * 73856093) ^ (v[:, 1] * 19349663) ^ (v[:, 2] * 83492791)
        np.unique(key[:200_000])


WORK = {"pure-Python loop": python_loop, "numpy voxel hash, 2M points": numpy_voxel_hash}


def _timed(name: str, q) -> None:
    t0 = time.process_time()
    WORK[name]()
    q.put(time.process_time() - t0)


def cpu_times(name: str, n: int) -> list[float]:
    """CPU seconds of each of ``n`` processes running ``WORK[name]`` at the same time."""
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    procs = [ctx.Process(target=_timed, args=(name, q)) for _ in range(n)]
    for p in procs:
        p.start()
    out = [q.get() for _ in procs]
    for p in procs:
        p.join()
    return out


def main(argv: list[str] | None = None) -> int:
    from bench.__main__ import machine

    from blockloc.fileio import atomic_write_text

    ap = argparse.ArgumentParser(prog="python -m bench.cores", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    rows = []
    for name in WORK:
        alone, paired = [], []
        for _ in range(args.repeats):  # alternate, so drifts of the host's clock hit both
            alone += cpu_times(name, 1)
            paired += cpu_times(name, 2)
        a, p = statistics.median(alone), statistics.median(paired)
        rows.append(f"| {name} | {a:.2f} | {p:.2f} | {a / p:.2f} | {2 * a / p:.2f}x |")
        print(rows[-1], flush=True)
    cmd = "python -m bench.cores " + " ".join(argv if argv is not None else sys.argv[1:])
    text = "\n".join([
        "## Two processes on the two cores", "",
        f"Command: `{cmd.strip()}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}). Machine: {machine()}. "
        f"Load average (1 min) {load0:.1f} before, {os.getloadavg()[0]:.1f} after.", "",
        f"The same single-threaded work, timed as CPU seconds per process: alone, then two processes at once "
        f"(medians of {args.repeats} rounds, alternating). Efficiency = alone / paired. The last column is "
        "the speed-up two processes can reach over one on this work.", "",
        "| work | CPU alone [s] | CPU paired [s] | efficiency | two-process ceiling |",
        "|---|---|---|---|---|", *rows, ""])
    atomic_write_text(Path(OUT), text)
    print(OUT)
    return 0


if __name__ == "__main__":
    sys.exit(main())
