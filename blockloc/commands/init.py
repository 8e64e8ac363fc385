"""``blockloc init``: global initialization of one frame of a sequence against a map store.

The work is :func:`blockloc.app.runs.run_init` (the scan prepared as tracking prepares it, the
global localizer with the configured engine); this prints the result, with ground truth also its
error.
"""

from __future__ import annotations

import json
import math

from blockloc.app.runs import run_init
from blockloc.commands.common import config_for, console, parse_pose_hint
from blockloc.errors import GlobalInitError


#: why a best that passed the fit tests is not the answer (``InitResult.stats['unjudged']``)
UNJUDGED = ("only its NDT fit could be judged (too little structure in the static band to test its coverage) "
            "and it is not the clear best (global_init.unjudged_end_min_fitness, "
            "global_init.unjudged_end_min_structure_fitness, global_init.unjudged_end_margin)")


def compile_note(info: dict) -> str:
    """" (+N s compiling kernels, ...)" when the kernels were compiled in the timed part, else ""."""
    c = info.get("compile_s") or 0.0
    return f" (+{c:.0f} s compiling kernels, first run after install only)" if c >= 0.5 else ""


def print_result(summ: dict, console) -> None:
    """Human-readable result (rich console)."""
    from rich.table import Table

    if "x" in summ:
        console.print(f"T_map_body  x {summ['x']:.3f}  y {summ['y']:.3f}  z {summ['z']:.3f} m   "
                      f"roll {math.degrees(summ['roll']):.2f}  pitch {math.degrees(summ['pitch']):.2f}  "
                      f"yaw {math.degrees(summ['yaw']):.2f} deg")
    console.print(f"score {summ['score']:.3f}  fitness {summ['fitness']:.3f}  verified {summ['verified']}  "
                  f"ambiguous {summ['ambiguous']}  time {summ['time_s']:.2f} s{compile_note(summ)}")
    if "error_m" in summ:
        console.print(f"against ground truth: {summ['error_m']:.3f} m, {summ['error_deg']:.2f} deg")
    if summ.get("stats", {}).get("timed_out") and not summ["verified"]:
        console.print("[yellow]not found: the search stopped at its budget (global_init.max_search_s; "
                      "--set global_init.max_search_s=0 searches the whole map however long it takes)[/yellow]")
    if summ.get("stats", {}).get("unjudged"):
        console.print(f"[yellow]not verified: {UNJUDGED}[/yellow]")
    elif summ["ambiguous"]:
        console.print("[yellow]warning: ambiguous: another verified candidate far from this one fits almost "
                      "as well (repeated structure); check the candidates or give a tighter hint[/yellow]")
    table = Table("#", "x", "y", "z", "yaw deg", "score", "fitness", "verified")
    for i, c in enumerate(summ["candidates"]):
        table.add_row(str(i), f"{c['x']:.2f}", f"{c['y']:.2f}", f"{c['z']:.2f}", f"{math.degrees(c['yaw']):.1f}",
                      f"{c['score']:.3f}", f"{c['fitness']:.3f}", str(c["verified"]))
    console.print(table)


def init_command(seq, frame, map_path, pose_hint, window, yaw_window, json_out, data_root, config,
                 poses=None, sets=None) -> None:
    """The command: run, print (JSON or tables), fail (exit 2) when nothing was verified."""
    cfg = config_for(seq, config, sets)
    hint = parse_pose_hint(pose_hint) if pose_hint is not None else None
    res, summ = run_init(seq, frame, map_path, cfg=cfg, hint=hint, window_m=window, yaw_window_deg=yaw_window,
                         data_root=data_root, poses=poses)
    if json_out:
        print(json.dumps(summ))
    else:
        print_result(summ, console())
    if not res.verified:
        why = f": {UNJUDGED}" if res.stats.get("unjudged") else ""
        raise GlobalInitError(f"no verified match (best score {res.score:.3f}, fitness {res.fitness:.3f}){why}")
