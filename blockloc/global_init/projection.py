"""2D projections for global initialization: levelling, local ground, height band, rasters.

Frames. The search runs in a *levelled* frame ``L``: the map frame rotated so that gravity points
along -z (z up), with the same origin. NCLT and simulated maps are z down (gravity (0, 0, +9.81)), so
there ``L`` = (x, -y, -z) of the map; ROS maps are z up and ``L`` = map. The scan is levelled by the
body's roll and pitch (from gravity measured by the accelerometer): ``p_lvl = R_tilt @ p_body`` has
z up and its heading is the body's, so ``R_L_body = Rz(yaw) @ R_tilt`` and only (x, y, yaw) remain.

What is projected (choice recorded in docs/bench/global_init.md): points in a *height band above the
local ground* (default 0.3 .. 3.0 m), not all points. Ground returns cover almost every cell near the
sensor in both map and scan, so an occupancy image of all points rewards any placement on open
ground; the band keeps walls, trunks, poles, cars and fences, which fix x, y and yaw. The local
ground is the minimum height in 1 m cells, eroded over +-1 cell so that a cell holding only a wall
still finds the ground next to it; this follows slopes and ramps, which an absolute z band does not.
Where that local minimum stands more than 1 m above the minimum over +-5 cells, it is a canopy or a
roof, not ground, and the wider minimum is used (else tree crowns fill whole areas of the raster).

The map raster is a smoothed occupancy: each occupied cell spreads exp(-d^2 / (2 sigma^2)) to its
neighbours (sigma = one cell), stored as uint8 0..255. The spread is a max over occupied cells, so
the raster of a union of map pieces is the element-wise max of their rasters (pieces compose).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

VERTICAL_CELL_M = 0.5  # columns of the "vertical" projection mode
VERTICAL_EXTENT_M = 0.5  # band points of a column spanning less: a layer (a ceiling) or stray returns
VERTICAL_MIN_POINTS = 5  # fewer in a column: stray returns (half the band cells of a simulated map held <= 2)

GROUND_CELL_M = 1.0
GROUND_ERODE_CELLS = 1
GROUND_WIDE_CELLS = 5
GROUND_MAX_STEP_M = 1.0
SMOOTH_RADIUS_CELLS = 2


# ----------------------------------------------------------------------------- levelling


def levelled_xy(points: np.ndarray, R_L_map: np.ndarray) -> np.ndarray:
    """(N, 2) float64: the levelled-frame xy (m) of points (N, 3), map frame (``R_L_map`` (3, 3)).

    einsum, not matmul: an (N, 3) x (3, 2) product is memory-bound, and OpenBLAS's threads spent
    ~20x the CPU time of this loop on a million points on a loaded machine."""
    pts = np.asarray(points).reshape(-1, 3)
    return np.einsum("nj,ij->ni", pts, np.asarray(R_L_map, float).reshape(3, 3)[:2], dtype=np.float64)


def rotation_aligning(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) smallest rotation R with R @ a/|a| = b/|b| (a, b: (3,) non-zero)."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-9:  # opposite: half turn about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def R_level_from_gravity(gravity: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking a frame in which gravity is ``gravity`` (3,) to one with gravity -z."""
    g = np.asarray(gravity, float).reshape(3)
    if not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-6:
        from blockloc.errors import GlobalInitError

        raise GlobalInitError(f"gravity vector {g.tolist()}: expected a finite non-zero (3,) vector")
    down = np.array([0.0, 0.0, -1.0])
    if g[2] > 0:
        # z-down frames (NCLT): flip about x first so the result stays near (x, -y, -z) and keeps
        # the heading, instead of a near half-turn about an axis set by the small tilt.
        F = np.diag([1.0, -1.0, -1.0])
        return rotation_aligning(F @ g, down) @ F
    return rotation_aligning(g, down)


def gravity_body_from_imu(acc_imu: np.ndarray, T_body_imu: np.ndarray) -> np.ndarray:
    """Gravity direction (3,) in the body frame from accelerometer samples (M, 3), imu frame, m/s^2.

    At rest the accelerometer reads minus gravity; the mean over ~0.5 s averages vibration and slow
    motion out. Returns the mean gravity vector in the body frame (m/s^2).
    """
    acc = np.asarray(acc_imu, float).reshape(-1, 3)
    if len(acc) == 0:
        from blockloc.errors import GlobalInitError

        raise GlobalInitError("no accelerometer samples near the frame: cannot level the scan")
    return -(np.asarray(T_body_imu, float)[:3, :3] @ acc.mean(axis=0))


