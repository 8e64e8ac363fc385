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

    Nested compilations (a kernel compiling the kernels it calls) are counted once: only the
    outermost compile of each thread adds to the total.
    """

    def __init__(self) -> None:
        self.seconds = 0.0
        self._local = threading.local()
        self._listener = None

    def __enter__(self) -> "CompileClock":
        try:
            from numba.core import event
        except ImportError:  # numba is a dependency; without its event API report 0
            return self
        clock = self

        class _Listener(event.Listener):
            def on_start(self, ev) -> None:
                depth = getattr(clock._local, "depth", 0)
                if depth == 0:
                    clock._local.t0 = time.perf_counter()
                clock._local.depth = depth + 1

            def on_end(self, ev) -> None:
                depth = getattr(clock._local, "depth", 1) - 1
                clock._local.depth = depth
                if depth == 0:
                    clock.seconds += time.perf_counter() - clock._local.t0

        self._listener = _Listener()
        event.register("numba:compile", self._listener)
        return self

    def __exit__(self, *exc) -> None:
        if self._listener is not None:
            from numba.core import event

            event.unregister("numba:compile", self._listener)
            self._listener = None
