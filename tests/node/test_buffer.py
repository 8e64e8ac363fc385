"""The node's scan buffer: bounded in every regime, evenly thinned while a global init runs, and a
catch-up that ends by itself."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.node.buffer import DENSE_HEAD, ScanBuffer


def stamps_of(buf: ScanBuffer) -> list[float]:
    return [s for s, _ in buf._items]


def test_tracking_keeps_the_newest_queue_size_scans():
    buf = ScanBuffer(2, 10)
    buf.end_backlog()  # tracking from the start (nothing waited)
    dropped = [d for k in range(5) for d in buf.push(0.1 * k, k)]
    assert dropped == [0, 1, 2] and [buf.pop(), buf.pop(), buf.pop()] == [3, 4, None]


def test_a_backlog_never_exceeds_its_bound_and_stays_evenly_spaced():
    buf = ScanBuffer(2, 12)
    dropped = [d for k in range(50) for d in buf.push(0.1 * k, k)]
    assert len(buf) == 12 and len(dropped) == 38
    s = np.array(stamps_of(buf))
    assert s[0] == 0.0 and s[-1] == pytest.approx(4.9)  # the scan being searched and the newest stay
    # the first scans after it at the sensor's rate (the velocity is learnt on them), then even
    assert np.diff(s[:DENSE_HEAD + 1]) == pytest.approx([0.1] * DENSE_HEAD)
    gaps = np.diff(s[DENSE_HEAD:])
    even = (s[-1] - s[DENSE_HEAD]) / len(gaps)
    assert gaps.max() <= 2.0 * even, gaps  # no hole: the tracker can follow the chain


def test_a_worker_faster_than_the_scans_catches_up_without_dropping():
    buf = ScanBuffer(2, 40)
    for k in range(14):  # a global init of 1.4 s at 10 Hz
        assert buf.push(0.1 * k, k) == []
    buf.end_backlog()
    assert buf.catching_up
    got, k = [], 14
    while buf.catching_up or len(buf):
        got.append(buf.pop())
        if len(got) % 3 == 0:  # one scan arrives while three are processed
            assert buf.push(0.1 * k, k) == []
            k += 1
    assert got == list(range(k)) and buf.bound == 2 and not buf.catching_up


def test_a_worker_slower_than_the_scans_still_ends_its_catch_up():
    buf = ScanBuffer(2, 40)
    k = 0
    for _ in range(100):
        buf.push(0.1 * k, k)
        k += 1
    buf.end_backlog()
    pops = 0
    while buf.catching_up:
        buf.pop()
        pops += 1
        for _ in range(2):  # two scans arrive per scan processed
            buf.push(0.1 * k, k)
            k += 1
        assert len(buf) <= 40
    assert pops <= 42 and buf.bound == 2 and len(buf) <= 2


def test_a_worker_winning_slowly_drops_nothing_at_the_end_of_its_catch_up():
    """29 scans waited through a global init; the worker then takes 0.6 of the scan period (two
    scans come per three processed): it drains them without dropping one (a bound shrinking at
    every pop dropped scans near the end)."""
    buf = ScanBuffer(2, 40)
    for k in range(29):
        assert buf.push(0.1 * k, k) == []
    buf.end_backlog()
    got, dropped, k = [], [], 29
    while buf.catching_up or len(buf):
        got.append(buf.pop())
        if len(got) % 3 != 0:
            dropped += buf.push(0.1 * k, k)
            k += 1
        assert len(buf) <= 40
    assert dropped == [] and got == list(range(k)) and buf.bound == 2


def test_a_new_global_init_opens_the_backlog_again():
    buf = ScanBuffer(2, 6)
    buf.end_backlog()
    buf.start_backlog()
    assert buf.bound == 6 and buf.backlog
    with pytest.raises(ValueError):
        ScanBuffer(3, 2)
