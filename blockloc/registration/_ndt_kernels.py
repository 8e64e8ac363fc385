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
SE(3) exponential chart). ``ndt_evaluate`` sums them in the "left" frame (with ``u = R p``) and
``right_derivatives`` rotates them with ``diag(R, R)``.

Alignment: ``ndt_level`` runs all Newton iterations of one level (direction, step cap, line
search, stopping test) in compiled code, so an alignment is one Python -> numba call per level
and stage; each iteration is one or more ``ndt_evaluate`` passes over the source points
(parallel above SERIAL_MAX_POINTS points, else serial).
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

from blockloc.registration._ndt_voxels import (  # noqa: E402, F401  (re-exported: ndt.py and tests use them from here)
    EMPTY,
    HASH_MUL,
    KEY_MASK,
    KEY_OFFSET,
    _TRI,
    TRI_FULL,
    TRI_I,
    TRI_J,
    _add_jmj,
    build_neighbor_table,
    build_table,
    coarsen_stats,
    _gaussians_range,
    gaussians_serial,
    _in_range,
    _jacobi_eig3,
    _lookup,
    lookup_keys,
    merge_stats,
    _offset7,
    _pack,
    _rehash,
    _slot,
    table_size_for,
    unpack_keys,
    voxel_stats,
)

# Pairs with d2/2 * q above this contribute exp(-30) ~ 1e-13 of a perfect match: skipped.
MAX_HALF_D2_Q = 30.0

# Evaluation modes and the layout of the accumulator row they fill.
MODE_SCORE = 0  # score and inliers only
MODE_EXACT = 1  # + gradient and exact Hessian
MODE_GN = 2  # + gradient and Gauss-Newton (IRLS) matrix
MODE_BOTH = 3  # + gradient, exact Hessian and Gauss-Newton matrix in the same pass
ACC_B = 2  # b_left (6) after score, inliers
ACC_H = 8  # exact H_left, upper triangle (21)
ACC_HGN = 29  # Gauss-Newton H_left, upper triangle (21)
ACC_LEN = 50
# A chunk of this many points or fewer is evaluated without a parallel region: its start-up
# and barrier cost more than they save (the coarse level's ~1500 points: measured 0.07 ms
# serial against 0.07-0.14 ms with 2 threads on shared cores).
SERIAL_MAX_POINTS = 2048


