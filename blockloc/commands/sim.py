"""``blockloc sim``: simulate a world's sessions and write them (NCLT layout or ROS bags)."""

from __future__ import annotations

import sys
from pathlib import Path


#: Free space a simulation needs at least (the `tiny` preset writes ~5 MiB).
SIM_MIN_BYTES = 16 * 2**20


def sim_command(preset: str, seed: int, out: Path, fmt: str, azimuth_steps: int | None, months: str = "") -> None:
    from blockloc.commands.common import progress
    from blockloc.errors import SimError
    from blockloc.fileio import SIM_DATASET, check_replaceable
    from blockloc.sim.writer import generate_dataset

    # before any work: never replace what blockloc did not make, nor another kind of its output
    check_replaceable(out, "--out", SIM_DATASET, "a simulated dataset")
    try:
        month_list = tuple(int(m) for m in months.split(",") if m.strip())
    except ValueError:
        raise SimError(f"--months {months!r}: expected month numbers separated by commas, e.g. 3,12") from None
    from blockloc.sim.changes import sessions_for_months

    sessions_for_months(month_list)  # checked before any work
    from blockloc.outdir import claim_output

    claim_output(out, "--out", need_bytes=SIM_MIN_BYTES)  # writable, room, no other run on it
    overrides = {} if azimuth_steps is None else {"azimuth_steps": azimuth_steps}
    current = {"session": None}
    with progress(f"sim {preset}") as cb:
        def report(session: str, done: int, total: int) -> None:
            if session != current["session"]:
                current["session"] = session
                print(f"sim {preset}: session {session}, {total} frames", file=sys.stderr, flush=True)
            cb(done, total)

        path = generate_dataset(preset, seed, out, fmt, progress=report, months=month_list, **overrides)
    print(f"wrote {path}")
