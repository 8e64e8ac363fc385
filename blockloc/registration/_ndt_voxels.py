"""Numba kernels of the NDT engine's voxel maps: voxel keys, the open-addressing hash table,
per-voxel statistics (accumulated, merged, coarsened), the Gaussians and the neighbour table
(leaf module: importing it imports numba). The key and table layout are described in
:mod:`blockloc.registration._ndt_kernels`, which evaluates and aligns against them and re-exports
these names.
"""

from __future__ import annotations

import numpy as np
from numba import njit

KEY_OFFSET = 1 << 20
KEY_MASK = (1 << 21) - 1
HASH_MUL = np.uint64(0x9E3779B97F4A7C15)
EMPTY = -1

# Upper-triangle order of a symmetric 6x6 in the accumulator rows.
_TRI = [(i, j) for i in range(6) for j in range(i, 6)]
TRI_I = np.array([p[0] for p in _TRI], dtype=np.int64)
TRI_J = np.array([p[1] for p in _TRI], dtype=np.int64)
# (6, 6) index into the upper triangle, for unpacking to a full symmetric matrix
TRI_FULL = np.array([[_TRI.index((min(i, j), max(i, j))) for j in range(6)] for i in range(6)])


@njit(cache=True, inline="always")
def _pack(ix, iy, iz):
    return ((ix + KEY_OFFSET) << 42) | ((iy + KEY_OFFSET) << 21) | (iz + KEY_OFFSET)


@njit(cache=True, inline="always")
def _in_range(ix, iy, iz):
    return (-KEY_OFFSET <= ix < KEY_OFFSET and -KEY_OFFSET <= iy < KEY_OFFSET
            and -KEY_OFFSET <= iz < KEY_OFFSET)


@njit(cache=True, inline="always")
def _slot(key, shift):
    h = np.uint64(key) * HASH_MUL
    return np.int64(h >> np.uint64(shift))


@njit(cache=True, inline="always")
def _lookup(table_keys, table_vals, shift, mask, key):
    s = _slot(key, shift)
    while True:
        k = table_keys[s]
        if k == key:
            return table_vals[s]
        if k == EMPTY:
            return -1
        s = (s + 1) & mask


@njit(cache=True, nogil=True)
def unpack_keys(keys):
    """(V,) int64 keys -> (V, 3) int64 voxel coordinates."""
    out = np.empty((keys.shape[0], 3), dtype=np.int64)
    for i in range(keys.shape[0]):
        k = keys[i]
        out[i, 0] = ((k >> 42) & KEY_MASK) - KEY_OFFSET
        out[i, 1] = ((k >> 21) & KEY_MASK) - KEY_OFFSET
        out[i, 2] = (k & KEY_MASK) - KEY_OFFSET
    return out


def table_size_for(n):
    """Power-of-two table size with load factor <= 0.5 (at least 16); returns (size, shift)."""
    bits = max(4, int(np.ceil(np.log2(max(2 * n, 2)))))
    return 1 << bits, 64 - bits


@njit(cache=True, nogil=True)
def _rehash(keys, nv, size):
    """New (size, 2) hash table over the first nv keys (rows 0..nv-1)."""
    bits = 0
    while (1 << bits) < size:
        bits += 1
    shift = 64 - bits
    mask = size - 1
    table = np.empty((size, 2), dtype=np.int64)
    for s in range(size):
        table[s, 0] = EMPTY
    for v in range(nv):
        s = _slot(keys[v], shift)
        while table[s, 0] != EMPTY:
            s = (s + 1) & mask
        table[s, 0] = keys[v]
        table[s, 1] = v
    return table, shift