# Strict IEEE arithmetic on purpose, no fastmath: with contract (FMA) and reassoc (5-10% faster
# passes) LLVM's choices depended on how the kernel was compiled (afresh inside its caller, or
# loaded from numba's cache), so the same alignment differed in the last bits from one process to
# the next, and a map build's blocks with them (tests/registration/test_ndt_reproducible.py)
@njit(cache=True, nogil=True)
def _eval_chunk(points, lo, hi, stride, T, level, neighbors, d1, d2, inlier_q, mode, key_cache,
                row_cache, out):
    """Add the terms of points[lo:hi:stride] to out (ACC_LEN,); see ``ndt_evaluate``."""
    table_keys, table_vals, shift, gauss, inv_res, ntable_keys, ntable_vals, nshift, nbr = level
    mask = table_keys.shape[0] - 1
    nmask = ntable_keys.shape[0] - 1
    r00 = T[0, 0]
    r01 = T[0, 1]
    r02 = T[0, 2]
    r10 = T[1, 0]
    r11 = T[1, 1]
    r12 = T[1, 2]
    r20 = T[2, 0]
    r21 = T[2, 1]
    r22 = T[2, 2]
    t0 = T[0, 3]
    t1 = T[1, 3]
    t2 = T[2, 3]
    half_d2 = 0.5 * d2
    exact = mode == MODE_EXACT or mode == MODE_BOTH
    gn = mode == MODE_GN or mode == MODE_BOTH
    derivs = mode != MODE_SCORE
    score = 0.0
    inliers = 0.0
    last_pk = np.int64(-1)  # the voxel of the point before (a key is never -1)
    last_row = np.int64(-1)
    for i in range(lo, hi, stride):
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
        row = -1
        if neighbors != 27:
            # DIRECT1/7: one probe of the neighbour-list table, memoized per point (a point
            # usually stays in its voxel from one iteration to the next)
            pk = _pack(ix, iy, iz)
            if key_cache[i] == pk:
                row = row_cache[i]
            else:
                # scan order is spatially coherent: the previous point's voxel is often this
                # one's too (a miss on a big table costs a cache miss: the first pass of an
                # alignment measured ~2x the cost of the later ones)
                if pk == last_pk:
                    row = last_row
                else:
                    row = _lookup(ntable_keys, ntable_vals, nshift, nmask, pk)
                key_cache[i] = pk
                row_cache[i] = row
            last_pk = pk
            last_row = row
            if row < 0:
                continue
        # per-point sums over neighbour Gaussians, a = -d1 d2 e > 0: w = sum a y,
        # G = sum a C (Gauss-Newton), Y = sum a d2 y y^T (exact: G - Y)
        w0 = 0.0
        w1 = 0.0
        w2 = 0.0
        g00 = 0.0
        g01 = 0.0
        g02 = 0.0
        g11 = 0.0
        g12 = 0.0
        g22 = 0.0
        y00 = 0.0
        y01 = 0.0
        y02 = 0.0
        y11 = 0.0
        y12 = 0.0
        y22 = 0.0
        qmin = 1e300
        hits = 0
        for nb in range(neighbors):
            if neighbors == 27:
                v = _lookup(table_keys, table_vals, shift, mask,
                            _pack(ix + (nb % 3) - 1, iy + ((nb // 3) % 3) - 1, iz + (nb // 9) - 1))
                if v < 0:
                    continue
            else:
                v = np.int64(nbr[row, nb])
                if v < 0:
                    if nb == 0:
                        continue  # no Gaussian in the point's own voxel; faces may have one
                    break  # face lists are packed: the rest are absent too
            dx = x0 - gauss[v, 0]
            dy = x1 - gauss[v, 1]
            dz = x2 - gauss[v, 2]
            c00 = gauss[v, 3]
            c01 = gauss[v, 4]
            c02 = gauss[v, 5]
            c11 = gauss[v, 6]
            c12 = gauss[v, 7]
            c22 = gauss[v, 8]
            ya = c00 * dx + c01 * dy + c02 * dz
            yb = c01 * dx + c11 * dy + c12 * dz
            yc = c02 * dx + c12 * dy + c22 * dz
            q = dx * ya + dy * yb + dz * yc
            if q < qmin:
                qmin = q
            if half_d2 * q > MAX_HALF_D2_Q:
                continue
            e = np.exp(-half_d2 * q)
            score += -d1 * e
            if derivs:
                hits += 1
                a = -d1 * d2 * e
                w0 += a * ya
                w1 += a * yb
                w2 += a * yc
                g00 += a * c00
                g01 += a * c01
                g02 += a * c02
                g11 += a * c11
                g12 += a * c12
                g22 += a * c22
                if exact:
                    ad2 = a * d2
                    y00 += ad2 * ya * ya
                    y01 += ad2 * ya * yb
                    y02 += ad2 * ya * yc
                    y11 += ad2 * yb * yb
                    y12 += ad2 * yb * yc
                    y22 += ad2 * yc * yc
        if qmin <= inlier_q:
            inliers += 1.0
        if hits == 0:
            continue
        # b = [u x w; w]
        out[2] += uy * w2 - uz * w1
        out[3] += uz * w0 - ux * w2
        out[4] += ux * w1 - uy * w0
        out[5] += w0
        out[6] += w1
        out[7] += w2
        if gn:
            _add_jmj(out, ACC_HGN, ux, uy, uz, g00, g01, g02, g11, g12, g22)
        if exact:
            _add_jmj(out, ACC_H, ux, uy, uz, g00 - y00, g01 - y01, g02 - y02, g11 - y11,
                     g12 - y12, g22 - y22)
            # second-order term S(w, u) of the SE(3) exponential
            wu = w0 * ux + w1 * uy + w2 * uz
            out[8] += w0 * ux - wu
            out[9] += 0.5 * (ux * w1 + w0 * uy)
            out[10] += 0.5 * (ux * w2 + w0 * uz)
            out[12] += 0.5 * w2
            out[13] += -0.5 * w1
            out[14] += w1 * uy - wu
            out[15] += 0.5 * (uy * w2 + w1 * uz)
            out[16] += -0.5 * w2
            out[18] += 0.5 * w0
            out[19] += w2 * uz - wu
            out[20] += 0.5 * w1
            out[21] += -0.5 * w0
    out[0] += score
    out[1] += inliers


@njit(cache=True, parallel=True, nogil=True)
def _eval_parallel(points, stride, T, level, neighbors, d1, d2, inlier_q, mode, nchunks,
                   key_cache, row_cache):
    n = points.shape[0]
    acc = np.zeros((nchunks, ACC_LEN))
    per_chunk = ((n + stride - 1) // stride + nchunks - 1) // nchunks  # points per chunk
    for c in prange(nchunks):
        lo = c * per_chunk * stride
        hi = min(n, lo + per_chunk * stride)
        _eval_chunk(points, lo, hi, stride, T, level, neighbors, d1, d2, inlier_q, mode,
                    key_cache, row_cache, acc[c])
    total = np.zeros(ACC_LEN)
    for c in range(nchunks):
        for j in range(ACC_LEN):
            total[j] += acc[c, j]
    return total


@njit(cache=True, nogil=True)
def ndt_evaluate(points, stride, T, level, neighbors, d1, d2, inlier_q, mode, key_cache,
                 row_cache):
    """Score (and derivatives) of the point-to-distribution NDT objective at T, one pass.

    points: (N, 3) float64 source points, of which every stride-th is used (no copy);
    T: (4, 4) maps them into the target frame.
    level: (table_keys, table_vals, shift, gauss, inv_res, ntable_keys, ntable_vals, nshift,
    nbr), one level's hash table of valid voxels, Gaussians gauss (M, 9: mean (3), inverse
    covariance (6: xx xy xz yy yz zz)), 1 / resolution and ``build_neighbor_table`` output.
    neighbors: 1, 7 or 27 (DIRECT1/7/27 around the voxel containing the transformed point).
    key_cache, row_cache: (N,) int64 per-point memo of the last voxel key and its neighbour-list
    row (DIRECT1/7), reused across the passes of one alignment on one level (key -1: empty).
    Per point and neighbour Gaussian: s = -d1 * exp(-d2/2 * x^T C x), x = T p - mean.
    mode: MODE_SCORE, MODE_EXACT (exact gradient and Hessian), MODE_GN (gradient and the
    Gauss-Newton / IRLS matrix sum a J^T C J: drops the second-order and -d2 y y^T terms, always
    PSD) or MODE_BOTH (both matrices from the same pass).

    Returns acc (ACC_LEN,): [score, num_inliers, b_left (6), H_left exact (21), H_left
    Gauss-Newton (21)] (upper triangles in TRI_I/TRI_J order; rows a mode does not fill are 0)
    of the cost f = -score in the left frame (see module doc; ``right_derivatives`` maps them
    to the right perturbation). Runs serially up to SERIAL_MAX_POINTS points, else in
    parallel over up to 64 chunks (numba's current thread count).
    """
    n = points.shape[0]
    used = (n + stride - 1) // stride
    if used <= SERIAL_MAX_POINTS:
        acc = np.zeros(ACC_LEN)
        _eval_chunk(points, 0, n, stride, T, level, neighbors, d1, d2, inlier_q, mode,
                    key_cache, row_cache, acc)
        return acc
    nchunks = min(64, used // 256)
    return _eval_parallel(points, stride, T, level, neighbors, d1, d2, inlier_q, mode, nchunks,
                          key_cache, row_cache)


@njit(cache=True, nogil=True)
def ndt_inliers_per_group(points, starts, T, level, neighbors, d1, d2, inlier_q, key_cache, row_cache):
    """(G,) int64: for each group g of points[starts[g]:starts[g + 1]] (``starts`` (G + 1,) int64,
    ascending), the inliers ``ndt_evaluate`` counts over that slice alone (MODE_SCORE), in one call:
    a count of points is the same whichever pass adds it up."""
    G = starts.shape[0] - 1
    out = np.zeros(G, np.int64)
    acc = np.zeros(ACC_LEN)
    for g in range(G):
        for j in range(ACC_LEN):
            acc[j] = 0.0
        _eval_chunk(points, starts[g], starts[g + 1], 1, T, level, neighbors, d1, d2, inlier_q, MODE_SCORE,
                    key_cache, row_cache, acc)
        out[g] = np.int64(np.round(acc[1]))
    return out


@njit(cache=True, nogil=True)
def _unpack_rotate(acc, o, T, H):
    """H (6, 6) = diag(R, R)^T S diag(R, R), S the symmetric matrix of acc[o:o+21]."""
    S = np.empty((6, 6))
    for i in range(6):
        for j in range(6):
            S[i, j] = acc[o + TRI_FULL[i, j]]
    Rb = np.zeros((6, 6))
    for i in range(3):
        for j in range(3):
            Rb[i, j] = T[i, j]
            Rb[i + 3, j + 3] = T[i, j]
    M = Rb.T @ S @ Rb
    for i in range(6):
        for j in range(6):
            H[i, j] = 0.5 * (M[i, j] + M[j, i])


@njit(cache=True, nogil=True)
def right_derivatives(acc, T, b, H, Hgn):
    """Left-frame sums of ``ndt_evaluate`` at T -> right-perturbation b (6,), exact H (6, 6) and
    Gauss-Newton Hgn (6, 6), written in place (J_right = J_left diag(R, R))."""
    for i in range(6):
        b[i] = 0.0
        for j in range(3):
            b[i] += T[j, i % 3] * acc[ACC_B + 3 * (i // 3) + j]
    _unpack_rotate(acc, ACC_H, T, H)
    _unpack_rotate(acc, ACC_HGN, T, Hgn)


@njit(cache=True, nogil=True)
def se3_exp(xi):
    """(6,) tangent (rotation rad, translation m) -> (4, 4), GTSAM ``Pose3.Expmap``."""
    wx = xi[0]
    wy = xi[1]
    wz = xi[2]
    theta2 = wx * wx + wy * wy + wz * wz
    W = np.zeros((3, 3))
    W[0, 1] = -wz
    W[0, 2] = wy
    W[1, 0] = wz
    W[1, 2] = -wx
    W[2, 0] = -wy
    W[2, 1] = wx
    W2 = W @ W
    if theta2 < 1e-12:
        A = 1.0 - theta2 / 6.0
        B = 0.5 - theta2 / 24.0
        C = 1.0 / 6.0 - theta2 / 120.0
    else:
        theta = np.sqrt(theta2)
        A = np.sin(theta) / theta
        B = (1.0 - np.cos(theta)) / theta2
        C = (theta - np.sin(theta)) / (theta2 * theta)
    T = np.eye(4)
    I3 = np.eye(3)
    T[:3, :3] = I3 + A * W + B * W2
    T[:3, 3] = (I3 + B * W + C * W2) @ xi[3:]
    return T


@njit(cache=True, nogil=True)
def _solve_clamped(H, b, floor_abs):
    """-H^+ b with H's eigenvalues clamped to >= max(1e-9 x largest, floor_abs)."""
    lam, V = np.linalg.eigh(H)
    lam = np.maximum(lam, max(1e-9 * lam[-1], floor_abs))
    return -(V @ ((V.T @ b) / lam))


@njit(cache=True, nogil=True)
def ndt_level(points, stride, T_init, level, neighbors, d1, d2, inlier_q, key_cache, row_cache,
              max_iterations, epsilon, max_step_m, max_step_rad, gauss_newton, first_mode,
              max_first_step=np.inf):
    """Newton iterations of one level, step and line search included (one call per level).

    Arguments as ``ndt_evaluate``; T_init (4, 4) the start. Per iteration: direction -H^-1 b
    with the exact Hessian where positive definite (eigenvalues > 1e-9 x the largest), else
    with the Gauss-Newton matrix (eigenvalues clamped, so a descent direction); with
    ``gauss_newton`` always the latter. The step is capped to max_step_m / max_step_rad, then
    a backtracking line search (Armijo 1e-4, halving up to 8 times, or, for a Newton step under 10 x
    epsilon with the exact Hessian positive definite, until the step is under epsilon: no
    decrease then means converged) on the score; the first
    trial is evaluated with derivatives (usually accepted as it is). The Gauss-Newton matrix
    comes from the same pass as the exact Hessian whenever the previous one on this level was
    not positive definite (first_mode for the first pass: MODE_EXACT or MODE_BOTH), else from
    an extra pass when needed. Stops (converged) when the next step ``|d|`` (after the cap; rad
    and m together) < epsilon, without taking it: T then lies within about epsilon of the
    minimum of the local quadratic model that b and H at T describe, and the pass after the
    step is saved; or when the step just taken ``|alpha d|`` < epsilon; or (not converged)
    after max_iterations (0: evaluate only). When the first step (after the cap) is at least
    ``max_first_step`` long, nothing is taken: T_init returned, 0 iterations, not converged
    (the start is not where this level alone converges fast).

    Returns (T (4, 4), acc (ACC_LEN,) at T, b (6,), H (6, 6) exact (Gauss-Newton with
    gauss_newton), iterations, converged, passes over the points).
    """
    T = T_init.copy()
    mode = MODE_GN if gauss_newton else first_mode
    acc = ndt_evaluate(points, stride, T, level, neighbors, d1, d2, inlier_q, mode, key_cache,
                       row_cache)
    passes = 1
    iterations = 0
    converged = False
    done = False
    b = np.zeros(6)
    H = np.zeros((6, 6))
    Hgn = np.zeros((6, 6))
    while True:
        right_derivatives(acc, T, b, H, Hgn)
        if done or iterations >= max_iterations:
            break
        positive = False
        if not gauss_newton:
            lam, V = np.linalg.eigh(H)
            positive = lam[0] > 1e-9 * max(lam[-1], 1e-300)
            if positive:
                d = -(V @ ((V.T @ b) / lam))
            elif mode != MODE_BOTH:
                acc_gn = ndt_evaluate(points, stride, T, level, neighbors, d1, d2, inlier_q,
                                      MODE_GN, key_cache, row_cache)
                passes += 1
                _unpack_rotate(acc_gn, ACC_HGN, T, Hgn)
        if not positive:
            d = _solve_clamped(Hgn, b, 1e-12)
        # cap the step so that one Newton step cannot leap across many voxels
        scale = 1.0
        nr = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        nt = np.sqrt(d[3] * d[3] + d[4] * d[4] + d[5] * d[5])
        if nr > max_step_rad:
            scale = min(scale, max_step_rad / nr)
        if nt > max_step_m:
            scale = min(scale, max_step_m / nt)
        d = d * scale
        dnorm = np.sqrt(nr * nr + nt * nt) * scale
        if iterations == 0 and dnorm >= max_first_step:
            break
        if dnorm < epsilon:
            converged = True
            break
        slope = b @ d  # directional derivative of the cost (< 0)
        trial_mode = MODE_GN if gauss_newton else (MODE_EXACT if positive else MODE_BOTH)
        alpha = 1.0
        accepted = False
        trial_no = 0
        T_try = T
        acc_try = acc
        while trial_no < 9:
            if trial_no > 0 and positive and dnorm < 10.0 * epsilon and alpha * dnorm < epsilon:
                # at the optimum (a Newton step with a positive-definite Hessian, under 10 x
                # epsilon, that did not decrease the score; a Gauss-Newton direction there may
                # be short far from the optimum (seen: 1 cm off), so it keeps halving):
                # a step shorter than epsilon is below the stop test either way, so its
                # score-only passes are saved (seen: 11 passes instead of 3 from a converged
                # pose); reported converged, as below, the pose within epsilon of where the
                # shorter step would have put it
                break
            T_try = T @ se3_exp(alpha * d)
            acc_try = ndt_evaluate(points, stride, T_try, level, neighbors, d1, d2, inlier_q,
                                   trial_mode if trial_no == 0 else MODE_SCORE, key_cache,
                                   row_cache)
            passes += 1
            if -acc_try[0] <= -acc[0] + 1e-4 * alpha * slope:
                accepted = True
                break
            alpha *= 0.5
            trial_no += 1
        iterations += 1
        if not accepted:
            # no decrease along a descent direction: at the optimum to numerical precision
            converged = dnorm < 10.0 * epsilon or abs(slope) < 1e-9
            break
        T = T_try
        mode = trial_mode
        if trial_no == 0:
            acc = acc_try
        else:
            acc = ndt_evaluate(points, stride, T, level, neighbors, d1, d2, inlier_q, mode,
                               key_cache, row_cache)
            passes += 1
        if alpha * dnorm < epsilon:
            converged = True
            done = True
    if gauss_newton:
        H[:, :] = Hgn
    return T, acc, b, H, iterations, converged, passes
