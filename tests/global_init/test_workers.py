"""The localizer's worker threads (``GlobalLocalizer._map``)."""

import threading
import time
from types import SimpleNamespace

import pytest

from blockloc.global_init.relocalize import GlobalLocalizer


def test_a_failing_call_is_raised_only_after_every_other_call_ended():
    """A call still running after another failed would write to the localizer (its structure sets)
    while the next search runs: ``_map`` raises only when every call has ended."""
    fake = SimpleNamespace(params=SimpleNamespace(refine_workers=2), _pool=None, place_source=None,
                           coverage_source=None)
    ended = threading.Event()

    def fn(i):
        if i == 0:
            raise ValueError("a sparse target")
        time.sleep(0.3)
        ended.set()
        return i

    try:
        with pytest.raises(ValueError, match="sparse target"):
            GlobalLocalizer._map(fake, fn, [0, 1])
        assert ended.is_set()
        assert GlobalLocalizer._map(fake, lambda i: i * i, [1, 2, 3]) == [1, 4, 9]  # in order
    finally:
        fake._pool.shutdown()