def heading_offset(R_tilt: np.ndarray) -> float:
    """Yaw (rad) of the body x axis after levelling by ``R_tilt`` (3, 3); 0 when x is horizontal."""
    ex = R_tilt[:, 0]
    return float(np.arctan2(ex[1], ex[0]))


# ----------------------------------------------------------------------------- ground and band


def ground_grid(points_lvl: np.ndarray, cell_m: float = GROUND_CELL_M,
                erode_cells: int = GROUND_ERODE_CELLS, wide_cells: int = GROUND_WIDE_CELLS,
                max_step_m: float = GROUND_MAX_STEP_M) -> tuple[np.ndarray, np.ndarray]:
    """Local ground height on a coarse grid.

    points_lvl: (N, 3) levelled frame (z up), metres.
    Returns (origin (2,) int64 coarse cell index of grid[0, 0], grid (GX, GY) float32 metres; NaN
    where no point fell within ``wide_cells``). The ground of a cell is the minimum z over the cell
    and its neighbours within ``erode_cells`` (follows slopes and ramps), unless that is more than
    ``max_step_m`` above the minimum within ``wide_cells``: then the cell's lowest points are no
    ground (tree canopies and roofs with no ground seen below) and the wide minimum is used.
    """
    from scipy.ndimage import minimum_filter

    cells = np.floor(points_lvl[:, :2] / cell_m).astype(np.int64)
    origin = cells.min(axis=0) - wide_cells
    shape = tuple(cells.max(axis=0) - origin + 1 + wide_cells)
    raw = np.full(shape, np.inf, dtype=np.float32)
    ij = cells - origin
    np.minimum.at(raw, (ij[:, 0], ij[:, 1]), points_lvl[:, 2].astype(np.float32))
    near = minimum_filter(raw, size=2 * erode_cells + 1, mode="constant", cval=np.inf)
    wide = minimum_filter(raw, size=2 * wide_cells + 1, mode="constant", cval=np.inf)
    with np.errstate(invalid="ignore"):
        grid = np.where(near - wide > max_step_m, wide, near)
    grid[~np.isfinite(grid)] = np.nan
    return origin, grid


def lookup_ground(origin: np.ndarray, grid: np.ndarray, xy: np.ndarray,
                  cell_m: float = GROUND_CELL_M) -> np.ndarray:
    """Ground height (M,) at levelled positions xy (M, 2); NaN outside the grid or unknown."""
    ij = np.floor(np.asarray(xy, float).reshape(-1, 2) / cell_m).astype(np.int64) - origin
    out = np.full(len(ij), np.nan, dtype=np.float64)
    ok = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < grid.shape[0]) & (ij[:, 1] < grid.shape[1])
    out[ok] = grid[ij[ok, 0], ij[ok, 1]]
    return out