@njit(cache=True, nogil=True)
def voxel_stats(points, inv_res, res):
    """Accumulate per-voxel statistics of points in one pass (hash accumulation, serial).

    points: (N, 3) float64. Returns keys (V,) int64, count (V,) int64, sums (V, 3) and outer
    sums (V, 6: xx xy xz yy yz zz) of coordinates relative to the voxel centre, and the number
    of points skipped because their voxel coordinate is out of the 21-bit range. Memory grows
    with the number of voxels (table and rows double as needed), not with N.
    """
    n = points.shape[0]
    cap = 1024
    while cap < min(n, 1 << 16):
        cap *= 2
    keys = np.empty(cap, dtype=np.int64)
    count = np.zeros(cap, dtype=np.int64)
    sums = np.zeros((cap, 3))
    outer = np.zeros((cap, 6))
    size = 2 * cap
    table, shift = _rehash(keys, 0, size)
    mask = size - 1
    nv = 0
    skipped = 0
    for i in range(n):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        fx = np.floor(x * inv_res)
        fy = np.floor(y * inv_res)
        fz = np.floor(z * inv_res)
        if not (-KEY_OFFSET <= fx < KEY_OFFSET and -KEY_OFFSET <= fy < KEY_OFFSET
                and -KEY_OFFSET <= fz < KEY_OFFSET):
            skipped += 1
            continue
        ix = np.int64(fx)
        iy = np.int64(fy)
        iz = np.int64(fz)
        key = _pack(ix, iy, iz)
        s = _slot(key, shift)
        while True:
            k = table[s, 0]
            if k == key:
                v = table[s, 1]
                break
            if k == EMPTY:
                if nv == cap:  # grow rows and table (load factor stays <= 0.5)
                    cap *= 2
                    keys2 = np.empty(cap, dtype=np.int64)
                    keys2[:nv] = keys[:nv]
                    keys = keys2
                    count2 = np.zeros(cap, dtype=np.int64)
                    count2[:nv] = count[:nv]
                    count = count2
                    sums2 = np.zeros((cap, 3))
                    sums2[:nv] = sums[:nv]
                    sums = sums2
                    outer2 = np.zeros((cap, 6))
                    outer2[:nv] = outer[:nv]
                    outer = outer2
                    size = 2 * cap
                    table, shift = _rehash(keys, nv, size)
                    mask = size - 1
                    s = _slot(key, shift)
                    while table[s, 0] != EMPTY:
                        s = (s + 1) & mask
                v = nv
                table[s, 0] = key
                table[s, 1] = v
                keys[v] = key
                nv += 1
                break
            s = (s + 1) & mask
        dx = x - (ix + 0.5) * res
        dy = y - (iy + 0.5) * res
        dz = z - (iz + 0.5) * res
        count[v] += 1
        sums[v, 0] += dx
        sums[v, 1] += dy
        sums[v, 2] += dz
        outer[v, 0] += dx * dx
        outer[v, 1] += dx * dy
        outer[v, 2] += dx * dz
        outer[v, 3] += dy * dy
        outer[v, 4] += dy * dz
        outer[v, 5] += dz * dz
    return keys[:nv].copy(), count[:nv].copy(), sums[:nv].copy(), outer[:nv].copy(), skipped


@njit(cache=True, nogil=True)
def merge_stats(keys, count, sums, outer):
    """Sum statistics of coinciding keys (e.g. the concatenated voxels of several tiles).

    Returns unique keys (U,), count (U,), sums (U, 3), outer (U, 6), and for each unique voxel
    the row of its first contributor (U,) and the number of contributors (U,).
    """
    n = keys.shape[0]
    size = 16
    while size < 2 * n:
        size *= 2
    bits = 0
    while (1 << bits) < size:
        bits += 1
    shift = 64 - bits
    mask = size - 1
    table_keys = np.full(size, EMPTY, dtype=np.int64)
    table_vals = np.empty(size, dtype=np.int64)
    ukeys = np.empty(n, dtype=np.int64)
    ucount = np.zeros(n, dtype=np.int64)
    usums = np.zeros((n, 3))
    uouter = np.zeros((n, 6))
    first = np.empty(n, dtype=np.int64)
    contributors = np.zeros(n, dtype=np.int64)
    nu = 0
    for i in range(n):
        key = keys[i]
        s = _slot(key, shift)
        while True:
            k = table_keys[s]
            if k == key:
                v = table_vals[s]
                break
            if k == EMPTY:
                v = nu
                table_keys[s] = key
                table_vals[s] = v
                ukeys[v] = key
                first[v] = i
                nu += 1
                break
            s = (s + 1) & mask
        contributors[v] += 1
        ucount[v] += count[i]
        for c in range(3):
            usums[v, c] += sums[i, c]
        for c in range(6):
            uouter[v, c] += outer[i, c]
    return (ukeys[:nu].copy(), ucount[:nu].copy(), usums[:nu].copy(), uouter[:nu].copy(),
            first[:nu].copy(), contributors[:nu].copy())


