"""``blockloc demo``: the whole system on the `small` simulated world, from nothing, in minutes.

Steps: build the block map of the world's mapping session (simulated on the fly: only its
keyframes are rendered; cached where ``blockloc track --seq sim:small/loc`` looks for it),
initialize on the localization session by branch-and-bound from a noisy position hint (yaw
unknown), track it with the sliding window while it is simulated scan by scan, evaluate against
ground truth and write the results folder (poses, metrics, plots, report.html, a Foxglove
recording). Nothing but the map is written to disk: a full-density session would be gigabytes.
The recipes are :mod:`blockloc.app.runs` (``prepare_small_world``, ``demo_session``).
"""

from __future__ import annotations

from pathlib import Path

from blockloc.app.runs import demo_session, prepare_small_world, write_run_report
from blockloc.commands.common import check_results_dir, console, progress, results_dir, track_bytes
from blockloc.commands.init import compile_note
from blockloc.commands.track import print_track_summary, print_where, run_observers, run_tracking


def demo_command(out: Path | None, max_frames: int | None, record: bool = True) -> None:
    con = console()
    out_dir = results_dir(out, "demo")
    check_results_dir(out_dir, track_bytes(max_frames or 1, record))

    def say(msg: str) -> None:
        con.print(f"[bold cyan]demo[/] {msg}")

    with progress("block map build tasks") as report:
        world, cfg = prepare_small_world(say=say, progress=report)
    session, hint = demo_session(cfg, world=world, out=out_dir, observers=run_observers(out_dir, record=record),
                                 say=say)
    say(f"global init: branch-and-bound around the hint ({hint[0]:.1f}, {hint[1]:.1f}), yaw unknown")
    ok = False
    try:
        res = run_tracking(session, mode="pose", hint=hint, out_dir=out_dir, max_frames=max_frames)
        ok = True
    finally:
        if session.result is not None:
            write_run_report(session, session.result, out_dir, quiet=not ok)
    init = res.metrics.get("init") or {}
    if init.get("time_s") is not None:
        say(f"global init: {init.get('error_m', float('nan')):.2f} m from the truth in {init['time_s']:.2f} s"
            f"{compile_note(init)}")
    print_track_summary(con, res.metrics, res.out_dir)
    print_where(con, out_dir)