def select_structure(points_lvl: np.ndarray, band_m: tuple[float, float],
                     mode: str = "band") -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Points that enter the 2D projection, and the ground grid used.

    mode "band": points whose height above the local ground is within ``band_m`` (lo, hi) metres;
    mode "vertical": of those, the ones in VERTICAL_CELL_M columns whose band points (at least
    VERTICAL_MIN_POINTS) span at least VERTICAL_EXTENT_M in height (walls, trunks, poles, crowns), not thin horizontal layers
    (ceilings of passages and indoor corridors, which would fill every cell under them) nor the
    stray single returns a map accumulates (sensor noise: a third of a simulated map's band cells
    held one point);
    mode "all": every point (plain 2D occupancy; kept for the measurement that justifies "band").
    Returns ((K, 3) selected points, (ground origin, ground grid)).
    """
    ground = ground_grid(points_lvl)
    if mode == "all":
        return points_lvl, ground
    if mode not in ("band", "vertical"):
        from blockloc.errors import GlobalInitError

        raise GlobalInitError(f"projection mode {mode!r}: expected 'band', 'vertical' or 'all'")
    g = lookup_ground(ground[0], ground[1], points_lvl[:, :2])
    h = points_lvl[:, 2] - g
    keep = (h >= band_m[0]) & (h <= band_m[1])
    if mode == "vertical" and keep.any():
        idx = np.flatnonzero(keep)
        keep[idx[~tall_columns(points_lvl[idx, :2], h[idx])]] = False
    return points_lvl[keep], ground


def unique_cells(cells: np.ndarray, return_inverse: bool = False):
    """``np.unique(cells, axis=0)`` of integer cells (N, 2) (sorted by x, then y), and with
    ``return_inverse`` the row of each cell in it (N,): the same arrays, by one sort of int64 codes.
    numpy's row-wise unique sorts a structured view, ~10x slower (18 vs 2 ms on 30k scan cells,
    several times a no-hint search)."""
    c = np.asarray(cells, np.int64).reshape(-1, 2)
    lo = c.min(axis=0) if len(c) else np.zeros(2, np.int64)
    span = (c.max(axis=0) - lo + 1) if len(c) else np.ones(2, np.int64)
    if len(c) == 0 or float(span[0]) * float(span[1]) >= 2.0**62:
        if not return_inverse:
            return np.unique(c, axis=0)
        u, inverse = np.unique(c, axis=0, return_inverse=True)
        return u, inverse.reshape(-1)
    code = (c[:, 0] - lo[0]) * span[1] + (c[:, 1] - lo[1])  # x-major: sorts as the rows do
    order = np.argsort(code, kind="stable")
    s = code[order]
    first = np.r_[True, s[1:] != s[:-1]]
    u = s[first]
    out = np.stack([u // span[1] + lo[0], u % span[1] + lo[1]], axis=1)
    if not return_inverse:
        return out
    inverse = np.empty(len(c), np.int64)
    inverse[order] = np.cumsum(first) - 1
    return out, inverse


def tall_columns(xy: np.ndarray, h: np.ndarray, min_points: int = VERTICAL_MIN_POINTS) -> np.ndarray:
    """(N,) bool: the points (xy (N, 2), levelled frame, metres; h (N,) height, m) whose
    VERTICAL_CELL_M column holds at least ``min_points`` points spanning at least
    VERTICAL_EXTENT_M in height."""
    if len(h) == 0:
        return np.zeros(0, bool)
    _, col = unique_cells(np.floor(np.asarray(xy) / VERTICAL_CELL_M).astype(np.int64), return_inverse=True)
    lo = np.full(col.max() + 1, np.inf)
    hi = np.full(col.max() + 1, -np.inf)
    np.minimum.at(lo, col, h)
    np.maximum.at(hi, col, h)
    n = np.bincount(col)
    return ((hi - lo) >= VERTICAL_EXTENT_M)[col] & (n >= min_points)[col]


# ----------------------------------------------------------------------------- map raster


@dataclass
class Raster:
    """Smoothed occupancy of map structure on a global cell lattice.

    origin: (2,) int64 cell index (floor(x / resolution), floor(y / resolution)) of ``grid[0, 0]``.
    grid: (NX, NY) uint8, 255 at occupied cells, spread to neighbours.
    resolution: cell side, metres. Levelled frame L.
    ground_origin, ground: coarse local-ground grid (see :func:`ground_grid`), metres.
    """

    origin: np.ndarray
    grid: np.ndarray
    resolution: float
    ground_origin: np.ndarray
    ground: np.ndarray


def smoothing_kernel(radius_cells: int = SMOOTH_RADIUS_CELLS) -> np.ndarray:
    """(2r+1, 2r+1) uint8 kernel exp(-d^2/2) * 255 with d in cells."""
    r = np.arange(-radius_cells, radius_cells + 1)
    d2 = r[:, None] ** 2 + r[None, :] ** 2
    return np.round(255.0 * np.exp(-0.5 * d2)).astype(np.uint8)


def rasterize_map(points_lvl: np.ndarray, resolution: float, band_m: tuple[float, float],
                  mode: str = "band", pad_cells: int = 0) -> Raster:
    """Raster of map points (N, 3), levelled frame, metres.

    ``pad_cells`` extra zero cells on every side (beyond the smoothing spread).
    """
    from blockloc.errors import GlobalInitError

    pts = np.asarray(points_lvl, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        raise GlobalInitError("map region holds no points: nothing to localize against")
    structure, (g_origin, g_grid) = select_structure(pts, band_m, mode)
    if len(structure) == 0:
        # a sliver of a map (an edge tile with a handful of ground points) is expected to have none:
        # only a region of substance without any is worth a warning (a wrong gravity, a wrong band)
        (log.warning if len(pts) >= 1000 else log.debug)(
            "no map points in the height band %s among %d; raster is empty", band_m, len(pts))
        structure = pts[:1]
    cells = np.floor(structure[:, :2] / resolution).astype(np.int64)
    rad = SMOOTH_RADIUS_CELLS
    margin = rad + pad_cells
    # Extent from all points (not only structure) so pieces of the same map cover the same area.
    all_cells = np.floor(pts[:, :2] / resolution).astype(np.int64)
    origin = all_cells.min(axis=0) - margin
    shape = tuple(all_cells.max(axis=0) - origin + 1 + margin)
    occ = np.zeros(shape, dtype=bool)
    ij = cells - origin
    occ[ij[:, 0], ij[:, 1]] = True
    grid = spread(occ, smoothing_kernel(rad))
    return Raster(origin, grid, resolution, g_origin, g_grid)


def spread(occ: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Max over occupied cells of the kernel centred there: (NX, NY) bool -> (NX, NY) uint8."""
    out = np.zeros(occ.shape, dtype=np.uint8)
    r = kernel.shape[0] // 2
    nx, ny = occ.shape
    for dx in range(-r, r + 1):
        for dy in range(-r, r + 1):
            val = kernel[dx + r, dy + r]
            if val == 0:
                continue
            src = occ[max(0, -dx):nx - max(0, dx), max(0, -dy):ny - max(0, dy)]
            dst = out[max(0, dx):nx - max(0, -dx), max(0, dy):ny - max(0, -dy)]
            np.maximum(dst, np.where(src, val, 0).astype(np.uint8), out=dst)
    return out


