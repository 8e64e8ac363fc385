"""``blockloc node --detect-changes``: the node's emitted frames fed to the change detector.

The node steps its session itself (no recorded sequence to tap), so it hands each processed
scan and the tracker's estimate to a frame hook (``LocalizationNode(on_frame=...)``) after the
pose is published. :class:`NodeChanges` is that hook: it decides in the node's processing
thread, in order, which frames are trusted (the run folder's rule,
:meth:`blockloc.app.runs.LiveChanges.trusted`: never lost, rejected, uninitialized or
just-relocalized frames) and passes them to the same :class:`~blockloc.app.runs.LiveChanges`
``track --detect-changes`` uses, on a worker thread of its own behind a bounded queue: a pose is
never made to wait for detection. Only the scans the detector will use (every ``stride``-th
trusted frame, counted here as the detector counts them) travel with their frame; the other
frames pass as poses. When the detector falls behind and ``queue_scans`` such scans already wait,
the next one is dropped for detection (its pose is still fed, as a frame that is not trusted, and
the next trusted frame is used in its place) and counted; the changes then miss what that scan
alone would have shown.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

import numpy as np

log = logging.getLogger(__name__)

_RESTART = ("restart",)  # the queue's marker of a source restart, between the frames around it


class NodeChanges:
    """The node's frame hook feeding ``live`` (a :class:`~blockloc.app.runs.LiveChanges`).

    threaded: detect on a worker thread behind a queue of at most ``queue_scans`` trusted scans
    (False: in the caller's thread, each call waits for the detector; tests and the bench's
    comparison). The default 40 is the node's backlog (about 80 MB of 64k-point scans): the
    detector's first scans compile its kernels (measured on the tiny world under a load of 6:
    up to 1 s CPU, 3.5 s wall each), and a queue of 8 dropped 14 of the first 23 trusted scans
    at 5 scans/s. :meth:`begin` once the session exists, call the object with each processed
    scan's (LidarFrame, Estimate) in order, :meth:`close` at shutdown (detects what waits), then
    :meth:`cost`."""

    def __init__(self, live, *, threaded: bool = True, queue_scans: int = 40) -> None:
        if queue_scans < 1:
            raise ValueError(f"queue_scans {queue_scans}: expected at least 1")
        self.live = live
        self.threaded = bool(threaded)
        self.queue_scans = int(queue_scans)
        self.scans_dropped = 0  # scans the detector would have used, not detected on: it was behind
        self.max_waiting = 0  # the most scans to use ever waiting at once
        self.restarts = 0  # source restarts told (:meth:`restart`)
        self._trusted_fed = 0  # trusted frames handed to the detector (its frames_trusted)
        self._hook_cpu: list[float] = []  # the node thread's CPU seconds per call
        self._items: deque = deque()
        self._scans_waiting = 0
        self._cond = threading.Condition()
        self._closing = False
        self._worker: threading.Thread | None = None

    def begin(self, session) -> None:
        """The detector for ``session``'s map and sensor; the worker starts (and loads the
        detector's compiled kernels first, on its own thread: the node's first scan does not wait)."""
        self.live.begin(session, warm=not self.threaded)
        if self.threaded and self._worker is None:
            self._worker = threading.Thread(target=self._work, name="blockloc-changes", daemon=True)
            self._worker.start()

    def __call__(self, frame, est) -> None:
        """One processed scan (``frame``: its LidarFrame, lidar frame points) and the tracker's
        estimate of it, in the order the node processed them."""
        c0 = time.thread_time()
        T = est.T_map_body
        trusted = self.live.trusted(est.diagnostics.status, T)
        # the detector uses every stride-th trusted frame it is fed (ChangeDetector.add)
        used = trusted and self._trusted_fed % max(int(self.live.stride), 1) == 0
        item = (int(frame.index), float(frame.stamp), None if T is None else np.asarray(T, float), trusted,
                frame if used else None)
        if not self.threaded:
            self.live.add(*item)
        else:
            with self._cond:
                if used and self._scans_waiting >= self.queue_scans:
                    self.scans_dropped += 1
                    used, item = False, item[:3] + (False, None)
                    if self.scans_dropped == 1:
                        log.warning("change detection is behind: scan %d dropped for detection (counted in "
                                    "changes.json; poses are not delayed)", frame.index)
                self._items.append(item)
                self._scans_waiting += int(used)
                self.max_waiting = max(self.max_waiting, self._scans_waiting)
                self._cond.notify()
        self._trusted_fed += int(item[3])
        self._hook_cpu.append(time.thread_time() - c0)

    def restart(self) -> None:
        """The node's source restarted (its scan stamps jumped back; the node's restart hook, in
        its processing thread, between the frames around it): trust starts over now, and the
        detector lets go of the poses before the restart when it reaches this point of the queue
        (:meth:`~blockloc.app.runs.LiveChanges.restart`)."""
        self.restarts += 1
        self.live.restart_trust()
        if not self.threaded:
            self.live.restart(trust=False)
            return
        with self._cond:
            self._items.append(_RESTART)
            self._cond.notify()

    def _work(self) -> None:
        det = self.live.detector
        if det is not None:
            try:
                det.warm_up()
            except Exception as exc:  # noqa: BLE001 - only a cost: the first scan loads them instead
                log.warning("change detection: loading the kernels ahead failed (%s); the first scan loads them", exc)
        while True:
            with self._cond:
                while not self._items and not self._closing:
                    self._cond.wait()
                if not self._items:
                    return
                item = self._items.popleft()
            if item is _RESTART:
                self.live.restart(trust=False)
                continue
            self.live.add(*item)  # a failure stops detection (live.error), never this thread's loop
            with self._cond:
                self._scans_waiting -= int(item[4] is not None)

    def close(self) -> None:
        """Detect what waits (at most ``queue_scans`` scans), then stop the worker. Idempotent."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        if self._worker is not None:
            self._worker.join()

    def cost(self) -> dict:
        """What detection cost the node: where it ran, scans dropped for it, and the node
        thread's CPU time per frame in the hook (p50 / max, ms; threaded: the hand-over only)."""
        hook = np.asarray(self._hook_cpu, float)
        return {"node_thread": "worker thread, bounded queue" if self.threaded else "the node's processing thread",
                "queue_scans": self.queue_scans if self.threaded else 0, "scans_dropped": self.scans_dropped,
                "max_scans_waiting": self.max_waiting, "source_restarts": self.restarts,
                "node_hook_cpu_ms": {"p50": round(1e3 * float(np.median(hook)), 3) if len(hook) else 0.0,
                                     "max": round(1e3 * float(hook.max()), 3) if len(hook) else 0.0}}
