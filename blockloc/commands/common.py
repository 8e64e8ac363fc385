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
    """The user stopped the command after its work was saved (a tracking run's partial results);
    ``exit_code`` is 130 (SIGINT) or 143 (SIGTERM)."""

    def __init__(self, message: str, exit_code: int = 130) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class Stopped(BaseException):
    """SIGINT or SIGTERM arrived (see :func:`install_signal_handlers`): raised in the main thread
    where it runs, it unwinds every ``with`` and ``finally`` on its way out (map builds and the
    simulator remove their temp directories), then the CLI prints one line and exits 130 / 143.

    A BaseException, as KeyboardInterrupt is, so that ``except Exception`` (a frame skipped, an
    observer's failure logged) never swallows it; not a KeyboardInterrupt, which typer would turn
    into a silent exit code."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.exit_code = EXIT_CODES.get(signum, 128 + signum)


#: The signals :func:`install_signal_handlers`' handler received, in order.
RECEIVED: list[int] = []


def _raise_stopped(signum, _frame):
    RECEIVED.append(signum)
    raise Stopped(signum)


def raise_if_stopped() -> None:
    """Raise :class:`Stopped` again if a signal arrived and the work goes on: an exception raised
    by a signal handler can be swallowed where it lands (a module's import turns it into an
    ImportError, a fallback catches that). Progress callbacks call this: the next step stops."""
    if RECEIVED:
        raise Stopped(RECEIVED[-1])


def install_signal_handlers() -> None:
    """Make SIGINT and SIGTERM raise :class:`Stopped` (main thread only). A signal the parent set
    to be ignored (``nohup``, a background job of a script) stays ignored."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    for sig in EXIT_CODES:
        if signal.getsignal(sig) in (signal.SIG_DFL, signal.default_int_handler):
            signal.signal(sig, _raise_stopped)


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
    from blockloc.app.catalog import config_for_sequence

    return config_for_sequence(seq, config, overrides=parse_sets(sets or []), overrides_source="--set")


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


def results_dir(out: Path | None, name: str) -> Path:
    """``out``, or ``results/<name>_<time>`` (name made file-safe)."""
    if out is not None:
        return Path(out)
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name.strip("/")).strip("_") or "run"
    return Path("results") / f"{safe[-60:]}_{time.strftime('%Y%m%d-%H%M%S')}"


def check_results_dir(out: Path, need_bytes: int = 0) -> None:
    """Before any work: ``out`` must be absent, empty or a results folder blockloc wrote (not
    another kind of blockloc output: a map store or a dataset is not replaced by results),
    writable, with ``need_bytes`` free, and not in use by another blockloc run (its lock is taken)."""
    from blockloc.fileio import RESULTS
    from blockloc.outdir import claim_output

    claim_output(out, "--out", need_bytes=need_bytes, kinds=RESULTS, kind="a results folder")


#: Bytes a tracking run writes per frame, an upper estimate for the free-space check: poses and
#: diagnostics rows (~1 kB) and, when recorded, the frame's MCAP messages (the deskewed scan and
#: the local map's changes, compressed; measured on the tiny fault-suite drive: see
#: docs/robustness.md).
TRACK_BYTES_PER_FRAME, TRACK_RECORD_BYTES_PER_FRAME = 2_000, 200_000


def track_bytes(frames: int, record: bool) -> int:
    """The free space a tracking run of ``frames`` frames needs (a floor of 1 MiB for the
    report and metrics)."""
    return 2**20 + frames * (TRACK_BYTES_PER_FRAME + (TRACK_RECORD_BYTES_PER_FRAME if record else 0))


#: Seconds without a progress line after which a piped progress prints one anyway.
HEARTBEAT_S = 30.0


def _line_to_stderr(text: str) -> None:
    """``text`` and its newline in one write: print() writes them apart, and a line another thread
    writes between the two (the command's last message on Ctrl-C) would run into this one."""
    sys.stderr.write(text + "\n")
    sys.stderr.flush()


@contextlib.contextmanager
def progress(label: str, total: int | None = None, *, err_console=None,
             heartbeat_s: float | None = None) -> Iterator[Callable[[int, int | None], None]]:
    """A progress callback ``(done, total)``: a rich bar in a terminal; otherwise a line to
    stderr every 10%, and every ``heartbeat_s`` (default :data:`HEARTBEAT_S`) without one (also
    while a long step, such as a global initialization, calls no callback), so piped output
    shows progress too."""
    import threading

    heartbeat_s = HEARTBEAT_S if heartbeat_s is None else heartbeat_s

    from rich.console import Console

    con = err_console or Console(stderr=True)
    if con.is_terminal:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        bar = Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                       console=con, transient=True)
        task = bar.add_task(label, total=total)
        def update(done: int, tot: int | None = None) -> None:
            raise_if_stopped()
            bar.update(task, completed=done, total=tot or total)

        with bar:
            yield update
        return
    t0 = time.monotonic()
    state = {"last_t": t0, "last_pct": -10.0, "done": 0, "total": total, "last_line": None}
    lock = threading.Lock()

    def line(done: int, tot: int | None) -> str:
        pct = f" ({100.0 * done / tot:.0f}%)" if tot else ""
        return f"{label}: {done}/{tot or '?'}{pct}"

    def report(done: int, tot: int | None = None) -> None:
        raise_if_stopped()
        tot = tot or total
        now = time.monotonic()
        pct = 100.0 * done / tot if tot else 0.0
        with lock:
            # counting again (the next session of a simulation), or a total that grew (a map
            # build plans its next tasks as results come in): 10% steps of the new count
            if done < state["done"] or pct < state["last_pct"]:
                state["last_pct"] = -10.0
            state["done"], state["total"] = done, tot
            text = line(done, tot)
            if text != state["last_line"] and (
                    (tot and (pct - state["last_pct"] >= 10.0 or done == tot)) or now - state["last_t"] >= heartbeat_s):
                state["last_t"], state["last_pct"], state["last_line"] = now, pct, text
                _line_to_stderr(text)

    stop = threading.Event()

    def heartbeat() -> None:
        while not stop.wait(heartbeat_s / 4.0):
            now = time.monotonic()
            with lock:
                if now - state["last_t"] >= heartbeat_s:
                    state["last_t"] = now
                    _line_to_stderr(f"{line(state['done'], state['total'])}, working for {now - t0:.0f} s")

    beat = threading.Thread(target=heartbeat, name=f"progress {label}", daemon=True)
    beat.start()
    try:
        yield report
    finally:
        stop.set()
        beat.join()


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

    @property
    def name(self) -> str:
        """SIGINT / SIGTERM (the signal that asked to stop)."""
        return signal.Signals(self.signal).name if self.signal is not None else "SIGINT"


@contextlib.contextmanager
def interruptible() -> Iterator[StopRequest]:
    """Turn the first SIGINT/SIGTERM into a stop request (a second one raises :class:`Stopped`
    at once). Outside the main thread nothing is installed."""
    import threading

    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, _frame):
        if stop.signal is not None:
            raise Stopped(signum)
        stop.signal = signum
        name = signal.Signals(signum).name
        again = "Ctrl-C" if signum == signal.SIGINT else name
        print(f"{name} received: stopping after the current frame ({again} again to abort at once)",
              file=sys.stderr, flush=True)

    old = {s: signal.signal(s, handler) for s in EXIT_CODES if signal.getsignal(s) is not signal.SIG_IGN}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)