@njit(cache=True, inline="always")
def _jacobi_eig3(a00, a01, a02, a11, a12, a22, V):
    """Eigen-decomposition of a symmetric 3x3 by cyclic Jacobi rotations (scalar code).

    Writes eigenvectors into the columns of V (3, 3); returns the three eigenvalues.
    """
    A = np.empty((3, 3))
    A[0, 0] = a00
    A[0, 1] = a01
    A[0, 2] = a02
    A[1, 0] = a01
    A[1, 1] = a11
    A[1, 2] = a12
    A[2, 0] = a02
    A[2, 1] = a12
    A[2, 2] = a22
    for i in range(3):
        for j in range(3):
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(16):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        diag = A[0, 0] * A[0, 0] + A[1, 1] * A[1, 1] + A[2, 2] * A[2, 2]
        if off <= 1e-30 * diag or off == 0.0:
            break
        for p in range(2):
            for q in range(p + 1, 3):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(3):
                    akp = A[k, p]
                    akq = A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(3):
                    apk = A[p, k]
                    aqk = A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                for k in range(3):
                    vkp = V[k, p]
                    vkq = V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    return A[0, 0], A[1, 1], A[2, 2]


@njit(cache=True, nogil=True)
def _gaussians_range(keys, count, sums, outer, res, min_points, eig_ratio, eig_floor,
                     means, icov, valid, lo, hi):
    V = np.empty((3, 3))
    for v in range(lo, hi):
        n = count[v]
        if n < min_points or n < 3:
            valid[v] = False
            continue
        k = keys[v]
        cx = (((k >> 42) & KEY_MASK) - KEY_OFFSET + 0.5) * res
        cy = (((k >> 21) & KEY_MASK) - KEY_OFFSET + 0.5) * res
        cz = ((k & KEY_MASK) - KEY_OFFSET + 0.5) * res
        inv_n = 1.0 / n
        mx = sums[v, 0] * inv_n
        my = sums[v, 1] * inv_n
        mz = sums[v, 2] * inv_n
        # Sample covariance (n - 1), as PCL's and ndt_omp's voxel grids.
        f = 1.0 / (n - 1)
        c00 = (outer[v, 0] - n * mx * mx) * f
        c01 = (outer[v, 1] - n * mx * my) * f
        c02 = (outer[v, 2] - n * mx * mz) * f
        c11 = (outer[v, 3] - n * my * my) * f
        c12 = (outer[v, 4] - n * my * mz) * f
        c22 = (outer[v, 5] - n * mz * mz) * f
        l0, l1, l2 = _jacobi_eig3(c00, c01, c02, c11, c12, c22, V)
        lmax = max(l0, max(l1, l2))
        floor = max(eig_ratio * lmax, eig_floor)
        l0 = max(l0, floor)
        l1 = max(l1, floor)
        l2 = max(l2, floor)
        i0 = 1.0 / l0
        i1 = 1.0 / l1
        i2 = 1.0 / l2
        # inverse covariance = V diag(1/l) V^T
        icov[v, 0] = V[0, 0] * V[0, 0] * i0 + V[0, 1] * V[0, 1] * i1 + V[0, 2] * V[0, 2] * i2
        icov[v, 1] = V[0, 0] * V[1, 0] * i0 + V[0, 1] * V[1, 1] * i1 + V[0, 2] * V[1, 2] * i2
        icov[v, 2] = V[0, 0] * V[2, 0] * i0 + V[0, 1] * V[2, 1] * i1 + V[0, 2] * V[2, 2] * i2
        icov[v, 3] = V[1, 0] * V[1, 0] * i0 + V[1, 1] * V[1, 1] * i1 + V[1, 2] * V[1, 2] * i2
        icov[v, 4] = V[1, 0] * V[2, 0] * i0 + V[1, 1] * V[2, 1] * i1 + V[1, 2] * V[2, 2] * i2
        icov[v, 5] = V[2, 0] * V[2, 0] * i0 + V[2, 1] * V[2, 1] * i1 + V[2, 2] * V[2, 2] * i2
        means[v, 0] = cx + mx
        means[v, 1] = cy + my
        means[v, 2] = cz + mz
        valid[v] = True


@njit(cache=True, nogil=True)
def gaussians_serial(keys, count, sums, outer, res, min_points, eig_ratio, eig_floor):
    """Voxel Gaussians (serial; safe to call from a background thread).

    Returns means (V, 3) absolute, inverse regularized covariances (V, 6: xx xy xz yy yz zz) and
    valid (V,) bool (count >= max(min_points, 3)). Covariance eigenvalues are clamped to
    ``max(eig_ratio * largest, eig_floor)`` (Magnusson's regularization, ratio 0.01).
    """
    nv = keys.shape[0]
    means = np.zeros((nv, 3))
    icov = np.zeros((nv, 6))
    valid = np.zeros(nv, dtype=np.bool_)
    _gaussians_range(keys, count, sums, outer, res, min_points, eig_ratio, eig_floor,
                     means, icov, valid, 0, nv)
    return means, icov, valid


