"""numba kernel of scan deskewing (imported lazily by ``blockloc.deskew``; compiled once, cached on disk)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)  # serial: ~5-20k points take < 0.5 ms; no contention with map builds
def deskew_kernel(pts, t, table_t, R, w_int, trans):  # pragma: no cover - compiled
    """Per point: find its table interval, rotate by R_j exp(alpha w_j), add lerped translation.

    pts (N, 3) float64; t (N,) float64; table_t (K,) increasing, K >= 2; R (K, 3, 3);
    w_int (K-1, 3) rotation vectors of R_j^T R_{j+1}; trans (K, 3). Returns (N, 3).
    """
    n = pts.shape[0]
    K = table_t.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        ti = min(max(t[i], table_t[0]), table_t[K - 1])
        lo = 0
        hi = K - 1
        while hi - lo > 1:  # binary search: table_t[lo] <= ti < table_t[hi]
            mid = (lo + hi) // 2
            if table_t[mid] <= ti:
                lo = mid
            else:
                hi = mid
        j = lo
        span = table_t[j + 1] - table_t[j]
        a = (ti - table_t[j]) / span if span > 0 else 0.0
        wx = w_int[j, 0] * a
        wy = w_int[j, 1] * a
        wz = w_int[j, 2] * a
        th = np.sqrt(wx * wx + wy * wy + wz * wz)
        px = pts[i, 0]
        py = pts[i, 1]
        pz = pts[i, 2]
        if th > 1e-12:
            kx = wx / th
            ky = wy / th
            kz = wz / th
            c = np.cos(th)
            s = np.sin(th)
            kdp = kx * px + ky * py + kz * pz
            cx = ky * pz - kz * py
            cy = kz * px - kx * pz
            cz = kx * py - ky * px
            qx = px * c + cx * s + kx * kdp * (1.0 - c)
            qy = py * c + cy * s + ky * kdp * (1.0 - c)
            qz = pz * c + cz * s + kz * kdp * (1.0 - c)
        else:
            qx = px
            qy = py
            qz = pz
        for r in range(3):
            out[i, r] = (R[j, r, 0] * qx + R[j, r, 1] * qy + R[j, r, 2] * qz
                         + trans[j, r] + (trans[j + 1, r] - trans[j, r]) * a)
    return out


@nb.njit(cache=True)
def interval_rotvecs(R):  # pragma: no cover - compiled
    """(K-1, 3) rotation vectors w_j = log(R_j^T R_{j+1}) of a (K, 3, 3) table, and whether every
    angle stayed below 3 rad (else the caller uses a log that is exact near pi: the axis from
    the antisymmetric part is ill-conditioned there; within a sweep angles are milliradians)."""
    K = R.shape[0]
    out = np.zeros((max(K - 1, 0), 3))
    for j in range(K - 1):
        # M = R_j^T R_{j+1}: only its trace and antisymmetric part are needed
        m = np.zeros((3, 3))
        for a in range(3):
            for b in range(3):
                m[a, b] = R[j, 0, a] * R[j + 1, 0, b] + R[j, 1, a] * R[j + 1, 1, b] + R[j, 2, a] * R[j + 1, 2, b]
        c = 0.5 * (m[0, 0] + m[1, 1] + m[2, 2] - 1.0)
        c = min(1.0, max(-1.0, c))
        th = np.arccos(c)
        vx = 0.5 * (m[2, 1] - m[1, 2])
        vy = 0.5 * (m[0, 2] - m[2, 0])
        vz = 0.5 * (m[1, 0] - m[0, 1])
        if th > 3.0:
            return out, False
        # theta / sin(theta) (series below 1e-4 rad: 1 + theta^2 / 6)
        f = 1.0 + th * th / 6.0 if th < 1e-4 else th / np.sin(th)
        out[j, 0] = f * vx
        out[j, 1] = f * vy
        out[j, 2] = f * vz
    return out, True
