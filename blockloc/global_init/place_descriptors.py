"""The place index's descriptors: parameters, polar bit tables, a scan's cells and descriptor,
matching scores and the static-band consistency test (module docstring of
:mod:`blockloc.global_init.place_index`, which holds the index itself, its file and its build).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from blockloc.errors import GlobalInitError

OBSTACLE_M = 0.3  # a scan point this high above the local ground hides what lies behind it
BAND_TOP_UNSEEN_M = 20.0
SCAN_COLUMN_POINTS = 3  # a scan column needs this many band points ("vertical" mode; a map 5: it is denser)
SCAN_VERTICAL_RANGE_M = 20.0  # ... within this range (a wall there gets band points >= 0.5 m apart)
STATIC_POINTS = 3000  # the static points kept per scan (verification's structure test)  # a scan with no points near the band's top: seen-through only beyond this


@dataclass(frozen=True)
class PlaceIndexParams:
    """resolution_m, band_m, mode, num_levels: the 2D projection (the global-init raster's, with
    its own band; equal values share its per-entry cache). num_sectors, min_range_m, max_range_m,
    ring_width_m: the polar bins (m). tolerance_m: how far from a place a scan may be taken and
    still match it (m). spacing_m: grid of places over the drivable area (m); keyframe_spacing_m:
    places along the mapping keyframes (m); max_offset_m: grid places within this of a keyframe (maps
    with keyframes); clearance_m: no structure this close to a grid place; min_bits: fewer occupied
    bins make a place too featureless to index. open_band_m: the height band of *open* places,
    where the static band holds fewer than ``min_bits`` bits (open stretches: fences, hedges, bushes,
    kerbside posts and what little stands higher; None: no open places). coverage, see_through: the
    matching model (module docstring); free_min_range_m: closer bins are never counted as seen through (a scan sees the
    band only beyond the range where its highest beams reach the band's top: that range, measured
    on each scan, raises this floor, see :func:`scan_cells`)."""

    resolution_m: float = 0.5
    band_m: tuple[float, float] = (2.0, 4.0)
    mode: str = "vertical"  # map structure with height (see projection.select_structure)
    num_levels: int = 6
    num_sectors: int = 64
    min_range_m: float = 3.0
    max_range_m: float = 63.0
    ring_width_m: float = 3.0
    tolerance_m: float = 1.5
    spacing_m: float = 3.0
    keyframe_spacing_m: float = 2.0
    max_offset_m: float = 20.0
    clearance_m: float = 0.75
    min_bits: int = 40
    open_band_m: tuple[float, float] | None = (0.5, 4.0)
    coverage: float = 0.85
    see_through: float = 0.05
    free_min_range_m: float = 7.0

    def __post_init__(self):
        if not (0 < self.min_range_m < self.max_range_m and self.ring_width_m > 0 and self.num_sectors >= 8
                and self.spacing_m > 0 and self.resolution_m > 0 and self.tolerance_m >= 0
                and 0 < self.see_through < self.coverage < 1
                and (self.open_band_m is None or 0 <= self.open_band_m[0] < self.open_band_m[1])):
            raise GlobalInitError(f"place index parameters {self}: expected 0 < min_range_m < max_range_m, "
                                  "positive ring width, spacing and resolution, num_sectors >= 8, "
                                  "tolerance >= 0, 0 < see_through < coverage < 1 and open_band_m None or (lo, hi), "
                                  "0 <= lo < hi")

    @property
    def num_rings(self) -> int:
        return int(math.ceil((self.max_range_m - self.min_range_m) / self.ring_width_m))

    @property
    def words(self) -> int:
        return (self.num_sectors + 63) // 64

    @property
    def projection_params(self):
        from blockloc.global_init.maps import ProjectionParams

        return ProjectionParams(self.resolution_m, self.num_levels, tuple(self.band_m), self.mode)

    @property
    def open_projection_params(self):
        """The 2D projection in ``open_band_m`` (the open places'), or None."""
        from blockloc.global_init.maps import ProjectionParams

        if self.open_band_m is None:
            return None
        return ProjectionParams(self.resolution_m, self.num_levels, tuple(self.open_band_m), self.mode)

    @classmethod
    def from_config(cls, gi) -> "PlaceIndexParams":
        """From ``GlobalInitConfig`` (its ``place_*`` fields)."""
        return cls(resolution_m=gi.resolution_m, num_levels=gi.pyramid_levels, band_m=tuple(gi.place_band_m),
                   spacing_m=gi.place_spacing_m, max_offset_m=gi.place_max_offset_m,
                   max_range_m=gi.place_max_range_m, tolerance_m=gi.place_tolerance_m)


# ----------------------------------------------------------------------------- descriptors


@dataclass(frozen=True)
class _Tables:
    s0: np.ndarray  # (2R, 2R) int16 first sector a cell covers
    n: np.ndarray  # (2R, 2R) int16 sectors it covers (0: outside the range annulus)
    ring: np.ndarray  # (2R, 2R) int16 ring
    range_m: np.ndarray  # (2R, 2R) float32 range of the cell centre
    radius: int


_TABLES: dict = {}


def _tables(p: PlaceIndexParams) -> _Tables:
    """Per cell offset (di, dj) from a lattice corner (index [di + R, dj + R]): the sectors the
    cell subtends, its ring and range."""
    key = (p.resolution_m, p.num_sectors, p.min_range_m, p.max_range_m, p.ring_width_m)
    if key in _TABLES:
        return _TABLES[key]
    res = p.resolution_m
    R = int(math.ceil(p.max_range_m / res)) + 1
    d = np.arange(-R, R)
    di, dj = np.meshgrid(d, d, indexing="ij")
    cx, cy = (di + 0.5) * res, (dj + 0.5) * res
    r = np.hypot(cx, cy)
    centre = np.arctan2(cy, cx)
    rel = []
    for a in (0, 1):
        for b in (0, 1):
            ang = np.arctan2((dj + b) * res, (di + a) * res) - centre
            rel.append((ang + np.pi) % (2 * np.pi) - np.pi)
    rel = np.array(rel)
    step = 2 * np.pi / p.num_sectors
    s_lo = np.floor((centre + rel.min(axis=0)) / step).astype(np.int64)
    s_hi = np.floor((centre + rel.max(axis=0)) / step).astype(np.int64)
    inside = (r >= p.min_range_m) & (r < p.min_range_m + p.num_rings * p.ring_width_m)
    n = np.where(inside, s_hi - s_lo + 1, 0).astype(np.int16)
    s0 = np.mod(s_lo, p.num_sectors).astype(np.int16)
    ring = np.clip(np.floor((r - p.min_range_m) / p.ring_width_m), 0, p.num_rings - 1).astype(np.int16)
    t = _Tables(s0, n, ring, r.astype(np.float32), R)
    _TABLES[key] = t
    return t


def descriptors_on_raster(occ: np.ndarray, corners: np.ndarray, params: PlaceIndexParams) -> np.ndarray:
    """Polar occupancy bits (P, rings, W) uint64 of places standing on lattice corners (P, 2)
    int64 (raster indices) of the occupancy raster ``occ`` (NX, NY) bool."""
    from blockloc.global_init import _kernels as K

    t = _tables(params)
    c = np.asarray(corners, np.int64).reshape(-1, 2)
    return K.polar_bits(np.ascontiguousarray(occ, dtype=np.bool_), c[:, 0].copy(), c[:, 1].copy(),
                        t.s0, t.n, t.ring, params.num_sectors, params.num_rings)


def unpack(bits: np.ndarray, num_sectors: int) -> np.ndarray:
    """(..., rings, W) uint64 -> (..., rings, num_sectors) bool (bit s of a ring: sector s)."""
    b = np.ascontiguousarray(bits).view(np.uint8)
    return np.unpackbits(b, axis=-1, bitorder="little")[..., :num_sectors].astype(bool)


def pack(occ: np.ndarray) -> np.ndarray:
    """(..., rings, S) bool -> (..., rings, W) uint64 (inverse of :func:`unpack`)."""
    S = occ.shape[-1]
    W = (S + 63) // 64
    pad = np.zeros(occ.shape[:-1] + (64 * W,), np.uint8)
    pad[..., :S] = occ
    return np.ascontiguousarray(np.packbits(pad, axis=-1, bitorder="little")).view(np.uint64)


@dataclass
class ScanCells:
    """A levelled scan's cells (M, 2) int64, ``floor(xy / resolution)`` of the levelled body frame:
    ``band`` in the index's height band, ``obstacles`` of every point OBSTACLE_M or more above the
    ground; R_tilt (3, 3) its levelling (p_lvl = R_tilt @ p_body); free_from_m: the range from which
    the scan sees the whole band (closer, structure high in the band is above its beams);
    static_body: up to STATIC_POINTS of the scan's points (K, 3), body frame, at or above the band's
    bottom (above people, cars and fences: what a map of another day still holds), fixed-seed
    sample; open_band: the cells in ``open_band_m`` (matched against the open places; None when the
    parameters have no open band).
    """

    band: np.ndarray
    obstacles: np.ndarray
    R_tilt: np.ndarray
    free_from_m: float = 0.0
    static_body: np.ndarray | None = None  # (K, 3) body-frame points at or above the band's bottom
    open_band: np.ndarray | None = None  # (M', 2) cells in open_band_m


@dataclass
class ScanDescriptor:
    """A scan's bits: occupied (rings, W) and seen-through (rings, W) uint64; per-ring counts."""

    occupied: np.ndarray
    free: np.ndarray

    def counts(self, num_sectors: int) -> tuple[np.ndarray, np.ndarray]:
        return (unpack(self.occupied, num_sectors).sum(axis=-1).astype(np.float32),
                unpack(self.free, num_sectors).sum(axis=-1).astype(np.float32))


def _inside(cells: np.ndarray, R: int) -> np.ndarray:
    c = np.asarray(cells, np.int64).reshape(-1, 2)
    return c[np.all((c >= -R) & (c < R), axis=1)]


def scan_cells(points_body: np.ndarray, gravity_body: np.ndarray, params: PlaceIndexParams) -> ScanCells:
    """A scan's cells (levelled body frame, ``floor(xy / resolution)``): in the band, and of every
    obstacle (OBSTACLE_M or more above the local ground); and its levelling R_tilt.

    points_body: (N, 3) body frame, metres; gravity_body: (3,) gravity in the body frame.
    """
    from blockloc.global_init.projection import (R_level_from_gravity, ground_grid, lookup_ground, tall_columns,
                                                 unique_cells)

    pts = np.asarray(points_body, float).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    R_tilt = R_level_from_gravity(gravity_body)
    lvl = pts @ np.ascontiguousarray(R_tilt.T)
    rng = np.hypot(lvl[:, 0], lvl[:, 1])
    lvl = lvl[(rng > 0.5) & (rng <= params.max_range_m + 5.0)]
    none = np.zeros((0, 2), np.int64)
    if len(lvl) == 0:
        return ScanCells(none, none, R_tilt, BAND_TOP_UNSEEN_M, np.zeros((0, 3)),
                         None if params.open_band_m is None else none)
    g_origin, g_grid = ground_grid(lvl)
    h = lvl[:, 2] - lookup_ground(g_origin, g_grid, lvl[:, :2])
    lo, hi = params.band_m

    def cells(keep):
        return unique_cells(np.floor(lvl[keep, :2] / params.resolution_m).astype(np.int64))

    # The nearest points at the band's top: closer, the beams pass below it (vertical field of view).
    top = np.hypot(lvl[:, 0], lvl[:, 1])[np.abs(h - hi) <= 0.5]
    top = top[top >= params.min_range_m]
    free_from = float(np.percentile(top, 2)) if len(top) >= 20 else BAND_TOP_UNSEEN_M

    def in_band(b_lo, b_hi):
        band = (h >= b_lo) & (h <= b_hi)
        if params.mode == "vertical":
            # As the map's raster (projection.select_structure): drop layers (the ceiling of a
            # passage) and stray returns, where walls are hit by several beams; farther away one
            # beam may be all a wall gets.
            idx = np.flatnonzero(band)
            near = np.hypot(lvl[idx, 0], lvl[idx, 1]) < SCAN_VERTICAL_RANGE_M
            band[idx[near & ~tall_columns(lvl[idx, :2], h[idx], min_points=SCAN_COLUMN_POINTS)]] = False
        return band

    static = lvl[h >= lo]
    if len(static) > STATIC_POINTS:
        static = static[np.sort(np.random.default_rng(0).choice(len(static), STATIC_POINTS, replace=False))]
    open_cells = None if params.open_band_m is None else cells(in_band(*params.open_band_m))
    return ScanCells(cells(in_band(lo, hi)), cells(h >= OBSTACLE_M), R_tilt,
                     max(params.free_min_range_m, free_from), static @ R_tilt, open_cells)


def consistency_at(source, xy_L: np.ndarray, theta: float, cells: ScanCells, params: PlaceIndexParams,
                   min_bits: int = 20, coverage_source=None, known=None) -> tuple[float, float]:
    """How well the map's static band around a pose agrees with a scan: (coverage, see_through).

    The pose: the body at ``xy_L`` (2,) of the levelled frame, its levelled scan turned by
    ``theta`` rad. coverage: share of the scan's occupied bins the map's structure (grown by the
    tolerance) covers, NaN below ``min_bits`` bins. see_through: of the sectors where the map's
    nearest structure lies beyond ``free_min_range_m`` (what the scan should see there), the share
    in which the scan saw through it (its free bins reach past it), NaN below ``min_bits / 4``
    such sectors. A share, not a count of bins: a wall across a quarter of the view is a quarter.
    source: a global-init map source in ``params``' band (``base_raster``); coverage_source: one
    for the coverage when not ``source`` (the plain band: a scan's column that the "vertical"
    projection would drop on the map's lattice is still covered). known: a function of levelled
    points (N, 2) -> (N,) bool, where the map holds data; the coverage then counts only the bins
    that lie wholly there (the scan's structure beyond the map's edge is no evidence either way).
    """
    from scipy.ndimage import binary_dilation

    t = _tables(params)
    res = params.resolution_m
    S = params.num_sectors
    corner = np.round(np.asarray(xy_L, float) / res).astype(np.int64)
    pad = int(math.ceil(params.tolerance_m / res)) + 1
    origin, base = source.base_raster(corner - t.radius - pad, corner + t.radius + pad)
    occ = base == 255
    at = (corner - origin)[None]
    raw = unpack(descriptors_on_raster(occ, at, params)[0], S)
    if coverage_source is not None:
        origin, base = coverage_source.base_raster(corner - t.radius - pad, corner + t.radius + pad)
        occ = base == 255
        at = (corner - origin)[None]
    grown = unpack(descriptors_on_raster(binary_dilation(occ, _disk(params.tolerance_m / res)), at, params)[0], S)
    sd = scan_descriptor(cells.band, params, cells.obstacles, cells.free_from_m)
    shift = int(round(theta / (2 * math.pi / S))) % S
    occ_s = np.roll(unpack(sd.occupied, S), shift, axis=-1)
    free_s = np.roll(unpack(sd.free, S), shift, axis=-1)
    if known is not None:
        # Bins touched by a cell outside the map's footprint are not judged.
        ii, jj = np.meshgrid(np.arange(occ.shape[0]), np.arange(occ.shape[1]), indexing="ij")
        centres = (np.stack([ii.ravel(), jj.ravel()], axis=1) + origin + 0.5) * res
        unknown = ~np.asarray(known(centres), bool).reshape(occ.shape)
        occ_s &= ~unpack(descriptors_on_raster(unknown, at, params)[0], S)
    n_occ = int(occ_s.sum())
    coverage = float((occ_s & grown).sum()) / n_occ if n_occ >= min_bits else float("nan")
    r0 = int(math.ceil((max(params.free_min_range_m, cells.free_from_m) - params.min_range_m)
                       / params.ring_width_m))
    has = raw.any(axis=0)
    first = np.where(has, raw.argmax(axis=0), 0)
    judged = has & (first >= r0)
    through = judged & free_s[first, np.arange(S)]
    n = int(judged.sum())
    see = float(through.sum()) / n if n >= max(1, min_bits // 4) else float("nan")
    return coverage, see


def scan_descriptor(cells: np.ndarray, params: PlaceIndexParams,
                    obstacles: np.ndarray | None = None, free_from_m: float = 0.0) -> ScanDescriptor:
    """Bits of a levelled scan from its occupied band cells (M, 2) int64, ``floor(xy / resolution)``
    of the levelled body frame (the body stands on the lattice corner 0, 0, as places do).

    Free bits: in each sector, the rings lying wholly between ``free_min_range_m`` (or
    ``free_from_m`` when farther, see :class:`ScanCells`) and the first obstacle minus ``tolerance_m``, where the first obstacle is the nearest one over the sectors
    within ``tolerance_m`` of the ring (a scan taken that far from
    a place sees the place's walls shifted by as much). ``obstacles``: cells (K, 2) of every point
    above the ground, any height (default: the band cells): a wall close by, hit below the band,
    hides what is behind it although the band saw nothing there.
    """
    t = _tables(params)
    R = t.radius
    S = params.num_sectors
    c = _inside(cells, R)
    occ = np.zeros((2 * R, 2 * R), dtype=np.bool_)
    occ[c[:, 0] + R, c[:, 1] + R] = True
    occupied = descriptors_on_raster(occ, np.array([[R, R]]), params)[0]
    # First obstacle per sector (every sector an obstacle cell covers).
    o = c if obstacles is None else np.concatenate([c, _inside(obstacles, R)])
    first = np.full(S, np.inf)
    a, b = o[:, 0] + R, o[:, 1] + R
    n = t.n[a, b]
    a, b, n = a[n > 0], b[n > 0], n[n > 0]
    for k in range(int(n.max()) if len(n) else 0):
        m = n > k
        np.minimum.at(first, (t.s0[a[m], b[m]] + k) % S, t.range_m[a[m], b[m]])
    step = 2 * math.pi / S
    free = np.zeros((params.num_rings, S), bool)
    for r in range(params.num_rings):
        inner = params.min_range_m + r * params.ring_width_m
        outer = inner + params.ring_width_m
        if inner < max(params.free_min_range_m, free_from_m):
            continue
        half = int(math.ceil(params.tolerance_m / max(inner, 1e-6) / step))
        near = first.copy()
        for k in range(1, half + 1):
            near = np.minimum(near, np.minimum(np.roll(first, k), np.roll(first, -k)))
        free[r] = outer <= near - params.tolerance_m
    return ScanDescriptor(occupied, pack(free))


def shifted(bits: np.ndarray, num_sectors: int) -> np.ndarray:
    """(S, rings, W): bits turned by every shift s (bit m of shift s = sector m - s)."""
    occ = unpack(bits, num_sectors)
    return np.stack([pack(np.roll(occ, s, axis=-1)) for s in range(num_sectors)])


def match_scores(scan: ScanDescriptor, index, rows: np.ndarray | None = None) -> np.ndarray:
    """(P, S) log-likelihood ratio per observed scan bit of "the scan was taken at place p, turned by
    shift s" against "taken anywhere" (see the module docstring); ``rows``: of these places only
    ((len(rows), S))."""
    from blockloc.global_init import _kernels as K

    p = index.params
    S = p.num_sectors
    n = len(index) if rows is None else len(rows)
    occ_ring, free_ring = scan.counts(S)
    total = float(occ_ring.sum() + free_ring.sum())
    if total == 0 or n == 0:
        return np.zeros((n, S), np.float32)
    occ_hit, occ_miss, free_hit, free_miss = index.llr_weights()
    grown, bits = index.grown, index.bits
    if rows is not None:
        occ_hit, occ_miss, free_hit, free_miss, grown, bits = (a[rows] for a in (occ_hit, occ_miss, free_hit,
                                                                                 free_miss, grown, bits))
    hits = K.polar_llr(shifted(scan.occupied, S), grown, occ_hit, shifted(scan.free, S), bits, free_hit)
    return (hits + (occ_miss @ occ_ring + free_miss @ free_ring)[:, None]) / total


def llr_weights(q: float, density: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(hit weight, miss weight), float32 like ``density`` (P, rings): log(q / rho) - miss and
    miss = log((1 - q) / (1 - rho)) of each ring's share of set bits rho (clipped to [0.01, 0.99]),
    for a bit the model sets with probability ``q`` (:func:`match_scores`)."""
    rho = np.clip(density, 0.01, 0.99)
    miss = np.log((1 - q) / (1 - rho))
    return (np.log(q / rho) - miss).astype(np.float32), miss.astype(np.float32)


def best_shift(score: np.ndarray, allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(best score (N,), fractional shift (N,) in sectors) of each row of ``score`` (N, S) over all
    S shifts, refined by a parabola through the neighbours; ``allowed`` (S,) bool restricts them."""
    L = np.where(allowed[None, :], score, -np.inf) if allowed is not None else score
    N, S = L.shape
    k = np.argmax(L, axis=1)
    rows = np.arange(N)
    l0 = score[rows, (k - 1) % S]
    l1 = score[rows, k]
    l2 = score[rows, (k + 1) % S]
    den = l0 - 2 * l1 + l2
    off = np.where(den < -1e-9, 0.5 * (l0 - l2) / np.where(den < -1e-9, den, -1.0), 0.0)
    return l1, k + np.clip(off, -0.5, 0.5)


def _disk(radius_cells: float) -> np.ndarray:
    r = int(math.floor(radius_cells))
    d = np.arange(-r, r + 1)
    return (d[:, None] ** 2 + d[None, :] ** 2) <= radius_cells ** 2 + 1e-9
