"""In-memory sequences for the Dask build tests: one that reads slowly (so a worker can be killed
while it works) and one whose scans fail part way (a task that raises). Workers import this
module (the tests put tests/ on their path)."""

from __future__ import annotations

import time

from .synthetic import MemorySequence


class SlowSequence(MemorySequence):
    """A MemorySequence whose every scan read takes ``delay_s`` longer (same scans)."""

    def __init__(self, *args, delay_s: float = 0.1, **kw):
        super().__init__(*args, **kw)
        self.delay_s = delay_s

    def frame(self, index):
        time.sleep(self.delay_s)
        return super().frame(index)


class FailingSequence(MemorySequence):
    """A MemorySequence whose scans after ``fail_after`` cannot be read (OSError)."""

    def __init__(self, *args, fail_after: int = 10, **kw):
        super().__init__(*args, **kw)
        self.fail_after = fail_after

    def frame(self, index):
        if index > self.fail_after:
            raise OSError(f"disk unplugged reading frame {index}")
        return super().frame(index)
