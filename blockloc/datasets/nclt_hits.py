"""NCLT's ``velodyne_hits.bin``: the packet index and per-point time lookup (reading), and
packets from time-sorted point words (writing). Byte layout: :mod:`blockloc.datasets.nclt`.
"""

from __future__ import annotations

import logging
import mmap
from pathlib import Path

import numpy as np

from blockloc.errors import DatasetError

log = logging.getLogger(__name__)

#: Magic number repeated 4 times at the start of every velodyne_hits.bin packet.
NCLT_HITS_MAGIC = 44444
NCLT_HITS_HEADER_BYTES = 24  # 4 x uint16 magic + uint32 num_hits + uint64 utime + 4 padding
NCLT_HITS_HEADER_DTYPE = np.dtype([("magic", "<u2", (4,)), ("num_hits", "<u4"), ("utime", "<u8"),
                                   ("pad", "<u4")])


# --- hits file --------------------------------------------------------------------------------

#: Words of velodyne_hits.bin walked at a time when indexing (64 MiB): the pages a walk reads
#: are handed back after each chunk.
HITS_INDEX_CHUNK_WORDS = 1 << 23


class HitsIndex:
    """Packet index of a ``velodyne_hits.bin`` and per-point time lookup.

    The file is memory-mapped as uint64 words (every packet is 8-byte aligned); indexing walks
    the packet headers once (numba, ~1 s for a multi-GB campus file), 64 MiB at a time, each
    chunk's pages handed back before the next (and a window's once the next is read): they stay in
    the page cache, but the process's RSS does not grow with the file (at most one window stays mapped). It did, to the file's size
    (1.8 GB for 400 s of city drive, tens of GB for a long NCLT session), and a Dask worker's
    memory monitor counts it.
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        size = self.path.stat().st_size
        if size % 8 != 0:
            raise DatasetError(f"{self.path}: {size} bytes, expected a multiple of 8 "
                               "(24-byte packet headers + 8-byte hits); the file is truncated")
        if size == 0:
            self.words = np.zeros(0, dtype="<u8")
            self.offsets = self.num_hits = self.utimes = np.zeros(0, dtype=np.int64)
            return
        # read-only map: one numba signature, compiled once per install (cache=True)
        with open(self.path, "rb") as fh:
            self._map = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        self.words = np.frombuffer(self._map, dtype="<u8")
        from blockloc.datasets._nclt_kernels import index_hits_words

        offs, nums, uts, status, bad = self._walk(index_hits_words)
        if status == 1:
            raise DatasetError(f"{self.path}: bad packet magic at byte {bad * 8}, expected "
                               f"4 x uint16 {NCLT_HITS_MAGIC}")
        if status == 2:
            n_need = (3 + int(self.words[bad + 1] & 0xFFFFFFFF)) * 8 if bad + 1 < len(self.words) else 24
            raise DatasetError(f"{self.path}: truncated packet at byte {bad * 8}: expected "
                               f"{n_need} bytes, {size - bad * 8} left")
        order = np.argsort(uts, kind="stable")
        self.offsets, self.num_hits, self.utimes = offs[order], nums[order], uts[order]
        log.debug("%s: %d packets, %d hits", self.path, len(self.offsets), int(self.num_hits.sum()))

    def _walk(self, kernel, chunk_words: int = HITS_INDEX_CHUNK_WORDS):
        """The kernel's packet walk over the file a chunk at a time, each chunk's pages handed
        back before the next (a whole-file walk peaked at the file's size in RSS). A packet cut
        by a chunk's end starts the next chunk. Returns the kernel's (offsets, num_hits, utimes,
        status, bad word) for the whole file."""
        n = len(self.words)
        parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        w0, span, status, bad = 0, chunk_words, 0, -1
        while w0 < n:
            w1 = min(n, w0 + span)
            offs, nums, uts, status, bad = kernel(self.words[w0:w1])
            parts.append((offs + w0, nums, uts))
            self._release(w0 * 8, w1 * 8)
            bad = bad + w0 if bad >= 0 else bad
            if status == 2 and w1 < n:  # cut by the chunk, not by the file's end
                span = span if bad > w0 else 2 * span  # a packet longer than a chunk: widen it
                w0, status, bad = bad, 0, -1
                continue
            if status != 0:
                break
            w0, span = w1, chunk_words
        offs, nums, uts = (np.concatenate([p[i] for p in parts]) for i in range(3))  # n > 0: a part at least
        return offs, nums, uts, status, bad

    def window(self, t0_us: int, t1_us: int) -> tuple[np.ndarray, np.ndarray]:
        """Raw 8-byte hit words (H,) uint64 and their packet utimes (H,) int64 for packets with
        t0_us <= utime <= t1_us, in time order."""
        i0, i1 = np.searchsorted(self.utimes, [t0_us, t1_us], side="left")
        i1 = np.searchsorted(self.utimes, t1_us, side="right")
        offs, nums, uts = self.offsets[i0:i1], self.num_hits[i0:i1], self.utimes[i0:i1]
        total = int(nums.sum())
        if total == 0:
            return np.zeros(0, dtype=np.uint64), np.zeros(0, dtype=np.int64)
        starts = np.repeat(offs + 3 - np.concatenate([[0], np.cumsum(nums)[:-1]]), nums)
        idx = starts + np.arange(total)
        hits = self.words[idx]  # a copy
        self._hold(int(offs.min()) * 8, int((offs + 3 + nums).max()) * 8)
        return hits, np.repeat(uts, nums)

    def _hold(self, lo: int, hi: int) -> None:
        """Keep bytes [lo, hi) (the window just read) mapped and hand back what the window before
        held outside them: consecutive frames' windows overlap, and handing each window back whole
        made the next frame map the overlap again (0.9 ms a frame, a third of reading one)."""
        a, b = getattr(self, "_held", (0, 0))
        if a < min(b, lo):
            self._release(a, min(b, lo))
        if max(a, hi) < b:
            self._release(max(a, hi), b)
        self._held = (lo, hi)

    def _release(self, lo: int, hi: int) -> None:
        """Drop bytes [lo, hi) of the file from this process's mapped pages (the kernel keeps
        them cached; a later read maps them again)."""
        start = lo - lo % mmap.PAGESIZE
        if hi > start:
            self._map.madvise(mmap.MADV_DONTNEED, start, min(hi, len(self._map)) - start)

    def point_utimes(self, sync_words: np.ndarray, utime_us: int, span_us: int = 110_000
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Times (N,) int64 us of the sync points (N,) uint64 words, and a found mask (N,) bool.

        Each sync point is matched to the identical 8-byte hit among the packets within
        ``span_us`` of the frame's utime. Fast path: the sync points are a contiguous run of the
        hit stream. Otherwise by sorting; a point whose bytes occur in several packets (e.g. a
        static robot repeats a return sweep after sweep) takes the one nearest the median time of
        the uniquely matched points.
        """
        n = len(sync_words)
        hits, hit_t = self.window(utime_us - span_us, utime_us + span_us)
        times = np.zeros(n, dtype=np.int64)
        if n == 0 or len(hits) == 0:
            return times, np.zeros(n, dtype=bool)
        for p in np.flatnonzero(hits == sync_words[0])[:16]:
            if p + n <= len(hits) and np.array_equal(hits[p:p + n], sync_words):
                return hit_t[p:p + n].copy(), np.ones(n, dtype=bool)
        order = np.argsort(hits, kind="stable")
        sk = hits[order]
        lo = np.searchsorted(sk, sync_words, side="left")
        hi = np.searchsorted(sk, sync_words, side="right")
        cnt = hi - lo
        found = cnt > 0
        uniq = cnt == 1
        times[uniq] = hit_t[order[lo[uniq]]]
        multi = np.flatnonzero(cnt > 1)
        if len(multi):
            ref = np.median(times[uniq]) if uniq.any() else float(utime_us)
            best_t = hit_t[order[lo[multi]]]
            best_d = np.abs(best_t - ref)
            for k in range(1, int(min(cnt[multi].max(), 32))):
                ok = cnt[multi] > k
                cand = hit_t[order[np.minimum(lo[multi] + k, len(sk) - 1)]]
                better = ok & (np.abs(cand - ref) < best_d)
                best_t = np.where(better, cand, best_t)
                best_d = np.where(better, np.abs(cand - ref), best_d)
            times[multi] = best_t
        return times, found


