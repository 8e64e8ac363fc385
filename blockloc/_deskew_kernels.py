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
