"""Rendering a session's frames in worker processes, handed back in order.

A frame is a pure function of (preset, seed, session, index) (``blockloc.sim.stream``), so the
process that casts it does not change its bytes (tested). Most of a scan's CPU is single-threaded
numpy (open3d's casts are about a quarter of it), so a dataset written by one process uses about
one core; workers cast chunks of consecutive frames while the calling process writes. Opt-in
(``generate_dataset(..., workers=2)``): see :func:`default_workers`.
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
#: A worker costs ~2 s of CPU to start (numpy, open3d and the world's scene in a fresh process):
#: below this many frames in all it cannot pay for itself.
MIN_FRAMES_FOR_WORKERS = 200

_SEQUENCES: dict = {}  # in a worker: (preset, session, seed) -> SimSequence


def default_workers(n_frames: int) -> int:
    """Worker processes ``generate_dataset`` uses unless told: 0 (render in the calling process).

    Not on by default yet: on this 2-core machine, shared and loaded (load 12-22), a whole
    ``blockloc sim --preset small`` with 2 workers spent ~4x the CPU a frame of the same run in
    one process (workers' CPU over frames written, 2026-12-05 22:42-23:00), while short runs
    (64 frames, ``generate_dataset(..., max_frames=64, workers=2)``) spent what one process does
    plus each worker's ~2 s start. Until that is understood, ask for them (``workers=2``)."""
    del n_frames
    return 0


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
