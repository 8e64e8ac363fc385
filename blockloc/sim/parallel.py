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

import numpy as np

from blockloc.datasets.base import LidarFrame
from blockloc.sim.presets import Preset

log = logging.getLogger(__name__)

#: Consecutive frames a worker renders per task (~1 MB a frame travels back encoded, ~2 MB not).
CHUNK_FRAMES = 8
#: Fewer frames than this in all are rendered in the calling process: a worker costs ~1-2 s to
#: start (numpy, open3d and the world's scene in a fresh process).
MIN_FRAMES_FOR_WORKERS = 200
#: Sessions a worker keeps open (their scenes): the chunks of the next session are rendered
#: ahead while the last ones of a session are written, and a worker may take either.
KEEP_SEQUENCES = 2

_SEQUENCES: dict = {}  # in a worker: (preset, session, seed) -> SimSequence, the newest last


def default_workers(n_frames: int) -> int:
    """Worker processes for ``n_frames`` frames: 0 (render here) for short runs or one core,
    else the cores this process may use (at most 4)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return 0 if n_frames < MIN_FRAMES_FOR_WORKERS or cores < 2 else min(cores, 4)


def _keep_freed_memory() -> None:
    """Let glibc keep the memory a scan frees for the next one: each scan allocates and frees
    ~100 arrays of 0.5-2 MB, which by default went back to the kernel (munmap, heap trim) and
    came again as fresh zeroed pages (~570 page faults, ~1.2 ms of system time a scan). A no-op
    where the C library is not glibc."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
        libc.mallopt(M_MMAP_THRESHOLD, 32 << 20)  # glibc's largest: 32 MB on 64-bit
        libc.mallopt(M_TRIM_THRESHOLD, 512 << 20)
    except (OSError, AttributeError):
        pass


def _init_worker() -> None:
    import signal

    from blockloc.threads import RAYCAST_THREADS_ENV

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    os.environ.setdefault(RAYCAST_THREADS_ENV, "1")  # one core a worker: no casting threads
    _keep_freed_memory()


def _render(preset: Preset, session: str, seed: int, start: int, stop: int, encode: bool = False,
            write_to: str | None = None):
    """Frames ``start .. stop - 1`` of the session: LidarFrames, or with ``encode`` the NCLT
    bytes ``write_session`` writes (``blockloc.datasets.nclt.EncodedFrame``: the encoding is
    done here, beside the rendering, and half the bytes go back). With ``encode`` and
    ``write_to`` (a directory) the bytes are written there instead (:func:`_write_chunk`) and
    only where they are goes back."""
    from blockloc.sim.stream import SimSequence

    key = (preset, session, seed)
    seq = _SEQUENCES.pop(key, None)
    if seq is None:
        while len(_SEQUENCES) >= KEEP_SEQUENCES:  # the oldest goes: its scene is the memory
            del _SEQUENCES[next(iter(_SEQUENCES))]
        seq = SimSequence(preset, session, seed)
    _SEQUENCES[key] = seq
    frames = (seq.frame(i) for i in range(start, stop))
    if not encode:
        return list(frames)
    from blockloc.datasets.nclt import encode_frame

    encoded = (encode_frame(f, encode_words=_encode_words) for f in frames)
    return list(encoded) if write_to is None else _write_chunk(encoded, write_to, start, stop)


def _encode_words(points, intensity, ring):
    """``blockloc.datasets.nclt._encode_words`` (words, keep mask) of a rendered scan by the
    one-pass kernel ``nclt_words`` (its bits; ~1.5 ms a scan of numpy passes, ~4% of a scan's
    CPU), for the dtypes the lidar model gives; anything else by ``_encode_words`` itself."""
    from blockloc.datasets import nclt

    pts = np.asarray(points)
    if (intensity is None or ring is None or pts.dtype != np.float64 or pts.ndim != 2 or pts.shape[1] != 3
            or np.asarray(intensity).dtype != np.float32 or np.asarray(ring).dtype != np.uint16):
        return nclt._encode_words(points, intensity, ring)
    from blockloc.sim._kernels import nclt_words

    return nclt_words(np.ascontiguousarray(pts), np.asarray(intensity), np.asarray(ring),
                      float(nclt.NCLT_POINT_OFFSET), float(nclt.NCLT_POINT_SCALE))


def _write_chunk(encoded, write_to: str, start: int, stop: int) -> tuple[str, list]:
    """Write a chunk's encoded frames into ``write_to``: each frame's velodyne_sync bytes as
    ``<utime>.bin``, the chunk's hits packets one after the other in ``<start>-<stop>.hits``.
    Returns (that hits file, [(index, stamp, utime, bytes of hits, dropped) a frame]).

    ~1 MB a frame crossed the pipe to the writing process (pickled, then 64 kB a read, then
    unpickled: ~1.2 ms of CPU a frame between the two processes); written here, the writing
    process moves the sync files in and reads the hits back in one read a chunk."""
    hits_path = os.path.join(write_to, f"{start}-{stop}.hits")
    meta = []
    with open(hits_path, "wb") as hits:
        for enc in encoded:
            with open(os.path.join(write_to, f"{enc.utime}.bin"), "wb") as fh:
                fh.write(enc.sync)
            hits.write(enc.hits)
            meta.append((enc.index, enc.stamp, enc.utime, len(enc.hits), enc.dropped))
    return hits_path, meta


