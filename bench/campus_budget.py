"""The campus block ATE split by error source: runs of ``bench.campus --exact PARTS`` side by side.

    python -m bench.campus_budget --run none=DIR --run slam=DIR --run extrinsic,lidar=DIR ...

Each ``DIR`` is a ``bench.campus --state`` directory of the same frames with the ``--exact`` parts
named before ``=`` (``none``: the realistic world as benchmarked). Per run: ATE, the body-frame
error's mean and standard deviation per axis (x forward, y left, z up), the share of the error a
2 s low-pass filter keeps (slow: map-shaped; fast: scan-to-scan jitter) and its correlation with the
first run's error (the same error along the route means the same cause). Writes
docs/bench/campus_budget.md.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from blockloc.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "campus_budget.md"
LOWPASS_SCANS = 20  # 2 s at 10 Hz


def body_errors(state: Path) -> tuple[dict, np.ndarray, dict]:
    """(progress.json, (N, 3) position error of the block backend in the true body frame, m,
    the tracker's counters)."""
    from bench._track import STATUS_CODES
    from bench.campus import _sim_name, exact_sequence
    from blockloc.app.catalog import open_sequence

    prog = json.loads((state / "progress.json").read_text())
    loc = [x for x in prog.get("exact", []) if x != "slam"]
    seq = exact_sequence(*_sim_name(prog["sequence"]), loc) if loc else open_sequence(prog["sequence"])
    z = np.load(state / "block.npz")
    ok = z["status"] != STATUS_CODES["uninitialized"]
    P = z["poses"][ok]
    G = seq.ground_truth().interpolate(z["stamps"][ok])
    e = np.einsum("nji,nj->ni", G[:, :3, :3], P[:, :3, 3] - G[:, :3, 3])
    return prog, e, json.loads(str(z["counters"]))


def lowpass(e: np.ndarray, k: int = LOWPASS_SCANS) -> np.ndarray:
    """(N, 3) running mean over k scans (edges: 'same' convolution)."""
    return np.stack([np.convolve(e[:, i], np.ones(k) / k, mode="same") for i in range(3)], axis=1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.campus_budget", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", action="append", required=True, metavar="PARTS=DIR")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    cmd = "python -m bench.campus_budget " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    runs = []
    for item in args.run:
        parts, sep, d = item.partition("=")
        if not sep or not (Path(d) / "progress.json").exists():
            ap.error(f"--run {item!r}: expected PARTS=DIR with DIR a bench.campus --state directory")
        runs.append((parts, Path(d)))
    lines = ["## Campus block ATE by error source (issue 15)", "", f"Command: `{cmd}`.", "",
             "Same frames, block backend; each row a `bench.campus --exact PARTS` run (its command below). "
             "Body frame: x forward, y left, z up. Slow share: the part of the error's mean square a "
             f"{LOWPASS_SCANS / 10:g} s running mean keeps. Corr.: per-axis correlation of the error with the first row's.",
             "", "| error sources off | ATE [m] | body mean x/y/z [m] | body std x/y/z [m] | slow share | corr. x/y | rejected |",
             "|---|---|---|---|---|---|---|"]
    first = None
    cmds = []
    for parts, d in runs:
        prog, e, counters = body_errors(d)
        k = LOWPASS_SCANS
        sm = lowpass(e)[k:-k]
        slow = float((sm ** 2).sum() / (e[k:-k] ** 2).sum())
        if first is None:
            first = e
        n = min(len(first), len(e))
        corr = [float(np.corrcoef(first[:n, i], e[:n, i])[0, 1]) for i in range(2)]
        ate = float(np.sqrt((e ** 2).sum(axis=1).mean()))
        f3 = lambda v: " / ".join(f"{x:.3f}" for x in v)  # noqa: E731
        lines.append(f"| {parts} | {ate:.3f} | {f3(e.mean(0))} | {f3(e.std(0))} | {slow:.2f} | "
                     f"{corr[0]:.2f} / {corr[1]:.2f} | {counters['rejected']} |")
        cmds.append(f"- {parts}: `{prog['command']}` ({prog['frames_done']} scans from frame {prog['start']}, "
                    f"started {prog['started']}, load mean {prog['load_mean']:.1f})")
    lines += ["", "Runs:", *cmds, ""]
    text = "\n".join(lines) + "\n"
    atomic_write_text(Path(args.out), text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
