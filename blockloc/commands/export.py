"""``blockloc export dynamicmap``: a sequence in the DynamicMap Benchmark layout."""

from __future__ import annotations

from pathlib import Path


def dynamicmap_command(seq: str, out: Path, poses: Path | None, start: int, frames: int | None, step: int,
                       min_range: float, max_range: float, data_root: str | None) -> None:
    from blockloc.app.dynamicmap import export_dynamicmap
    from blockloc.commands.common import progress
    from blockloc.errors import DatasetError
    from blockloc.fileio import check_replaceable
    from blockloc.outdir import DYNAMIC_MAP, claim_output

    if min_range >= max_range:
        raise DatasetError(f"--min-range {min_range} m: expected less than --max-range {max_range} m")
    # before any work: never replace what blockloc did not make, nor another kind of its output
    check_replaceable(out, "--out", (DYNAMIC_MAP,), "a DynamicMap export")
    claim_output(out, "--out")
    with progress("export dynamicmap") as cb:
        s = export_dynamicmap(seq, out, poses=poses, start=start, frames=frames, step=step,
                              min_range_m=min_range, max_range_m=max_range, data_root=data_root, progress=cb)
    what = (f"gt_cloud.pcd: {s.points} points, {s.dynamic_points} dynamic" if s.labelled
            else "no labels: scans only, no gt_cloud.pcd")
    print(f"wrote {s.out}: {s.scans} scans (frames {s.first_frame}..{s.last_frame}), {what}")