@njit(cache=True, nogil=True)
def build_table(keys, size, shift):
    """Hash table over unique keys (V,): returns table_keys (size,), table_vals (size,).

    Both are strided views of one (size, 2) array, so a probe reads one cache line.
    """
    mask = size - 1
    table = np.empty((size, 2), dtype=np.int64)
    table_keys = table[:, 0]
    table_vals = table[:, 1]
    table_keys[:] = EMPTY
    for v in range(keys.shape[0]):
        key = keys[v]
        s = _slot(key, shift)
        while table_keys[s] != EMPTY:
            s = (s + 1) & mask
        table_keys[s] = key
        table_vals[s] = v
    return table_keys, table_vals


@njit(cache=True, nogil=True)
def lookup_keys(table_keys, table_vals, shift, query):
    """Rows of query keys (Q,) in the table, -1 where absent."""
    mask = table_keys.shape[0] - 1
    out = np.empty(query.shape[0], dtype=np.int64)
    for i in range(query.shape[0]):
        out[i] = _lookup(table_keys, table_vals, shift, mask, query[i])
    return out


@njit(cache=True, inline="always")
def _add_jmj(acc, o, ux, uy, uz, m00, m01, m02, m11, m12, m22):
    """acc[o:o+21] += upper triangle of J^T M J, J = [-skew(u), I] (3 x 6), M symmetric."""
    # P = skew(u) M is the rot-trans block; rot-rot = P skew(u)^T, row i = u x (row i of P)
    p00 = uy * m02 - uz * m01
    p01 = uy * m12 - uz * m11
    p02 = uy * m22 - uz * m12
    p10 = uz * m00 - ux * m02
    p11 = uz * m01 - ux * m12
    p12 = uz * m02 - ux * m22
    p20 = ux * m01 - uy * m00
    p21 = ux * m11 - uy * m01
    p22 = ux * m12 - uy * m02
    acc[o + 0] += uy * p02 - uz * p01
    acc[o + 1] += uz * p00 - ux * p02
    acc[o + 2] += ux * p01 - uy * p00
    acc[o + 3] += p00
    acc[o + 4] += p01
    acc[o + 5] += p02
    acc[o + 6] += uz * p10 - ux * p12
    acc[o + 7] += ux * p11 - uy * p10
    acc[o + 8] += p10
    acc[o + 9] += p11
    acc[o + 10] += p12
    acc[o + 11] += ux * p21 - uy * p20
    acc[o + 12] += p20
    acc[o + 13] += p21
    acc[o + 14] += p22
    acc[o + 15] += m00
    acc[o + 16] += m01
    acc[o + 17] += m02
    acc[o + 18] += m11
    acc[o + 19] += m12
    acc[o + 20] += m22


