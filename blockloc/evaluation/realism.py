"""How much a LiDAR scan looks like a real one: a few statistics of one sweep, pure numpy/scipy.

The yardstick for the simulator (issue 15): the same code runs on real HDL-32E scans and on
simulated ones. Every statistic takes one scan: ``points`` (N, 3) float, sensor frame, metres;
``intensity`` (N,) 0..255; ``ring`` (N,) laser id (or None: derived from the elevation angle for
the HDL-32E's 32 known elevations); ``up`` the sensor frame's up direction (real Velodyne
drivers: +z; the NCLT / blockloc.sim lidar frame: -z).

Statistics (``scan_realism`` returns them as a dict):

- ``azimuth_step_deg``: median angle between consecutive returns of one laser.
- ground: points within ``ground_band_m`` of the lowest points of 2 m cells whose minimum lies
  near a robust plane through all cell minima (so roofs, crowns and walls are not ground).
- ``scattered_share``: of the non-ground points with enough neighbours within ``pca_radius_m``,
  the share whose neighbourhood is volumetric: with sigma_k = sqrt(eigenvalues) of the local
  covariance, sorted s1 >= s2 >= s3, the 3-D dimensionality s3 / s1 exceeds both the linear
  (s1 - s2) / s1 and the planar (s2 - s3) / s1 one (Demantke et al. 2011).
- ``thickness_m``: median of s3 (spread along the local normal) over those points.
- ``ground_residual_m``: rms point-to-plane residual of ground points in 3 m cells (4-25 m
  away, spanning >= 2 rings, tilted < 8 deg), a plane fitted per cell.
- ``dark_share`` / ``bright_share``: points with intensity <= 3 / >= 100.
- ``ground_ring_cv``: coefficient of variation over rings of the mean ground intensity (rings
  with >= 30 ground points): how unequal the lasers' gains are.
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

#: Elevation (deg) of the HDL-32E's 32 lasers (same table as blockloc.sim.lidar, sorted by id).
HDL32E_ELEVATION_DEG = np.array([
    -30.67, -9.33, -29.33, -8.00, -28.00, -6.67, -26.67, -5.33, -25.33, -4.00, -24.00, -2.67,
    -22.67, -1.33, -21.33, 0.00, -20.00, 1.33, -18.67, 2.67, -17.33, 4.00, -16.00, 5.33,
    -14.67, 6.67, -13.33, 8.00, -12.00, 9.33, -10.67, 10.67])

STAT_NAMES = ("azimuth_step_deg", "scattered_share", "thickness_m", "ground_residual_m",
              "dark_share", "bright_share", "ground_ring_cv")


def _as_up(points: np.ndarray, up) -> np.ndarray:
    """Points rotated so that ``up`` becomes +z (a proper rotation; only z and the horizontal
    plane matter to the statistics)."""
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    if np.allclose(u, z):
        return np.asarray(points, dtype=np.float64)
    if np.allclose(u, -z):
        return np.asarray(points, dtype=np.float64) * [1.0, -1.0, -1.0]
    v = np.cross(u, z)
    s, c = np.linalg.norm(v), float(u @ z)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    R = np.eye(3) + K + K @ K * ((1 - c) / s ** 2)
    return np.asarray(points, dtype=np.float64) @ R.T


def rings_from_elevation(points: np.ndarray, up=(0.0, 0.0, 1.0),
                         elevations_deg: np.ndarray = HDL32E_ELEVATION_DEG) -> np.ndarray:
    """(N,) laser id of each point: the laser whose elevation is nearest the point's.

    points: (N, 3) sensor frame, metres. The HDL-32E's lasers are 1.33 deg apart, so points
    within +-0.66 deg of the nominal elevation are assigned without ambiguity."""
    p = _as_up(points, up)
    el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    order = np.argsort(elevations_deg)
    srt = np.asarray(elevations_deg)[order]
    k = np.clip(np.searchsorted(srt, el), 1, len(srt) - 1)
    k -= (el - srt[k - 1]) < (srt[k] - el)
    return order[k].astype(np.int64)


def azimuth_step_deg(points: np.ndarray, ring: np.ndarray, up=(0.0, 0.0, 1.0)) -> float:
    """Median angle (deg) between azimuth-consecutive returns of the same laser."""
    p = _as_up(points, up)
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    steps = []
    for r in np.unique(ring):
        a = np.sort(az[ring == r])
        if len(a) > 10:
            d = np.diff(a)
            steps.append(d[d > 1e-4])
    if not steps:
        return float("nan")
    # drivers quantise azimuth (0.01 deg): the mean of the regular steps, gaps (lost returns) out
    st = np.concatenate(steps)
    return float(np.mean(st[st < 1.5 * np.median(st)]))


def ground_mask(points_up: np.ndarray, cell_m: float = 2.0, band_m: float = 0.25,
                plane_tol_m: float = 0.4, max_range_m: float = 40.0) -> np.ndarray:
    """(N,) bool: ground points of a scan whose z is up (see the module docstring)."""
    p = points_up
    rh = np.hypot(p[:, 0], p[:, 1])
    inside = (rh < max_range_m) & (rh > 1.0)
    ij = np.floor(p[:, :2] / cell_m).astype(np.int64)
    key = (ij[:, 0] + 100000) * 200003 + (ij[:, 1] + 100000)
    key = np.where(inside, key, -1)
    uniq, inv = np.unique(key, return_inverse=True)
    zmin = np.full(len(uniq), np.inf)
    np.minimum.at(zmin, inv, p[:, 2])
    cx = np.zeros(len(uniq))
    cy = np.zeros(len(uniq))
    cnt = np.bincount(inv, minlength=len(uniq)).astype(float)
    np.add.at(cx, inv, p[:, 0])
    np.add.at(cy, inv, p[:, 1])
    cx /= cnt
    cy /= cnt
    valid = uniq >= 0
    # a robust plane z = a x + b y + c through the cell minima (iteratively trimmed LSQ); the
    # sensor sits above the ground, so start from the lower half of the minima
    A = np.c_[cx, cy, np.ones_like(cx)]
    use = valid & (zmin <= np.median(zmin[valid]))
    coef = np.zeros(3)
    for tol in (2.0, 1.0, 0.6, plane_tol_m):
        if use.sum() < 3:
            break
        coef, *_ = np.linalg.lstsq(A[use], zmin[use], rcond=None)
        use = valid & (np.abs(zmin - A @ coef) < tol)
    ground_cell = use
    return ground_cell[inv] & (p[:, 2] - zmin[inv] < band_m)


def voxel_subsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices of one point (the first) per ``voxel_m`` cube: density-independent neighbourhoods."""
    key = np.floor(points / voxel_m).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(first)


