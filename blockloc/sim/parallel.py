"""Rendering a session's frames in worker processes, handed back in order.

A frame is a pure function of (preset, seed, session, index) (``blockloc.sim.stream``), so the
process that casts it does not change its bytes. Most of a scan's CPU is single-threaded numpy
(open3d's casts are about a third of it), so writing a dataset on one process used one core of
two; workers cast chunks of consecutive frames while the calling process writes.
"""

from __future__ import annotations

import logging
import os
from collections import deque
from typing import Iterator

from blockloc.datasets.base import LidarFrame
from blockloc.sim.presets import Preset

log = logging.getLogger(__name__)

#: Consecutive frames a worker renders per task (~2 MB a frame travels back pickled).
CHUNK_FRAMES = 8
#: Fewer frames than this in all are rendered in the calling process: a worker costs ~1-2 s to
#: start (numpy, open3d and the world's scene in a fresh process).
MIN_FRAMES_FOR_WORKERS = 200

_SEQUENCES: dict = {}  # in a worker: (preset, session, seed) -> SimSequence


def default_workers(n_frames: int) -> int:
    """Worker processes for ``n_frames`` frames: 0 (render here) for short runs or one core,
    else the cores this process may use (at most 4)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return 0 if n_frames < MIN_FRAMES_FOR_WORKERS or cores < 2 else min(cores, 4)


def _init_worker() -> None:
    import signal

    from blockloc.threads import RAYCAST_THREADS_ENV

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    os.environ.setdefault(RAYCAST_THREADS_ENV, "1")  # one core a worker: no casting threads


def _render(preset: Preset, session: str, seed: int, start: int, stop: int) -> list[LidarFrame]:
    from blockloc.sim.stream import SimSequence

    key = (preset, session, seed)
    if key not in _SEQUENCES:
        _SEQUENCES.clear()  # one session at a time: its scene is the memory
        _SEQUENCES[key] = SimSequence(preset, session, seed)
    seq = _SEQUENCES[key]
    return [seq.frame(i) for i in range(start, stop)]


class FramePool:
    """Worker processes rendering frames of simulated sessions (``workers`` of them; spawned,
    not forked: open3d and BLAS threads do not survive a fork). Use as a context manager."""

    def __init__(self, workers: int):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.workers = int(workers)
        self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init_worker)

    def frames(self, preset: Preset, session: str, seed: int, start: int, stop: int) -> Iterator[LidarFrame]:
        """Frames ``start .. stop - 1`` of the session, in order; at most two chunks a worker
        are queued (memory stays bounded however long the session)."""
        pending: deque = deque()
        nxt = start
        try:
            while nxt < stop or pending:
                while nxt < stop and len(pending) < 2 * self.workers:
                    end = min(stop, nxt + CHUNK_FRAMES)
                    pending.append(self._pool.submit(_render, preset, session, seed, nxt, end))
                    nxt = end
                yield from pending.popleft().result()
        finally:
            for f in pending:
                f.cancel()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "FramePool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
