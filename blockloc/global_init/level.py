"""Gravity from the scan itself, for sequences without an IMU: the floor (or ground) plane.

:func:`gravity_from_scan` finds the dominant floor plane below the sensor and returns gravity
as the plane's downward normal, in the frame the points are given in (the body frame, for
``project_scan`` and the global localizer):

1. Local planes: the points are binned in cubic cells (``cell_m``, 0.5 m); each cell with at
   least 6 points gets its covariance (moments summed with ``np.bincount``, no KD-tree) and is
   kept when planar (smallest eigenvalue under ``planarity`` of the trace). Its normal is the
   smallest eigenvector, weighted by the cell's point count.
2. The vertical axis: a vote over the normals within ``max_tilt_deg`` of ``up_hint`` (a 2D
   histogram of 1 deg bins in the tangent plane of ``up_hint``, smoothed over 3x3 bins), refined
   by the weighted mean of the normals within 5 deg, then 3 deg, of the peak. Walls (normals
   perpendicular to the vertical) lie outside the cone whenever the sensor is tilted less than
   90 - ``max_tilt_deg`` deg, so scans dominated by walls do not move the vote; floor, ceiling,
   table tops and ground share the vertical axis and all vote for it.
3. The floor: among the points of planar cells facing along that axis (10 deg; a horizontal
   slice of walls is not a floor), the most populated 5 cm height bin more than 0.3 m below the
   sensor (a ceiling lies above it); a plane is fitted (SVD) to them within 10 cm of it, then
   refitted to all points within 5 cm and 3 cm of each new plane. Gravity = minus the
   plane's normal, pointing away from the sensor side.
Without a floor below the sensor (fewer than ``min_floor_points`` points), the axis of step 2 is
returned with method ``"normals"`` and a lower confidence.

Confidence (a heuristic in [0, 1]): floor ``n / (n + 500)`` for n inlier points, times
``exp(-(a / 2 deg)^2)`` for the angle a between the fitted plane and the normal vote; normals-only
``0.5 * share`` (share of the planar cells' weight that voted for the axis).

On the real Hilti walk (177 scans, a 64-beam sensor, partly indoors; rolls to 37 deg) the floor
normals agree with the floor plane fitted once over the whole map to 0.11 deg median, 0.26 deg at
most, at about 25 ms a scan (development figures, 2 shared cores). That map's own vertical differs
from the floor normal by 2.7 deg (the first scan's frame is not level).

:func:`refine_gravity_by_ndt` refines roll and pitch (with the rest of the pose) by NDT against
a map once a candidate pose is known; gravity then follows the map's vertical.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from blockloc.errors import GlobalInitError
from blockloc.geometry import tangent_basis

log = logging.getLogger(__name__)

GRAVITY_M_S2 = 9.81


@dataclass
class GravityEstimate:
    """Gravity from a scan.

    direction: (3,) unit vector of gravity (pointing down) in the points' frame.
    confidence: heuristic in [0, 1] (see the module docstring).
    method: 'floor' (plane fitted below the sensor), 'normals' (normal vote only) or 'ndt'.
    num_points: inlier points of the floor plane (normals: planar cells that voted; ndt: NDT
    inliers). floor_distance_m: the sensor's height above the floor plane (NaN without one).
    """

    direction: np.ndarray
    confidence: float
    method: str
    num_points: int = 0
    floor_distance_m: float = float("nan")

    @property
    def gravity(self) -> np.ndarray:
        """(3,) gravity vector, m/s^2 (``GRAVITY_M_S2`` along ``direction``)."""
        return GRAVITY_M_S2 * self.direction


def up_hint_from_gravity_map(gravity_map: np.ndarray) -> np.ndarray:
    """(3,) the up direction of a level body whose axes match the map's: -gravity_map / |g|
    (z-up maps: +z; NCLT-style z-down maps: -z)."""
    from blockloc.geometry import up_from_gravity

    return up_from_gravity(gravity_map)


def _planar_cells(points: np.ndarray, cell_m: float, planarity: float, min_points: int = 6):
    """Normals (M, 3) and weights (M,) of the planar cells of a cubic grid, and the planar cell
    (0..M-1) each point (N,) falls in, -1 for points in other cells."""
    keys = np.floor(points / cell_m).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, inv, cnt = np.unique(flat, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    m = len(cnt)
    mean = np.stack([np.bincount(inv, points[:, k], m) for k in range(3)], axis=1) / cnt[:, None]
    cov = np.empty((m, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = (np.bincount(inv, points[:, a] * points[:, b], m) / cnt
                                           - mean[:, a] * mean[:, b])
    ok = np.flatnonzero(cnt >= min_points)
    w, v = np.linalg.eigh(cov[ok])
    flat_enough = w[:, 0] <= planarity * np.maximum(w.sum(axis=1), 1e-12)
    kept = ok[flat_enough]
    label = np.full(m, -1, np.int64)
    label[kept] = np.arange(len(kept))
    return v[flat_enough, :, 0], cnt[kept].astype(np.float64), label[inv]


def _vote_axis(normals: np.ndarray, weights: np.ndarray, up: np.ndarray, max_tilt_deg: float
               ) -> tuple[np.ndarray, float]:
    """The up axis most normals within the cone agree with, and the weight share voting for it."""
    from scipy.ndimage import uniform_filter

    e1, e2 = tangent_basis(up)
    c = normals @ up
    a, b = (normals @ e1) / c, (normals @ e2) / c
    lim = np.tan(np.radians(max_tilt_deg))
    bw = np.tan(np.radians(1.0))
    edges = np.arange(-lim, lim + bw, bw)
    hist, _, _ = np.histogram2d(a, b, bins=[edges, edges], weights=weights)
    i, j = np.unravel_index(np.argmax(uniform_filter(hist, 3, mode="constant")), hist.shape)
    axis = up + (edges[i] + bw / 2) * e1 + (edges[j] + bw / 2) * e2
    axis /= np.linalg.norm(axis)
    for within_deg in (5.0, 3.0):
        sel = normals @ axis > np.cos(np.radians(within_deg))
        if not sel.any():
            break
        axis = (normals[sel] * weights[sel, None]).sum(axis=0)
        axis /= np.linalg.norm(axis)
    share = float(weights[normals @ axis > np.cos(np.radians(3.0))].sum() / weights.sum())
    return axis, share


def _fit_plane(points: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit normal on the ``up`` side, centroid) of the least-squares plane through points."""
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    n = vt[2]
    return (n if n @ up >= 0 else -n), centroid


