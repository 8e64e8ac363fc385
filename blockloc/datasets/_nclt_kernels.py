"""Numba kernel that indexes NCLT's velodyne_hits.bin (leaf module: imported lazily)."""

from __future__ import annotations

import numba
import numpy as np

# 4 x uint16 44444 (0xAD9C) read as one little-endian uint64 word.
MAGIC_WORD = np.uint64(0xAD9CAD9CAD9CAD9C)


@numba.njit(cache=True)
def index_hits_words(words):  # pragma: no cover - compiled
    """Walk packets of a hits file viewed as (W,) uint64 little-endian words.

    Every packet is 3 header words (magic, num_hits | utime_lo << 32, utime_hi | padding) and
    num_hits point words, so packets start on word boundaries.

    Returns (word_offsets, num_hits, utimes, status, bad_word): arrays for the complete packets
    found; status 0 = clean end, 1 = bad magic at ``bad_word``, 2 = truncated packet at ``bad_word``.
    """
    n_words = words.shape[0]
    cap = 1024
    offs = np.empty(cap, np.int64)
    nums = np.empty(cap, np.int64)
    uts = np.empty(cap, np.int64)
    count = 0
    w = 0
    status = 0
    bad = -1
    magic = MAGIC_WORD
    lo32 = np.uint64(0xFFFFFFFF)
    sh = np.uint64(32)
    while w < n_words:
        if w + 3 > n_words:
            status = 2
            bad = w
            break
        if words[w] != magic:
            status = 1
            bad = w
            break
        w1 = words[w + 1]
        w2 = words[w + 2]
        n = np.int64(w1 & lo32)
        ut = np.int64((w1 >> sh) | ((w2 & lo32) << sh))
        if w + 3 + n > n_words:
            status = 2
            bad = w
            break
        if count == cap:
            cap *= 2
            o2 = np.empty(cap, np.int64)
            n2 = np.empty(cap, np.int64)
            u2 = np.empty(cap, np.int64)
            o2[:count] = offs[:count]
            n2[:count] = nums[:count]
            u2[:count] = uts[:count]
            offs, nums, uts = o2, n2, u2
        offs[count] = w
        nums[count] = n
        uts[count] = ut
        count += 1
        w += 3 + n
    return offs[:count], nums[:count], uts[:count], status, bad