def _written_frames(result) -> list:
    """The ``EncodedFrame`` list of a chunk :func:`_write_chunk` wrote: ``sync`` the path of each
    frame's file (``write_session`` moves it in), ``hits`` its bytes (the chunk's file is read
    once, then removed)."""
    from pathlib import Path

    from blockloc.datasets.nclt import EncodedFrame

    hits_path, meta = result
    with open(hits_path, "rb") as fh:
        hits = memoryview(fh.read())
    os.unlink(hits_path)
    folder = Path(hits_path).parent
    out, at = [], 0
    for index, stamp, utime, n_hits, dropped in meta:
        out.append(EncodedFrame(index, stamp, utime, folder / f"{utime}.bin", hits[at:at + n_hits], dropped))
        at += n_hits
    return out


#: Modules the workers' fork server imports once, before it forks them (~1.2 s of CPU a worker
#: when each imported them itself).
PRELOAD = ("numpy", "scipy.interpolate", "open3d", "numba", "blockloc.sim._kernels", "blockloc.sim.stream",
           "blockloc.sim.scene", "blockloc.datasets.nclt")


def _context():
    """The workers' start method: forked from a fork server that has imported ``PRELOAD`` (and
    started no thread pool: open3d's and the casts' threads start in each worker), not from
    this process (its open3d and BLAS threads would not survive a fork); spawned where there is
    no fork server (not on Linux)."""
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))
    return ctx


def _stop_fork_server() -> None:
    """Stop the fork server and wait for it (it has reaped the workers): its CPU, the
    workers' included, is then this process's children's, as spawned workers' was
    (``resource.getrusage(RUSAGE_CHILDREN)``: what bench.sim reports); it would otherwise
    linger until this process exits and be nobody's. The next pool starts another."""
    try:
        from multiprocessing import forkserver

        forkserver._forkserver._stop()  # the standard library's own stop (used by its tests)
    except (AttributeError, OSError, ChildProcessError):
        pass


class FramePool:
    """Worker processes rendering frames of simulated sessions (``workers`` of them, forked from
    a fork server: :func:`_context`). Use as a context manager."""

    def __init__(self, workers: int):
        from concurrent.futures import ProcessPoolExecutor

        self.workers = int(workers)
        self._pool = ProcessPoolExecutor(self.workers, mp_context=_context(), initializer=_init_worker)

    def frames(self, preset: Preset, session: str, seed: int, start: int, stop: int,
               encode: bool = False) -> Iterator[LidarFrame]:
        """Frames ``start .. stop - 1`` of the session, in order (``encode``: as
        ``EncodedFrame``); at most two chunks a worker are queued (memory stays bounded however
        long the session)."""
        return self.runs(preset, seed, [(session, start, stop)], encode)[0]

    def runs(self, preset: Preset, seed: int, runs: list[tuple[str, int, int]], encode: bool = False,
             write_to: list | None = None) -> list[Iterator]:
        """One iterator per run ``(session, start, stop)``, each giving that run's frames in
        order (as :meth:`frames`); read them one after the other, each to its end. The chunks of all runs are
        queued in one line, so while the last chunks of a run are rendered the workers go on
        with the next run's (one queue per run drained at each run's end left a worker idle
        and paid its start again).

        write_to: with ``encode``, one existing directory per run (or None) on the filesystem
        the frames will be written to: the workers write each frame's bytes there and the
        ``EncodedFrame`` handed back has the path of its sync file (``write_session`` moves it
        in; whatever is not moved in stays there for the caller to remove)."""
        dirs = [None] * len(runs) if write_to is None or not encode else [
            None if d is None else os.fspath(d) for d in write_to]
        chunks = deque((k, a, min(stop, a + CHUNK_FRAMES)) for k, (_, start, stop) in enumerate(runs)
                       for a in range(start, stop, CHUNK_FRAMES))
        pending: deque = deque()  # (run, future), in the order of the chunks

        def top_up() -> None:
            while chunks and len(pending) < 2 * self.workers:
                k, a, b = chunks.popleft()
                pending.append((k, self._pool.submit(_render, preset, runs[k][0], seed, a, b, encode, dirs[k])))

        def run(k: int) -> Iterator:
            try:
                top_up()
                while pending and pending[0][0] == k:
                    _, fut = pending.popleft()
                    top_up()  # before waiting: the workers stay busy
                    yield from fut.result() if dirs[k] is None else _written_frames(fut.result())
            except GeneratorExit:  # the reader stopped early: nothing more is rendered
                chunks.clear()
                for _, fut in pending:
                    fut.cancel()
                raise

        top_up()  # the workers start now, while the caller prepares the first run's writing
        return [run(k) for k in range(len(runs))]

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        _stop_fork_server()

    def __enter__(self) -> "FramePool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
