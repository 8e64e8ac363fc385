"""Numba kernels of the NDT engine (leaf module: importing it imports numba).

Everything here works on plain arrays; ``blockloc.registration.ndt`` holds the classes.

Voxel keys: integer voxel coordinates ``i = floor(x / resolution)`` packed into one int64,
21 bits per axis with an offset of 2**20 (so |i| < 2**20), ``key = (ix << 42) | (iy << 21) | iz``.
A voxel's statistics are kept relative to its centre ``(i + 0.5) * resolution`` so sums of outer
products stay well conditioned far from the origin and sums of different tiles can be added.

Hash table: open addressing with linear probing, size a power of two, ``table_keys`` (S,) int64
with -1 for an empty slot and ``table_vals`` (S,) int64 holding the row of the voxel (search
tables: strided views of one (S, 2) array, so that a probe touches one cache line).

Kernels release the GIL (``nogil``), so a background thread updating tiles does not stop the
tracking thread's Python code, and vice versa.

Derivatives follow the right perturbation ``T * Exp(xi)``, ``xi = (omega, v)`` (GTSAM Pose3 order,
SE(3) exponential chart). The kernels compute them in the "left" frame (with ``u = R p``) and the
caller rotates them with ``diag(R, R)``; see ``ndt_derivatives``.
"""

from __future__ import annotations

import os

# GNU OpenMP (numba's "omp" threading layer) spin-waits at every parallel region's barrier. When
# the cores are shared (other processes, or this process's own background threads), a waiting
# worker spins its whole spin count while the thread it waits for is descheduled: measured on 2
# shared cores, a 10k-point alignment took 330 ms median with 2 threads against 9 ms with 1.
# Passive waiting removes that (2 threads: 9 ms). Must be set before libgomp loads, i.e. before
# the first parallel kernel of the process runs; a value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
from numba import njit, prange  # noqa: E402

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
def _add_jmj(acc, c, o, ux, uy, uz, m00, m01, m02, m11, m12, m22):
    """acc[c, o:o+21] += upper triangle of J^T M J, J = [-skew(u), I] (3 x 6), M symmetric."""
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
    acc[c, o + 0] += uy * p02 - uz * p01
    acc[c, o + 1] += uz * p00 - ux * p02
    acc[c, o + 2] += ux * p01 - uy * p00
    acc[c, o + 3] += p00
    acc[c, o + 4] += p01
    acc[c, o + 5] += p02
    acc[c, o + 6] += uz * p10 - ux * p12
    acc[c, o + 7] += ux * p11 - uy * p10
    acc[c, o + 8] += p10
    acc[c, o + 9] += p11
    acc[c, o + 10] += p12
    acc[c, o + 11] += ux * p21 - uy * p20
    acc[c, o + 12] += p20
    acc[c, o + 13] += p21
    acc[c, o + 14] += p22
    acc[c, o + 15] += m00
    acc[c, o + 16] += m01
    acc[c, o + 17] += m02
    acc[c, o + 18] += m11
    acc[c, o + 19] += m12
    acc[c, o + 20] += m22