# ----------------------------------------------------------------------------- scan projection


@dataclass
class ScanProjection:
    """A levelled scan reduced to the 2D cells it occupies.

    xy: (N, 2) float64 cell centres, levelled body frame (origin at the body), metres.
    max_range: largest |xy|, metres (sets the angular step).
    ground_below: height of the ground below the body in the levelled body frame (negative: the
    ground is below), metres; NaN when not seen.
    R_tilt: (3, 3) levelling rotation of the body (p_lvl = R_tilt @ p_body).
    structure_body: (K, 3) the 3D points in the height band, body frame (at most 3000, fixed-seed
    subsample): verification checks that these, not the ground, fit the map.
    """

    xy: np.ndarray
    max_range: float
    ground_below: float
    R_tilt: np.ndarray
    structure_body: np.ndarray | None = None


def project_scan(points_body: np.ndarray, gravity_body: np.ndarray, resolution: float,
                 band_m: tuple[float, float], mode: str = "band", max_range_m: float = 60.0,
                 max_cells: int = 1500, min_cells: int = 50, seed: int = 0,
                 min_range_m: float = 3.0) -> ScanProjection:
    """Level, filter and reduce a scan to unique occupied cells.

    points_body: (N, 3) body frame, metres. gravity_body: (3,) gravity direction in the body frame.
    Keeps cells between ``min_range_m`` (the robot itself and the innermost ground rings, whose
    height is the most sensitive to a tilt error) and ``max_range_m`` horizontally; at most ``max_cells`` (a fixed-seed subsample).
    Raises GlobalInitError when fewer than ``min_cells`` cells remain.
    """
    from blockloc.errors import GlobalInitError

    pts = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    R_tilt = R_level_from_gravity(gravity_body)
    lvl = pts @ np.ascontiguousarray(R_tilt.T)  # matmul with a transposed view is ~100x slower
    rng_xy = np.hypot(lvl[:, 0], lvl[:, 1])
    lvl = lvl[(rng_xy > 0.5) & (rng_xy <= max_range_m)]  # ground estimate uses the near points too
    if len(lvl) < min_cells:
        raise GlobalInitError(f"scan has {len(lvl)} usable points within {max_range_m} m: "
                              f"expected at least {min_cells}")
    structure, (g_origin, g_grid) = select_structure(lvl, band_m, mode)
    near = lookup_ground(g_origin, g_grid, np.array([[0.0, 0.0]]))[0]
    structure = structure[np.hypot(structure[:, 0], structure[:, 1]) >= min_range_m]
    cells = unique_cells(np.floor(structure[:, :2] / resolution).astype(np.int64))
    if len(cells) < min_cells:
        raise GlobalInitError(f"scan has {len(cells)} occupied cells in the height band {band_m} m: "
                              f"expected at least {min_cells} (too few points or open ground)")
    if len(cells) > max_cells:
        rng = np.random.default_rng(seed + 1)
        cells = cells[np.sort(rng.choice(len(cells), max_cells, replace=False))]
    xy = (cells + 0.5) * resolution
    rng = np.random.default_rng(seed)
    if len(structure) > 3000:
        structure = structure[np.sort(rng.choice(len(structure), 3000, replace=False))]
    return ScanProjection(xy, float(np.hypot(xy[:, 0], xy[:, 1]).max()), float(near), R_tilt,
                          structure @ R_tilt)