#: Duration of one HDL-32E data packet (12 firing blocks x 46.08 us); the hits file written by
#: ``write_session`` groups points into packets of this length, so per-point times read back
#: within half of it.
HITS_PACKET_US = 553


def _hits_packets(words: np.ndarray, t_us: np.ndarray) -> bytes:
    """Group time-sorted point words (N,) uint64 with times (N,) int64 into hits packets."""
    if len(words) == 0:
        return b""
    bins = (t_us - t_us[0]) // HITS_PACKET_US
    cuts = np.flatnonzero(np.diff(bins)) + 1
    starts = np.concatenate([[0], cuts])
    ends = np.concatenate([cuts, [len(words)]])
    n = ends - starts
    # packet utime: middle of its points' time span, so the read-back error is <= half a packet
    utime = (t_us[starts] + t_us[ends - 1] + 1) // 2
    out = np.empty(len(words) + 3 * len(starts), dtype="<u8")
    pos = starts + 3 * np.arange(len(starts))
    out[pos] = np.uint64(0xAD9CAD9CAD9CAD9C)
    ut = utime.astype(np.uint64)
    out[pos + 1] = n.astype(np.uint64) | ((ut & np.uint64(0xFFFFFFFF)) << np.uint64(32))
    out[pos + 2] = ut >> np.uint64(32)
    point_pos = np.arange(len(words)) + 3 * np.repeat(np.arange(len(starts)) + 1, n)
    out[point_pos] = words
    return out.tobytes()