def local_pca(points: np.ndarray, query: np.ndarray, radius_m: float, min_neighbors: int = 8,
              tree=None) -> tuple[np.ndarray, np.ndarray]:
    """Sorted sqrt-eigenvalues (M, 3) (s1 >= s2 >= s3, metres) of the covariance of all
    ``points`` within ``radius_m`` of each ``query`` index into ``points``, and the (M,) bool of
    queries with at least ``min_neighbors`` neighbours (the others are NaN)."""
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(points)
    nbrs = tree.query_ball_point(points[query], r=radius_m)
    lens = np.fromiter((len(n) for n in nbrs), dtype=np.int64, count=len(nbrs))
    ok = lens >= min_neighbors
    sig = np.full((len(query), 3), np.nan)
    if not ok.any():
        return sig, ok
    # second moments per neighbourhood, vectorised over the concatenated neighbour lists
    lens = lens[ok]
    flat = np.concatenate([np.asarray(n, dtype=np.int64) for n, o in zip(nbrs, ok) if o])
    owner = np.repeat(np.arange(len(lens)), lens)
    P = points[flat]
    mean = np.stack([np.bincount(owner, weights=P[:, a], minlength=len(lens)) for a in range(3)],
                    axis=1) / lens[:, None]
    d = P - mean[owner]
    C = np.empty((len(lens), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            C[:, a, b] = C[:, b, a] = np.bincount(owner, weights=d[:, a] * d[:, b],
                                                  minlength=len(lens)) / lens
    w = np.linalg.eigvalsh(C)[:, ::-1]
    sig[ok] = np.sqrt(np.clip(w, 0.0, None))
    return sig, ok


def scan_realism(points: np.ndarray, intensity: np.ndarray | None = None,
                 ring: np.ndarray | None = None, up=(0.0, 0.0, 1.0), *, pca_radius_m: float = 0.9,
                 pca_voxel_m: float = 0.1, max_range_m: float = 40.0, max_pca_points: int = 6000,
                 seed: int = 0) -> dict[str, float]:
    """The statistics of one scan (see the module docstring); NaN where a scan lacks the data.

    points: (N, 3) sensor frame, metres; returns at the origin (no return) are dropped.
    intensity: (N,) or None. ring: (N,) laser id or None (derived from elevation, HDL-32E).
    max_pca_points: the PCA statistics use a random subset of this many non-ground points.
    """
    pts = np.asarray(points, dtype=np.float64)
    r = np.linalg.norm(pts, axis=1)
    keep = np.isfinite(r) & (r > 0.1)
    pts = pts[keep]
    inten = None if intensity is None else np.asarray(intensity, dtype=np.float64)[keep]
    ring = rings_from_elevation(pts, up) if ring is None else np.asarray(ring)[keep]
    p = _as_up(pts, up)
    out = dict.fromkeys(STAT_NAMES, float("nan"))
    out["azimuth_step_deg"] = azimuth_step_deg(p, ring)
    g = ground_mask(p, max_range_m=max_range_m)
    out.update(_structure_stats(p, g, pca_radius_m, pca_voxel_m, max_range_m, max_pca_points, seed))
    out["ground_residual_m"] = ground_residual(p, g, ring)
    if inten is not None:
        out["dark_share"] = float(np.mean(inten <= 3.0))
        out["bright_share"] = float(np.mean(inten >= 100.0))
        out["ground_ring_cv"] = ground_ring_cv(inten, g, ring)
    return out


def _structure_stats(p, g, radius, voxel_m, max_range_m, max_points, seed) -> dict[str, float]:
    from scipy.spatial import cKDTree

    rh = np.hypot(p[:, 0], p[:, 1])
    cand = np.flatnonzero(~g & (rh < max_range_m))
    ng = p[cand]
    ng = ng[voxel_subsample(ng, voxel_m)]
    query = np.arange(len(ng))
    if len(query) > max_points:
        query = np.sort(np.random.default_rng(seed).choice(len(ng), max_points, replace=False))
    sig, ok = local_pca(ng, query, radius, tree=cKDTree(ng))
    s = sig[ok]
    if not len(s):
        return {"scattered_share": float("nan"), "thickness_m": float("nan")}
    s1 = np.maximum(s[:, 0], 1e-12)
    a1, a2, a3 = (s[:, 0] - s[:, 1]) / s1, (s[:, 1] - s[:, 2]) / s1, s[:, 2] / s1
    scattered = (a3 > a1) & (a3 > a2)
    return {"scattered_share": float(scattered.mean()), "thickness_m": float(np.median(s[:, 2]))}


def ground_residual(p: np.ndarray, g: np.ndarray, ring: np.ndarray, cell_m: float = 2.0,
                    min_range_m: float = 2.0, max_range_m: float = 40.0,
                    max_tilt_deg: float = 8.0) -> float:
    """RMS point-to-plane residual (m) of ground points, one plane fitted per cell."""
    rh = np.hypot(p[:, 0], p[:, 1])
    sel = np.flatnonzero(g & (rh >= min_range_m) & (rh <= max_range_m))
    if len(sel) < 10:
        return float("nan")
    ij = np.floor(p[sel, :2] / cell_m).astype(np.int64)
    key = (ij[:, 0] + 100000) * 200003 + (ij[:, 1] + 100000)
    order = np.argsort(key, kind="stable")
    key, sel = key[order], sel[order]
    starts = np.flatnonzero(np.r_[True, np.diff(key) != 0])
    ends = np.r_[starts[1:], len(key)]
    sq, n = 0.0, 0
    cos_max = np.cos(np.deg2rad(max_tilt_deg))
    for a, b in zip(starts, ends):
        idx = sel[a:b]
        if len(idx) < 10 or len(np.unique(ring[idx])) < 2:
            continue
        q = p[idx] - p[idx].mean(axis=0)
        w, V = np.linalg.eigh(q.T @ q / len(idx))
        if abs(V[2, 0]) < cos_max or w[1] < 0.04:  # tilted, or degenerate (a line)
            continue
        sq += float(np.sum((q @ V[:, 0]) ** 2))
        n += len(idx)
    return float(np.sqrt(sq / n)) if n else float("nan")


def ground_ring_cv(intensity: np.ndarray, g: np.ndarray, ring: np.ndarray,
                   min_points: int = 30) -> float:
    """Coefficient of variation over rings of the mean ground intensity."""
    means = []
    for r in np.unique(ring[g]):
        m = g & (ring == r)
        if m.sum() >= min_points:
            means.append(float(np.mean(intensity[m])))
    if len(means) < 3:
        return float("nan")
    means = np.asarray(means)
    return float(np.std(means) / max(np.mean(means), 1e-9))


#: Range bins (m) of :func:`intensity_by_range`.
RANGE_BINS_M = ((0.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0))


def intensity_by_range(scans, bins=RANGE_BINS_M) -> list[dict[str, float]]:
    """How intensity depends on range, pooled over scans: per bin of range (m), the share of all
    returns in it (``share``), the share of its returns with intensity <= 3 (``dark``) and its
    median intensity (``median``); NaN for an empty bin.

    scans: iterable of (points (N, 3) sensor frame m, intensity (N,)). A LiDAR that reports
    received power falls off with range; one that range-compensates does not: the yardstick for
    the simulator's intensity model (the real HDL-32E pair: dark ~12% within 5 m, ~27% at
    5-20 m)."""
    parts = [(np.linalg.norm(np.asarray(p, np.float64)[:, :3], axis=1), np.asarray(i, np.float64))
             for p, i in scans]
    r = np.concatenate([a for a, _ in parts]) if parts else np.zeros(0)
    inten = np.concatenate([b for _, b in parts]) if parts else np.zeros(0)
    out = []
    for lo, hi in bins:
        m = (r >= lo) & (r < hi)
        n = int(m.sum())
        out.append({"lo_m": float(lo), "hi_m": float(hi), "share": n / max(len(r), 1),
                    "dark": float(np.mean(inten[m] <= 3.0)) if n else float("nan"),
                    "median": float(np.median(inten[m])) if n else float("nan")})
    return out


def median_stats(rows: list[dict[str, float]]) -> dict[str, float]:
    """Per-statistic median over scans (NaN ignored)."""
    return {k: float(np.nanmedian([r[k] for r in rows])) if rows else float("nan")
            for k in STAT_NAMES}
