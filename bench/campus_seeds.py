"""Campus over several seeds (issue 41): one row per seed from ``bench.campus`` runs, median and worst.

    python -m bench.campus --seed 2 --backends block --km 2 --map MAP2 --state S2 --out S2.md   # per seed
    python -m bench.campus_seeds --state S1,S2,S3 --out docs/bench/campus.md

Each ``--state`` is a ``bench.campus`` checkpoint directory of one seed (one run, or consecutive
segments joined with ``bench.campus --merge``); its block backend is read. The section
``--title`` is written into ``--out``, replacing a section of that title and keeping the rest of
the file (``bench.campus`` keeps it too when it rewrites docs/bench/campus.md). Above the table:
each seed's exact commands, when they ran, the load and the map they used.

Per seed: accuracy against ground truth with the error breakdown of ``blockloc eval`` (along-track,
cross-track, the time shift that best explains the along-track error), health (failures,
rejected scans) and time: the core (deskew + registration + smoother, wall) and the whole tracker
step in wall and in the main thread's CPU time (``time.thread_time``), medians per scan, with the
1-min load average beside them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bench.campus import OUT, _sim_name, summarize
from blockloc.fileio import atomic_write_text

TITLE = "Campus over three seeds with the defaults (issue 41)"
#: issue 41's campus targets: median ATE over the seeds, and no failure on any
TARGET_MEDIAN_ATE_M = 0.03


def seed_row(state: Path) -> dict:
    """The block backend's metrics of one ``bench.campus`` checkpoint, with its progress record."""
    from blockloc.app.catalog import open_sequence

    prog = json.loads((state / "progress.json").read_text())
    if prog.get("exact"):
        raise SystemExit(f"--state {state}: a run with error sources off (--exact); this table is of the defaults")
    if "block" not in prog["backends"] or not (state / "block.npz").exists():
        raise SystemExit(f"--state {state}: no block backend checkpoint (block.npz) there")
    seq = open_sequence(prog["sequence"])
    m = summarize(state, "block", seq.ground_truth())
    return {"seed": _sim_name(prog["sequence"])[2], "prog": prog, "m": m, "session_frames": len(seq)}


def replace_section(text: str, title: str, body: str) -> str:
    """``text`` with the ``## title`` section (up to the next ``## `` heading) replaced by
    ``body``, or ``body`` appended when there is none."""
    head = f"## {title}"
    lines = text.splitlines()
    if head in lines:
        i = lines.index(head)
        j = next((k for k in range(i + 1, len(lines)) if lines[k].startswith("## ")), len(lines))
        return "\n".join(lines[:i] + body.rstrip("\n").splitlines() + [""] + lines[j:]).rstrip("\n") + "\n"
    return (text.rstrip("\n") + "\n\n" if text.strip() else "") + body.rstrip("\n") + "\n"


def section(rows: list[dict], title: str = TITLE) -> str:
    f = lambda v, s="{:.3f}": "-" if v is None else s.format(v)  # noqa: E731
    cm = lambda v: "-" if v is None else f"{100 * v:+.1f}"  # noqa: E731
    lines = [f"## {title}", ""]
    for r in rows:
        p = r["prog"]
        cmds = [g["command"] for g in p.get("segments", [])] or [p["command"]]
        cpu = p.get("cpu_s")
        lines += [f"Seed {r['seed']}: " + "; ".join(f"`{c}`" for c in cmds)
                  + (f" (segments joined by `python -m bench.campus --merge ...`; each starts at the ground-truth "
                     f"pose of its first frame, frames {', '.join(str(g['start']) for g in p['segments'])})"
                     if p.get("segments") else "")
                  + f"; started {p['started']}, last checkpoint {p['updated']}, {p['wall_s'] / 60:.1f} min wall"
                  + (f", {cpu / 60:.1f} min CPU of the whole process (ray casting included)" if cpu else "")
                  + f"; load average (1 min) {p['load_start']:.1f} at the start, {p['load_now']:.1f} at the end, "
                  f"mean of samples {p['load_mean']:.1f}"
                  + ("" if p["finished"] else " (**not finished**: still running or stopped)") + ".",
                  f"Map: `{p['map']}` ({p['map_desc']}).", ""]
    lines += ["| seed | frames | km | ATE trans RMSE [m] | ATE max [m] | ATE rot RMSE [deg] | failures | recoveries | "
              "rejected | along-track mean / RMS [cm] | cross-track RMS [cm] | best time shift [ms] | "
              "core median, wall [ms] | step median, wall / CPU [ms] | load mean |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m, p = r["m"], r["prog"]
        shift = m.get("err_time_shift_s")
        lines.append(
            f"| {r['seed']} | {p['start']}..{p['start'] + m['frames'] - 1} | {(m.get('path_length_m') or 0) / 1000:.2f} | "
            f"{f(m.get('ate_trans_rmse_m'))} | {f(m.get('ate_trans_max_m'), '{:.2f}')} | "
            f"{f(m.get('ate_rot_rmse_deg'))} | {m['failures']} | {m['recoveries']} | {m['rejected']} | "
            f"{cm(m.get('err_along_mean_m'))} / {f(m.get('err_along_rms_m') and 100 * m['err_along_rms_m'], '{:.1f}')} | "
            f"{f(m.get('err_cross_rms_m') and 100 * m['err_cross_rms_m'], '{:.1f}')} | "
            f"{f(shift and 1e3 * shift, '{:+.0f}')} | {m['core_ms_median']:.1f} | "
            f"{f(m.get('step_wall_ms_median'), '{:.1f}')} / {f(m.get('step_cpu_ms_median'), '{:.1f}')} | "
            f"{p['load_mean']:.1f} |")
    ates = [r["m"].get("ate_trans_rmse_m") for r in rows]
    if rows and all(a is not None for a in ates):
        med, worst = float(np.median(ates)), max(ates)
        wseed = rows[int(np.argmax(ates))]["seed"]
        fails = sum(r["m"]["failures"] for r in rows)
        ok = lambda c: "met" if c else "**missed**"  # noqa: E731
        lines += ["", f"Over {len(rows)} seed(s): ATE median {med:.3f} m, worst {worst:.3f} m (seed {wseed}); "
                  f"max error {max(r['m'].get('ate_trans_max_m') or 0 for r in rows):.2f} m; rotation RMSE at most "
                  f"{max(r['m'].get('ate_rot_rmse_deg') or 0 for r in rows):.3f} deg; {fails} failures.", "",
                  f"- median ATE <= {TARGET_MEDIAN_ATE_M} m: {med:.3f} m — {ok(med <= TARGET_MEDIAN_ATE_M)}"
                  + ("" if len(rows) >= 3 else f" (on {len(rows)} seed(s) only, 3 asked)") + ".",
                  f"- no failures: {fails} — {ok(fails == 0)}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.campus_seeds", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--state", required=True, metavar="DIR,DIR,...", help="bench.campus --state dirs, one per seed")
    ap.add_argument("--title", default=TITLE, help="the section's heading (without '## ')")
    ap.add_argument("--out", default=str(OUT), help="markdown file to write the section into")
    args = ap.parse_args(argv)
    states = [Path(s) for s in args.state.split(",") if s]
    for s in states:
        if not (s / "progress.json").is_file():
            ap.error(f"--state {s}: not a bench.campus --state directory (no progress.json)")
    rows = sorted((seed_row(s) for s in states), key=lambda r: (r["seed"], r["prog"]["start"]))
    body = section(rows, args.title)
    out = Path(args.out)
    atomic_write_text(out, replace_section(out.read_text() if out.exists() else "", args.title, body))
    print(body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
