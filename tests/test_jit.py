"""CompileClock: the numba compile time inside a block, counted once for nested kernels."""

import time

import numba
import numpy as np

from blockloc.jit import CompileClock


def _kernels():
    # defined here, uncached, so every call of this helper compiles anew
    @numba.njit(cache=False)
    def inner(x):
        return np.sqrt(x * x + 1.0)

    @numba.njit(cache=False)
    def outer(a):
        s = 0.0
        for v in a:
            s += inner(v)
        return s

    return outer


def test_compile_time_is_measured_once_and_within_the_wall_time():
    outer = _kernels()
    a = np.arange(10.0)
    t0 = time.perf_counter()
    with CompileClock() as jit:
        outer(a)  # compiles outer and, nested, inner
    wall = time.perf_counter() - t0
    assert 0.0 < jit.seconds <= wall


def test_nested_compiles_are_not_counted_twice():
    outer = _kernels()
    events = []
    from numba.core import event

    class Rec(event.Listener):
        def on_start(self, ev):
            events.append(("start", time.perf_counter()))

        def on_end(self, ev):
            events.append(("end", time.perf_counter()))

    rec = Rec()
    event.register("numba:compile", rec)
    try:
        with CompileClock() as jit:
            outer(np.arange(3.0))
    finally:
        event.unregister("numba:compile", rec)
    starts = [t for k, t in events if k == "start"]
    ends = [t for k, t in events if k == "end"]
    assert len(starts) >= 2  # outer and the nested inner
    outermost = max(ends) - min(starts)
    summed = sum(e - s for s, e in zip(sorted(starts), sorted(ends)))
    assert jit.seconds <= outermost + 1e-3 < summed


def test_a_compiled_kernel_costs_nothing_and_the_listener_is_removed():
    outer = _kernels()
    outer(np.arange(3.0))
    with CompileClock() as jit:
        outer(np.arange(5.0))
    assert jit.seconds == 0.0
    other = _kernels()
    other(np.arange(3.0))  # compiles after the block closed: not counted
    assert jit.seconds == 0.0
