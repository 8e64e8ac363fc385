"""CompileClock: the numba compile time inside a block, counted once for nested kernels."""

import time

import numba
import numpy as np

from blockloc.jit import NEVER, CompileClock, Deadline


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


def test_compiles_in_two_threads_at_once_count_their_wall_time_once():
    """init's searched windows run side by side: their compiles overlap in time, and the clock
    must not count that time twice (seen: init --json's time_s came out negative)."""
    import threading

    from numba.core import event

    def compiling(delay_s, hold_s):
        time.sleep(delay_s)
        event.start_event("numba:compile")
        time.sleep(hold_s)
        event.end_event("numba:compile")

    t0 = time.perf_counter()
    with CompileClock() as jit:
        threads = [threading.Thread(target=compiling, args=a) for a in ((0.0, 0.3), (0.1, 0.3))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    wall = time.perf_counter() - t0
    assert 0.35 < jit.seconds <= wall  # the union of [0, 0.3] and [0.1, 0.4]; summed it is 0.6


def test_the_place_index_load_time_leaves_out_a_compile_inside_it_and_the_cold_search_never_goes_negative(
        monkeypatch):
    """CI on a fresh install: the place index was built (compiling kernels) inside the first search,
    its load time kept the compile that the caller's clock also took off: ``search_s`` -1.12 s."""
    from blockloc.app.runs import cold_start
    from blockloc.global_init import place_index as pi
    from blockloc.global_init.relocalize import GlobalLocalizer

    def build_compiling(map_source, params):
        time.sleep(0.05)
        _kernels()(np.arange(4.0))  # compiles here, as numba does on a fresh install
        return "index"

    monkeypatch.setattr(pi, "index_for_source", build_compiling)
    loc = object.__new__(GlobalLocalizer)  # the property needs only these
    loc._place_index, loc.map, loc.params = None, None, type("P", (), {"place_index_params": None})()
    t0 = time.perf_counter()
    with CompileClock() as jit:
        assert loc.place_index == "index"
    wall = time.perf_counter() - t0
    assert jit.seconds > 0.0
    assert 0.04 < loc._index_load_s <= wall - jit.seconds + 1e-3
    cold = cold_start(0.01, wall, {"index_load_s": loc._index_load_s}, jit.seconds)
    assert cold["search_s"] >= 0.0 and cold["total_s"] >= 0.0


def test_a_deadline_is_pushed_back_by_the_time_spent_compiling():
    outer = _kernels()
    with CompileClock() as jit:
        dl = Deadline(time.perf_counter() + 0.01, jit)
        outer(np.arange(3.0))  # compiles: longer than the 10 ms budget
        assert jit.seconds > 0.01
        assert not dl.passed()  # what is left took microseconds
        already = Deadline(time.perf_counter() + 0.01, jit, since=jit.seconds)  # compiling before it is not
        time.sleep(0.02)
        assert already.passed()
    assert not NEVER.passed()
    assert Deadline(time.perf_counter()).passed()  # no clock: wall time alone
