"""What every command shares: the console, option parsing, config for a sequence, progress that
shows in a terminal and in a log, results folders, and honest interruption (Ctrl-C, SIGTERM)."""

from __future__ import annotations

import contextlib
import logging
import math
import signal
import sys
import time
from pathlib import Path
from typing import Callable, Iterator

from blockloc.errors import BlocklocError

log = logging.getLogger("blockloc")

#: Exit codes of an interrupted command (the shell's convention: 128 + the signal number).
EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}


class Interrupted(BlocklocError):
    """The user stopped the command; ``exit_code`` is 130 (SIGINT) or 143 (SIGTERM)."""

    def __init__(self, message: str, exit_code: int = 130) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def console():
    """The rich console (stdout)."""
    from rich.console import Console

    return Console()


def parse_pose_hint(text: str, option: str = "--pose-hint") -> tuple[float, float, float | None]:
    """'x,y' or 'x,y,yaw' (metres, metres, radians; map frame) -> (x, y, yaw or None)."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (2, 3) or not all(math.isfinite(v) for v in vals):
        raise BlocklocError(f"{option} {text!r}: expected x,y or x,y,yaw (metres, radians)")
    return vals[0], vals[1], (vals[2] if len(vals) == 3 else None)


def parse_deltas(text: str, option: str = "--rpe-deltas") -> tuple[float, ...]:
    """'1,10,100' -> (1.0, 10.0, 100.0); an empty string -> () (no RPE)."""
    try:
        deltas = tuple(float(v) for v in text.replace(" ", "").split(",") if v)
    except ValueError:
        deltas = (-1.0,)
    if any(not (d > 0 and math.isfinite(d)) for d in deltas):
        raise BlocklocError(f"{option} {text!r}: expected positive distances in metres, e.g. 1,10,100")
    return deltas


def config_for(seq: str | None, config: str | None, sets: list[str] | None = None):
    """The config: ``--config`` (a file or preset name) when given, else the preset that fits
    the sequence (``SequenceRef.preset``), else the defaults; then every ``--set SECTION.KEY=VALUE``
    (VALUE read as YAML: numbers, true/false, lists)."""
    from blockloc.config import load_config, preset_for_sequence

    return load_config(config or (preset_for_sequence(seq) if seq else None), overrides=parse_sets(sets or []))


def parse_sets(sets: list[str]) -> dict:
    """['registration.method=vgicp', 'map.grid_n=3'] -> {'registration': {'method': 'vgicp'}, ...}."""
    import yaml

    out: dict = {}
    for item in sets:
        key, sep, value = item.partition("=")
        parts = key.strip().split(".")
        if not sep or len(parts) != 2 or not all(parts):
            raise BlocklocError(f"--set {item!r}: expected SECTION.KEY=VALUE, e.g. registration.method=vgicp")
        try:
            parsed = yaml.safe_load(value) if value.strip() else ""
        except yaml.YAMLError:
            parsed = value
        out.setdefault(parts[0], {})[parts[1]] = parsed
    return out


def map_params(map_cfg, kind: str) -> tuple:
    """The map-building settings a cached map depends on (part of its cache key)."""
    size = map_cfg.block_size_m if kind == "block" else map_cfg.tile_size_m
    return (size, map_cfg.keyframe_distance_m, map_cfg.keyframe_angle_deg, map_cfg.voxel_size_m)


def results_dir(out: Path | None, name: str) -> Path:
    """``out``, or ``results/<name>_<time>`` (name made file-safe)."""
    if out is not None:
        return Path(out)
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name.strip("/")).strip("_") or "run"
    return Path("results") / f"{safe[-60:]}_{time.strftime('%Y%m%d-%H%M%S')}"


def check_results_dir(out: Path) -> None:
    """Before any work: ``out`` must be absent, empty or a results folder blockloc wrote."""
    from blockloc.fileio import check_replaceable

    check_replaceable(out, "--out")


@contextlib.contextmanager
def progress(label: str, total: int | None = None, *, err_console=None) -> Iterator[Callable[[int, int | None], None]]:
    """A progress callback ``(done, total)``: a rich bar in a terminal; otherwise a log line to
    stderr every 10% (and at least every 30 s), so piped output shows progress too."""
    from rich.console import Console

    con = err_console or Console(stderr=True)
    if con.is_terminal:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        bar = Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                       console=con, transient=True)
        task = bar.add_task(label, total=total)
        with bar:
            yield lambda done, tot=None: bar.update(task, completed=done, total=tot or total)
        return
    state = {"last_t": time.monotonic(), "last_pct": -10.0}

    def report(done: int, tot: int | None = None) -> None:
        tot = tot or total
        now = time.monotonic()
        pct = 100.0 * done / tot if tot else 0.0
        if (tot and (pct - state["last_pct"] >= 10.0 or done == tot)) or now - state["last_t"] >= 30.0:
            state["last_t"], state["last_pct"] = now, pct
            print(f"{label}: {done}/{tot or '?'}" + (f" ({pct:.0f}%)" if tot else ""), file=sys.stderr, flush=True)

    yield report


class StopRequest:
    """Set by SIGINT/SIGTERM while :func:`interruptible` is active; the work checks it between
    steps, finishes the current one and stops (so what was computed is kept)."""

    def __init__(self) -> None:
        self.signal: int | None = None

    def __call__(self) -> bool:
        return self.signal is not None

    @property
    def exit_code(self) -> int:
        return EXIT_CODES.get(self.signal, 130)


@contextlib.contextmanager
def interruptible() -> Iterator[StopRequest]:
    """Turn the first SIGINT/SIGTERM into a stop request (a second SIGINT raises
    KeyboardInterrupt at once). Outside the main thread nothing is installed."""
    import threading

    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, _frame):
        if stop.signal is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        stop.signal = signum
        print("stopping after the current frame (Ctrl-C again to abort)", file=sys.stderr, flush=True)

    old = {s: signal.signal(s, handler) for s in EXIT_CODES}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)