@njit(cache=True, nogil=True)
def build_neighbor_table(keys, table_keys, table_vals, shift):
    """DIRECT7 neighbour lists, so one hash look-up per source point replaces seven.

    keys: (V,) valid voxel keys (row v of the Gaussians), table_*: their hash table.
    Returns nkeys (W,) keys of every voxel that is a valid voxel or a face neighbour of one,
    their hash table (size, shift as ``table_size_for``) and nbr (W, 7) int32: the rows of the
    valid voxels among that voxel and its 6 face neighbours (-1 where absent).
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
        m = 0
        for nb in range(7):
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


# Pairs with d2/2 * q above this contribute exp(-30) ~ 1e-13 of a perfect match: skipped.
MAX_HALF_D2_Q = 30.0


@njit(cache=True, parallel=True, nogil=True)
def ndt_kernel(points, R, t, table_keys, table_vals, shift, gauss, inv_res, neighbors,
               d1, d2, inlier_q, mode, nchunks, ntable_keys, ntable_vals, nshift, nbr,
               key_cache, row_cache):
    """Score (and derivatives) of the point-to-distribution NDT objective at T = (R, t).

    points: (N, 3) source points; R (3, 3), t (3,) map them into the target frame.
    gauss: (M, 9) rows of mean (3) and inverse covariance (6: xx xy xz yy yz zz).
    neighbors: 1, 7 or 27 (DIRECT1/7/27 around the voxel containing the transformed point).
    ntable_*, nshift, nbr: ``build_neighbor_table`` output, used when neighbors == 7.
    key_cache, row_cache: (N,) int64 per-point memo of the last voxel key and its neighbour-list
    row (DIRECT7), reused across the iterations of one alignment (key -1: empty); a point
    usually stays in its voxel from one iteration to the next, which saves the hash probe.
    Per point and neighbour Gaussian: s = -d1 * exp(-d2/2 * x^T C x), x = R p + t - mean.
    mode: 0 score only; 1 exact gradient and Hessian; 2 gradient and the Gauss-Newton (IRLS)
    matrix sum a J^T C J (drops the second-order and -d2 y y^T terms: always PSD).

    Returns acc (nchunks, 29): per chunk [score, num_inliers, b_left (6), H_left upper triangle
    (21)] of the cost f = -score in the left frame (see module doc): the caller sums over chunks
    and maps them to the right perturbation with diag(R^T, R^T).
    """
    n = points.shape[0]
    mask = table_keys.shape[0] - 1
    nmask = ntable_keys.shape[0] - 1
    r00 = R[0, 0]
    r01 = R[0, 1]
    r02 = R[0, 2]
    r10 = R[1, 0]
    r11 = R[1, 1]
    r12 = R[1, 2]
    r20 = R[2, 0]
    r21 = R[2, 1]
    r22 = R[2, 2]
    t0 = t[0]
    t1 = t[1]
    t2 = t[2]
    acc = np.zeros((nchunks, 29))
    step = (n + nchunks - 1) // nchunks
    half_d2 = 0.5 * d2
    exact = mode == 1
    derivs = mode != 0
    for c in prange(nchunks):
        lo = c * step
        hi = min(n, lo + step)
        score = 0.0
        inliers = 0.0
        for i in range(lo, hi):
            px = points[i, 0]
            py = points[i, 1]
            pz = points[i, 2]
            ux = r00 * px + r01 * py + r02 * pz
            uy = r10 * px + r11 * py + r12 * pz
            uz = r20 * px + r21 * py + r22 * pz
            x0 = ux + t0
            x1 = uy + t1
            x2 = uz + t2
            fx = np.floor(x0 * inv_res)
            fy = np.floor(x1 * inv_res)
            fz = np.floor(x2 * inv_res)
            if not (-KEY_OFFSET < fx < KEY_OFFSET - 1 and -KEY_OFFSET < fy < KEY_OFFSET - 1
                    and -KEY_OFFSET < fz < KEY_OFFSET - 1):
                continue
            ix = np.int64(fx)
            iy = np.int64(fy)
            iz = np.int64(fz)
            # per-point sums over neighbour Gaussians: w = sum a y, M = sum a (C - d2 y y^T)
            # (exact) or sum a C (Gauss-Newton), a = -d1 d2 e > 0
            w0 = 0.0
            w1 = 0.0
            w2 = 0.0
            m00 = 0.0
            m01 = 0.0
            m02 = 0.0
            m11 = 0.0
            m12 = 0.0
            m22 = 0.0
            qmin = 1e300
            hits = 0
            row = -1
            if neighbors == 7:
                pk = _pack(ix, iy, iz)
                if key_cache[i] == pk:
                    row = row_cache[i]
                else:
                    row = _lookup(ntable_keys, ntable_vals, nshift, nmask, pk)
                    key_cache[i] = pk
                    row_cache[i] = row
                if row < 0:
                    continue
            for nb in range(neighbors):
                if neighbors == 7:
                    v = np.int64(nbr[row, nb])
                    if v < 0:
                        break  # lists are packed: the rest are absent too
                else:
                    jx = ix
                    jy = iy
                    jz = iz
                    if neighbors == 27:
                        jx = ix + (nb % 3) - 1
                        jy = iy + ((nb // 3) % 3) - 1
                        jz = iz + (nb // 9) - 1
                    v = _lookup(table_keys, table_vals, shift, mask, _pack(jx, jy, jz))
                    if v < 0:
                        continue
                dx = x0 - gauss[v, 0]
                dy = x1 - gauss[v, 1]
                dz = x2 - gauss[v, 2]
                c00 = gauss[v, 3]
                c01 = gauss[v, 4]
                c02 = gauss[v, 5]
                c11 = gauss[v, 6]
                c12 = gauss[v, 7]
                c22 = gauss[v, 8]
                y0 = c00 * dx + c01 * dy + c02 * dz
                y1 = c01 * dx + c11 * dy + c12 * dz
                y2 = c02 * dx + c12 * dy + c22 * dz
                q = dx * y0 + dy * y1 + dz * y2
                if q < qmin:
                    qmin = q
                if half_d2 * q > MAX_HALF_D2_Q:
                    continue
                e = np.exp(-half_d2 * q)
                score += -d1 * e
                if derivs:
                    hits += 1
                    a = -d1 * d2 * e
                    w0 += a * y0
                    w1 += a * y1
                    w2 += a * y2
                    m00 += a * c00
                    m01 += a * c01
                    m02 += a * c02
                    m11 += a * c11
                    m12 += a * c12
                    m22 += a * c22
                    if exact:
                        ad2 = a * d2
                        m00 -= ad2 * y0 * y0
                        m01 -= ad2 * y0 * y1
                        m02 -= ad2 * y0 * y2
                        m11 -= ad2 * y1 * y1
                        m12 -= ad2 * y1 * y2
                        m22 -= ad2 * y2 * y2
            if qmin <= inlier_q:
                inliers += 1.0
            if hits > 0:
                # b = [u x w; w]
                acc[c, 2] += uy * w2 - uz * w1
                acc[c, 3] += uz * w0 - ux * w2
                acc[c, 4] += ux * w1 - uy * w0
                acc[c, 5] += w0
                acc[c, 6] += w1
                acc[c, 7] += w2
                _add_jmj(acc, c, 8, ux, uy, uz, m00, m01, m02, m11, m12, m22)
                if exact:
                    # second-order term S(w, u) of the SE(3) exponential
                    wu = w0 * ux + w1 * uy + w2 * uz
                    acc[c, 8] += w0 * ux - wu
                    acc[c, 9] += 0.5 * (ux * w1 + w0 * uy)
                    acc[c, 10] += 0.5 * (ux * w2 + w0 * uz)
                    acc[c, 12] += 0.5 * w2
                    acc[c, 13] += -0.5 * w1
                    acc[c, 14] += w1 * uy - wu
                    acc[c, 15] += 0.5 * (uy * w2 + w1 * uz)
                    acc[c, 16] += -0.5 * w2
                    acc[c, 18] += 0.5 * w0
                    acc[c, 19] += w2 * uz - wu
                    acc[c, 20] += 0.5 * w1
                    acc[c, 21] += -0.5 * w0
        acc[c, 0] += score
        acc[c, 1] += inliers
    return acc


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
