"""numba kernels of ``blockloc.voxels`` (imported lazily; compiled once, cached on disk).

One pass over the points, no sort: each point's voxel key ``floor(p / size)`` (float64 division,
the same numbers as the numpy reference) is packed into one int64 (21 bits per axis, offset
2**20) and looked up in an open-addressing hash table (linear probing, power-of-two size, load
factor <= 0.5). A key outside +-2**20 voxels makes the kernel give up (``ok`` False) and the
caller use the numpy reference instead, which handles any extent.
"""

from __future__ import annotations

import numba as nb
import numpy as np

KEY_OFFSET = 1 << 20
HASH_MUL = np.uint64(0x9E3779B97F4A7C15)


@nb.njit(cache=True, inline="always")
def _key(x, y, z, inv_size_div):  # pragma: no cover - compiled
    """Packed key of the voxel holding (x, y, z), or -1 when a coordinate is out of range (or
    not finite). ``inv_size_div`` is the voxel size itself: divided, not multiplied, as numpy's
    reference does, so both floor the same quotient."""
    fx = np.floor(x / inv_size_div)
    fy = np.floor(y / inv_size_div)
    fz = np.floor(z / inv_size_div)
    if not (-KEY_OFFSET <= fx < KEY_OFFSET and -KEY_OFFSET <= fy < KEY_OFFSET
            and -KEY_OFFSET <= fz < KEY_OFFSET):
        return np.int64(-1)
    return (((np.int64(fx) + KEY_OFFSET) << 42) | ((np.int64(fy) + KEY_OFFSET) << 21)
            | (np.int64(fz) + KEY_OFFSET))


@nb.njit(cache=True, inline="always")
def _probe(table, mask, shift, key):  # pragma: no cover - compiled
    """Slot of ``key`` in ``table`` (its own, or the empty one where it belongs)."""
    s = np.int64((np.uint64(key) * HASH_MUL) >> np.uint64(shift))
    while True:
        k = table[s]
        if k == key or k == -1:
            return s
        s = (s + 1) & mask


def table_bits(n: int) -> int:
    """log2 of a hash table size for up to n keys at load factor <= 0.5 (at least 16 slots)."""
    return max(4, int(np.ceil(np.log2(max(2 * n, 2)))))


@nb.njit(cache=True, nogil=True)
def select_first(points, size, min_r2, max_r2, in_range_only, bits):  # pragma: no cover - compiled
    """Indices (ascending) of the first point of every occupied voxel, and whether every key fit.

    points: (N, 3+) float32 or float64; size: voxel edge (m); in_range_only: consider only
    points that are finite with min_r2 <= x^2 + y^2 + z^2 <= max_r2 (others skipped), else every
    point (a non-finite one then makes ``ok`` False). bits: log2 of the table size
    (:func:`table_bits` of N). Returns (idx (M,) int64, ok).
    """
    n = points.shape[0]
    table = np.full(1 << bits, np.int64(-1))
    mask = (1 << bits) - 1
    shift = 64 - bits
    out = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        if in_range_only:
            r2 = x * x + y * y + z * z
            if not (r2 >= min_r2 and r2 <= max_r2):  # NaN fails both: skipped
                continue
        key = _key(x, y, z, size)
        if key < 0:
            return out[:0], False
        s = _probe(table, mask, shift, key)
        if table[s] == -1:
            table[s] = key
            out[m] = i
            m += 1
    return out[:m], True
