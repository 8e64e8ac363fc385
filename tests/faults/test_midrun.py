"""Finding 10 (issue 40): the disk fills, or the results folder is removed, while ``blockloc track``
writes. The run stops with one line naming the file and the cause (exit 1); every row written is
whole; the metrics of what was done are written (into the space the run kept in reserve)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from .cases import case
from .conftest import Outcome, Running, small_fs


def _track(world: dict, out: Path) -> Running:
    return Running("track", "--seq", world["long"], "--map", world["map"], "--init", "gt", "--config",
                   world["config"], "--out", out)


def _finish(run: Running, timeout: float = 600) -> Outcome:
    out = run.proc.stdout.read().decode(errors="replace")
    run.proc.wait(timeout)
    run._reader.join(10)
    return Outcome(run.proc.returncode, out, run.err)


def _rows_whole(path: Path, fields: int | None = None) -> list[str]:
    data = path.read_bytes()
    assert data.endswith(b"\n"), f"{path.name} ends in a torn row"
    rows = [r for r in data.decode().splitlines() if r and not r.startswith("#")]
    if fields is not None:
        assert all(len(r.split()) == fields for r in rows), path.name
    return rows


def _poses_written(out: Path, n: int):
    def ready() -> bool:
        p = out / "poses.tum"
        return p.is_file() and p.read_bytes().count(b"\n") > n
    return ready


@case(10, "the disk fills while `blockloc track` writes (a 40 MiB tmpfs filled by another file after "
      "10 poses)", "exit 1, one line naming a file of --out and 'No space left on device'; poses.tum and "
      "diagnostics.csv end in whole rows; metrics.json holds the frames done; no *.partial left unnamed")
def test_disk_full_during_track(tiny_world, tmp_path):
    with small_fs(tmp_path / "fs", "40m") as fs:
        out = fs / "res"
        run = _track(tiny_world, out)
        run.wait_for(_poses_written(out, 10))
        with open(fs / "filler", "wb") as fh:  # another program fills the disk
            try:
                while True:
                    fh.write(bytes(1 << 16))
                    fh.flush()
            except OSError:
                pass
        r = _finish(run)
        assert r.code == 1, r.err[-3000:]
        lines = [ln for ln in r.err_lines if ln.startswith("error: ")]
        assert len(lines) == 1 and "Traceback" not in r.err, r.err[-3000:]
        assert lines[0].startswith(f"error: {out}/") and "No space left on device" in lines[0], lines[0]
        assert "tracking stopped after" in lines[0]
        poses = _rows_whole(out / "poses.tum", 8)
        diag = _rows_whole(out / "diagnostics.csv")
        m = json.loads((out / "metrics.json").read_text())
        assert 10 <= len(poses) < 120 and m["frames"] < 120 and m["interrupted"] is True
        assert len(diag) - 1 <= m["frames"] <= len(diag)  # the frame whose row failed is counted
        left = [p.name for p in out.glob("*.partial")]
        assert all(name in lines[0] for name in left), (left, lines[0])


@case(10, "the results folder is removed while `blockloc track` writes into it",
      "exit 1, one line naming poses.tum (or diagnostics.csv) and 'removed during the run'; the run stops "
      "at once (was: tracked on, writing into deleted files)")
def test_out_removed_during_track(tiny_world, tmp_path):
    out = tmp_path / "res"
    run = _track(tiny_world, out)
    run.wait_for(_poses_written(out, 10))
    held = os.open(out / "poses.tum", os.O_RDONLY)
    try:
        # One removal: the run may add a file meanwhile ("directory not empty": the folder stays), or
        # notice at once and write what it did anew; removing again would take that away.
        shutil.rmtree(out, ignore_errors=True)
        assert os.fstat(held).st_nlink == 0  # the file the run writes is gone
    finally:
        os.close(held)
    r = _finish(run)
    assert r.code == 1, r.err[-3000:]
    lines = [ln for ln in r.err_lines if ln.startswith("error: ")]
    assert len(lines) == 1 and "Traceback" not in r.err, r.err[-3000:]
    assert "removed during the run" in lines[0] and "tracking stopped after" in lines[0], lines[0]
    done = int(lines[0].split("tracking stopped after ")[1].split()[0])
    assert done < 120
    # what was done is kept: the metrics and the whole trajectory (held in memory) are written anew
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == done and len((out / "poses_kitti.txt").read_text().splitlines()) >= done - 1