@njit(cache=True, nogil=True)
def build_neighbor_table(keys, table_keys, table_vals, shift):
    """DIRECT7 neighbour lists, so one hash look-up per source point replaces seven.

    keys: (V,) valid voxel keys (row v of the Gaussians), table_*: their hash table.
    Returns nkeys (W,) keys of every voxel that is a valid voxel or a face neighbour of one,
    their hash table (size, shift as ``table_size_for``) and nbr (W, 7) int32: column 0 the row
    of the voxel itself (-1: no Gaussian there), columns 1-6 the rows of its valid face
    neighbours, packed (-1 after the last). Column 0 alone serves DIRECT1, so DIRECT1 and
    DIRECT7 share one look-up (and one per-point memo) per source point.
    """
    nv = keys.shape[0]
    mask = table_keys.shape[0] - 1
    cand = np.empty(7 * nv, dtype=np.int64)
    nc = 0
    for v in range(nv):
        k = keys[v]
        ix = ((k >> 42) & KEY_MASK) - KEY_OFFSET
        iy = ((k >> 21) & KEY_MASK) - KEY_OFFSET
        iz = (k & KEY_MASK) - KEY_OFFSET
        for nb in range(7):
            jx, jy, jz = _offset7(ix, iy, iz, nb)
            if _in_range(jx, jy, jz):
                cand[nc] = _pack(jx, jy, jz)
                nc += 1
    size = 16
    while size < 2 * nc:
        size *= 2
    bits = 0
    while (1 << bits) < size:
        bits += 1
    nshift = 64 - bits
    nmask = size - 1
    ntable = np.empty((size, 2), dtype=np.int64)  # key and row in one cache line
    ntable_keys = ntable[:, 0]
    ntable_vals = ntable[:, 1]
    ntable_keys[:] = EMPTY
    nkeys = np.empty(nc, dtype=np.int64)
    nw = 0
    for i in range(nc):
        key = cand[i]
        s = _slot(key, nshift)
        while True:
            k = ntable_keys[s]
            if k == key:
                break
            if k == EMPTY:
                ntable_keys[s] = key
                ntable_vals[s] = nw
                nkeys[nw] = key
                nw += 1
                break
            s = (s + 1) & nmask
    # compact table sized for the unique voxels (the first was sized for all candidates)
    size = 16
    while size < 2 * nw:
        size *= 2
    ntable, nshift = _rehash(nkeys, nw, size)
    ntable_keys = ntable[:, 0]
    ntable_vals = ntable[:, 1]
    nbr = np.full((nw, 7), -1, dtype=np.int32)
    for w in range(nw):
        k = nkeys[w]
        ix = ((k >> 42) & KEY_MASK) - KEY_OFFSET
        iy = ((k >> 21) & KEY_MASK) - KEY_OFFSET
        iz = (k & KEY_MASK) - KEY_OFFSET
        nbr[w, 0] = _lookup(table_keys, table_vals, shift, mask, k)
        m = 1
        for nb in range(1, 7):
            jx, jy, jz = _offset7(ix, iy, iz, nb)
            if _in_range(jx, jy, jz):
                r = _lookup(table_keys, table_vals, shift, mask, _pack(jx, jy, jz))
                if r >= 0:
                    nbr[w, m] = r
                    m += 1
    return nkeys[:nw].copy(), ntable_keys, ntable_vals, nshift, nbr


@njit(cache=True, inline="always")
def _offset7(ix, iy, iz, nb):
    if nb == 1:
        return ix - 1, iy, iz
    if nb == 2:
        return ix + 1, iy, iz
    if nb == 3:
        return ix, iy - 1, iz
    if nb == 4:
        return ix, iy + 1, iz
    if nb == 5:
        return ix, iy, iz - 1
    if nb == 6:
        return ix, iy, iz + 1
    return ix, iy, iz


@njit(cache=True, nogil=True)
def coarsen_stats(keys, count, sums, outer, res):
    """Re-express voxel statistics at twice the resolution (parent voxel = floor(i / 2)).

    Inputs as ``voxel_stats`` output at voxel edge ``res``. Returns parent keys (V,) and the
    statistics moved to the parent centres, one row per child (not merged: use ``merge_stats``).
    """
    n = keys.shape[0]
    pkeys = np.empty(n, dtype=np.int64)
    psums = np.empty((n, 3))
    pouter = np.empty((n, 6))
    for v in range(n):
        k = keys[v]
        ix = ((k >> 42) & KEY_MASK) - KEY_OFFSET
        iy = ((k >> 21) & KEY_MASK) - KEY_OFFSET
        iz = (k & KEY_MASK) - KEY_OFFSET
        jx = ix >> 1  # arithmetic shift: floor division by 2 for negative indices too
        jy = iy >> 1
        jz = iz >> 1
        pkeys[v] = _pack(jx, jy, jz)
        # child centre minus parent centre
        dx = (ix + 0.5) * res - (jx + 0.5) * 2.0 * res
        dy = (iy + 0.5) * res - (jy + 0.5) * 2.0 * res
        dz = (iz + 0.5) * res - (jz + 0.5) * 2.0 * res
        m = count[v]
        sx = sums[v, 0]
        sy = sums[v, 1]
        sz = sums[v, 2]
        psums[v, 0] = sx + m * dx
        psums[v, 1] = sy + m * dy
        psums[v, 2] = sz + m * dz
        pouter[v, 0] = outer[v, 0] + 2.0 * sx * dx + m * dx * dx
        pouter[v, 1] = outer[v, 1] + sx * dy + dx * sy + m * dx * dy
        pouter[v, 2] = outer[v, 2] + sx * dz + dx * sz + m * dx * dz
        pouter[v, 3] = outer[v, 3] + 2.0 * sy * dy + m * dy * dy
        pouter[v, 4] = outer[v, 4] + sy * dz + dy * sz + m * dy * dz
        pouter[v, 5] = outer[v, 5] + 2.0 * sz * dz + m * dz * dz
    return pkeys, psums, pouter
