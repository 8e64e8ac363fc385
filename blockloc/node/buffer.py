"""``ScanBuffer``: the scans waiting for the node's worker, always bounded.

Two regimes:

- **tracking**: at most ``queue_size`` scans wait; a scan past that drops the oldest (the newest
  is what a robot needs, and the tracker bridges a short gap with its motion model);
- **backlog**: while a global initialization runs (it blocks the worker for a second or more)
  and while the worker catches up after it, up to ``backlog_size`` scans wait. Past that, the
  waiting scan whose removal leaves the smallest gap between its neighbours is dropped (never the
  newest, nor the oldest and the ``DENSE_HEAD`` after it: right after a fresh initialization the
  velocity is unknown, and the first scans must come at the sensor's rate for the tracker to
  learn it; seen: 0.2 s gaps at 5 m/s lost the robot). The waiting scans stay a chain from the
  scan being searched to the newest, evenly spaced after its head, which the tracker then follows
  from the verified pose to the present (the catch-up) instead of jumping from a pose verified
  seconds ago to the newest scan.

A catch-up ends by itself. From :meth:`end_backlog` on, scans arriving and scans popped are
counted: while the worker pops faster than scans arrive (fewer than ``SLOW_RATIO`` arrivals per
pop so far) the waiting scans fall on their own and the bound stays (no scan is dropped: a
bound that shrank at every pop whatever the worker's speed dropped scans at the end of a catch-up
the worker was winning, seen at 1x with a worker taking ~0.4 of the scan period); once it is
not, the bound shrinks by one scan at every :meth:`pop` (never below ``queue_size``), so a
worker slower than the scans arrive drains the backlog within about ``backlog_size`` scans
(dropping more, evenly). Not thread-safe: the node holds its lock around every call.
"""

from __future__ import annotations

from typing import Any

DENSE_HEAD = 3  # scans after the oldest a backlog keeps at the sensor's rate
SLOW_RATIO = 0.75  # arrivals per pop during a catch-up from which the bound shrinks (a worker winning
# more slowly than that would stay seconds behind for tens of seconds: dropping, evenly, is better)


class ScanBuffer:
    """Waiting scans as (stamp s, item), oldest first. queue_size >= 1, backlog_size >= queue_size."""

    def __init__(self, queue_size: int, backlog_size: int) -> None:
        if queue_size < 1 or backlog_size < queue_size:
            raise ValueError(f"queue_size {queue_size}, backlog_size {backlog_size}: expected "
                             "1 <= queue_size <= backlog_size")
        self.queue_size = int(queue_size)
        self.backlog_size = int(backlog_size)
        self._items: list[tuple[float, Any]] = []
        self._bound = self.backlog_size  # the node starts initializing
        self._catching_up = False
        self.backlog = True
        self._arrived = self._popped = 0  # scans pushed and popped since the catch-up started

    def __len__(self) -> int:
        return len(self._items)

    @property
    def bound(self) -> int:
        """How many scans may wait now."""
        return self._bound

    def start_backlog(self) -> None:
        """A global initialization starts: up to ``backlog_size`` scans may wait."""
        self.backlog, self._catching_up = True, False
        self._bound = self.backlog_size

    def end_backlog(self) -> None:
        """The worker tracks again: it catches up on what waits, with a bound shrinking at every pop."""
        if not self.backlog:
            return
        self.backlog = False
        self._catching_up = len(self._items) >= self.queue_size
        self._arrived = self._popped = 0
        if not self._catching_up:
            self._bound = self.queue_size

    @property
    def catching_up(self) -> bool:
        """Scans that waited through a global initialization are being worked off."""
        return self._catching_up

    def push(self, stamp: float, item: Any) -> list[Any]:
        """Add a scan (stamp in s, arrival order); returns the items dropped to stay in bound."""
        self._items.append((float(stamp), item))
        self._arrived += int(self._catching_up)
        dropped = []
        while len(self._items) > self._bound:
            dropped.append(self._items.pop(self._victim())[1])
        return dropped

    def pop(self) -> Any | None:
        """The oldest waiting scan's item, or None."""
        if not self._items:
            return None
        item = self._items.pop(0)[1]
        if self._catching_up:
            self._popped += 1
            if self._arrived >= SLOW_RATIO * self._popped:  # not winning: make it end
                self._bound = max(self.queue_size, self._bound - 1)
            if len(self._items) < self.queue_size:  # room for the scan arriving while this one is processed
                self._catching_up = False
                self._bound = self.queue_size
        return item

    def _victim(self) -> int:
        """Index of the scan to drop: the oldest when tracking, else the inner one leaving the smallest gap."""
        if not (self.backlog or self._catching_up) or len(self._items) < 3:
            return 0
        stamps = [s for s, _ in self._items]
        first = 1 + DENSE_HEAD if len(stamps) > DENSE_HEAD + 2 else 1
        gaps = [stamps[i + 1] - stamps[i - 1] for i in range(first, len(stamps) - 1)]
        return first + min(range(len(gaps)), key=gaps.__getitem__)
