"""How long numba spent compiling kernels during a block of code.

blockloc's kernels are compiled on their first call after an install and cached beside the
sources (``cache=True``); later processes load them in milliseconds. On a fresh clone the first
``blockloc init`` or ``demo`` compiles the NDT and branch-and-bound kernels inside the timed search
(measured: 120 s of a 133 s init on 2 loaded cores, 9.9 s once cached), so a search time that
includes it says nothing about the search. :class:`CompileClock` measures that share through
numba's event API, so that callers can report it apart.
"""

from __future__ import annotations

import threading
import time


class CompileClock:
    """Context manager: ``seconds`` = wall time numba spent compiling while it was open.

    Counted as wall time during which at least one compilation runs: nested compilations (a kernel
    compiling the kernels it calls) and compilations in several threads at once (the search's
    windows run side by side) count once, so ``seconds`` never exceeds the time the block took.
    """

    def __init__(self) -> None:
        self.seconds = 0.0
        self._lock = threading.Lock()
        self._active = 0
        self._t0 = 0.0
        self._listener = None

    def __enter__(self) -> "CompileClock":
        try:
            from numba.core import event
        except ImportError:  # numba is a dependency; without its event API report 0
            return self
        clock = self

        class _Listener(event.Listener):
            def on_start(self, ev) -> None:
                with clock._lock:
                    if clock._active == 0:
                        clock._t0 = time.perf_counter()
                    clock._active += 1

            def on_end(self, ev) -> None:
                with clock._lock:
                    if clock._active == 0:  # a compile that began before the clock was opened
                        return
                    clock._active -= 1
                    if clock._active == 0:
                        clock.seconds += time.perf_counter() - clock._t0

        self._listener = _Listener()
        event.register("numba:compile", self._listener)
        return self

    def __exit__(self, *exc) -> None:
        if self._listener is not None:
            from numba.core import event

            event.unregister("numba:compile", self._listener)
            self._listener = None


class Deadline:
    """A search's time budget that numba's compiling does not spend: :meth:`passed` once
    ``time.perf_counter()`` reaches ``at`` (seconds; inf: never) plus the compile time ``clock`` (a
    :class:`CompileClock`, open while the search runs) counted after ``since`` of its seconds.

    Why: on a fresh install the first no-hint search compiles its kernels inside the search (50 s
    on the campus, 2 cores); counted against ``max_search_s`` (10 s) it stopped after its first
    stage with nothing verified, where the same call once compiled verifies the pose.
    """

    def __init__(self, at: float, clock: CompileClock | None = None, since: float = 0.0) -> None:
        self.at = float(at)
        self.clock = clock
        self.since = float(since)

    def passed(self) -> bool:
        compiling = self.clock.seconds - self.since if self.clock is not None else 0.0
        return time.perf_counter() - compiling >= self.at


NEVER = Deadline(float("inf"))