def gravity_from_scan(points: np.ndarray, *, up_hint=(0.0, 0.0, 1.0), max_tilt_deg: float = 45.0,
                      cell_m: float = 0.5, planarity: float = 0.01, min_range_m: float = 0.5,
                      max_range_m: float = 30.0, min_floor_below_m: float = 0.3,
                      min_floor_points: int = 200) -> GravityEstimate:
    """Gravity direction from one scan's floor plane (see the module docstring).

    points: (N, 3) one scan, sensor or body frame, metres. up_hint: (3,) roughly up in that frame
    (a z-up sensor mounted upright: +z; see :func:`up_hint_from_gravity_map`); the true vertical
    must lie within ``max_tilt_deg`` of it. Points outside [min_range_m, max_range_m] are not used.
    Raises GlobalInitError when no planar surface lies within the cone.
    """
    up = np.asarray(up_hint, np.float64).reshape(3)
    up = up / np.linalg.norm(up)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    r = np.linalg.norm(pts, axis=1)
    pts = pts[(r >= min_range_m) & (r <= max_range_m)]
    if len(pts) < 50:
        raise GlobalInitError(f"scan has {len(pts)} points within {min_range_m}..{max_range_m} m: "
                              "expected at least 50 to find the floor")
    normals, weights, cell = _planar_cells(pts, cell_m, planarity)
    normals = normals * np.where(normals @ up < 0, -1.0, 1.0)[:, None]
    cone = normals @ up > np.cos(np.radians(max_tilt_deg))
    if not cone.any():
        raise GlobalInitError(f"no planar surface within {max_tilt_deg:.0f} deg of the up hint "
                              f"{up.round(3).tolist()}: cannot level the scan without an IMU")
    axis, share = _vote_axis(normals[cone], weights[cone], up, max_tilt_deg)

    # floor candidates: points of planar cells facing along the axis (not slices of walls);
    # points in no planar cell (label -1) read the appended False
    facing = np.append(normals @ axis > np.cos(np.radians(10.0)), False)[cell]
    height = pts @ axis
    below = facing & (height < -min_floor_below_m)
    if below.sum() >= min_floor_points:
        hb = height[below]
        hist, edges = np.histogram(hb, bins=np.arange(hb.min(), -min_floor_below_m + 0.1, 0.05))
        h0 = edges[int(np.argmax(hist))] + 0.025
        floor = pts[below & (np.abs(height - h0) < 0.10)]
        normal, centroid = _fit_plane(floor, axis) if len(floor) >= 3 else (axis, np.zeros(3))
        for band_m in (0.05, 0.03):  # refit to every point near the plane, clutter cells too
            floor = pts[np.abs((pts - centroid) @ normal) < band_m]
            if len(floor) < 3:
                break
            normal, centroid = _fit_plane(floor, axis)
        if len(floor) >= min_floor_points:
            off = np.degrees(np.arccos(np.clip(normal @ axis, -1.0, 1.0)))
            n = len(floor)
            conf = n / (n + 500.0) * float(np.exp(-(off / 2.0) ** 2))
            return GravityEstimate(-normal, conf, "floor", n, float(-(centroid @ normal)))
    log.debug("no floor below the sensor (%d points below %.1f m): the normal vote alone",
              int(below.sum()), min_floor_below_m)
    return GravityEstimate(-axis, 0.5 * share, "normals", int(cone.sum()))


def refine_gravity_by_ndt(refiner, points_body: np.ndarray, T_map_body: np.ndarray,
                          gravity_map) -> tuple[np.ndarray, GravityEstimate]:
    """Refine a candidate pose by NDT and read gravity in the body frame off the refined attitude.

    refiner: a :class:`~blockloc.global_init.refine.Refiner` (a registration target over the map,
    built once) or map points (M, 3), map frame, metres (an NDT target at 1 m is built). points_body: (N, 3) the scan, body frame.
    T_map_body: (4, 4) the candidate (its roll and pitch from :func:`gravity_from_scan`).
    gravity_map: (3,) gravity in the map frame. Returns (refined T_map_body (4, 4), the estimate
    with method 'ndt', confidence = NDT inlier ratio, 0 when NDT did not converge).
    """
    from blockloc.global_init.refine import Refiner

    if not isinstance(refiner, Refiner):
        from blockloc.registration.engines import make_engine

        refiner = Refiner(make_engine("ndt", resolution_m=1.0), np.asarray(refiner, np.float64))
    res = refiner.align(np.asarray(points_body, np.float64), np.asarray(T_map_body, np.float64))
    g = np.asarray(gravity_map, np.float64).reshape(3)
    direction = res.T_map_body[:3, :3].T @ (g / np.linalg.norm(g))
    conf = float(res.fitness) if res.converged else 0.0
    return res.T_map_body, GravityEstimate(direction, conf, "ndt",
                                           round(res.fitness * len(points_body)))
