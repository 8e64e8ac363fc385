"""Grid-puzzle tiles (Byeon et al.): square, non-overlapping tiles named by their centre.

The plane is cut into cells of side s aligned to the map origin: cell (ix, iy) covers
``[ix*s, (ix+1)*s) x [iy*s, (iy+1)*s)`` (map frame, metres, all heights). Its tile file is
``{cx}_{cy}.pcd`` with the centre ``((ix+0.5)*s, (iy+0.5)*s)`` printed with a fixed number of
decimals (enough to be exact for s; at least one), e.g. ``-3.0_5.0.pcd`` for s = 2. Every point
falls in exactly one tile and the union of the tiles is the input (Algorithm 1).

The tile window of Algorithm 2 lives here too: (2n+1)^2 cells around the robot's cell, widened by
k cells toward the motion direction according to one of 8 heading sectors (:func:`grid_window`).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Callable

import numpy as np

from blockloc.errors import MapError

log = logging.getLogger(__name__)

# Heading sectors of 45 degrees centred on the axes and diagonals, counter-clockwise from +x
# (map frame): the direction (dx, dy) in cells toward which the window is widened.
SECTOR_DIRECTIONS = ((1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1))
SECTOR_NAMES = ("E", "NE", "N", "NW", "W", "SW", "S", "SE")


def check_tile_size(tile_size_m: float) -> float:
    try:
        s = float(tile_size_m)
    except (TypeError, ValueError):
        s = float("nan")
    if not (s > 0 and math.isfinite(s)):
        raise MapError(f"tile size {tile_size_m!r} m: expected a positive number of metres")
    return s


def name_decimals(tile_size_m: float) -> int:
    """Decimals that print every tile centre (odd multiples of s/2) exactly; at least 1."""
    half = check_tile_size(tile_size_m) / 2.0
    for d in range(1, 10):
        if abs(round(half, d) - half) < 1e-9 * max(1.0, half):
            return d
    return 9


def cell_of(xy: np.ndarray, tile_size_m: float) -> np.ndarray:
    """Cell indices (N, 2) int64 of points ``xy`` (N, >=2), exact at cell borders:
    ``ix*s <= x < (ix+1)*s`` holds in float64 for every returned index."""
    s = check_tile_size(tile_size_m)
    xy = np.asarray(xy, np.float64)[:, :2]
    idx = np.floor(xy / s).astype(np.int64)
    # x / s rounds; fix the rare index that disagrees with the float64 cell bounds
    idx -= (xy < idx * s)
    idx += (xy >= (idx + 1) * s)
    return idx


def tile_name(ix: int, iy: int, tile_size_m: float, decimals: int | None = None) -> str:
    """Tile id ``{cx}_{cy}`` of cell (ix, iy): its centre in metres with fixed decimals."""
    s = check_tile_size(tile_size_m)
    d = name_decimals(s) if decimals is None else decimals
    return f"{(ix + 0.5) * s:.{d}f}_{(iy + 0.5) * s:.{d}f}"


def parse_tile_name(name: str, tile_size_m: float) -> tuple[int, int]:
    """Cell (ix, iy) of a tile id or file name ``{cx}_{cy}[.pcd]``; MapError when malformed."""
    s = check_tile_size(tile_size_m)
    stem = name[:-4] if name.endswith(".pcd") else name
    try:
        cx_s, cy_s = stem.split("_")
        cx, cy = float(cx_s), float(cy_s)
    except ValueError:
        raise MapError(f"tile name {name!r}: expected '{{cx}}_{{cy}}' centre coordinates") from None
    ix, iy = round(cx / s - 0.5), round(cy / s - 0.5)
    if abs((ix + 0.5) * s - cx) > 1e-6 * s or abs((iy + 0.5) * s - cy) > 1e-6 * s:
        raise MapError(f"tile name {name!r}: not the centre of a {s} m cell")
    return int(ix), int(iy)


def tile_bounds(name: str, tile_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """xy_min (2,), xy_max (2,) of the tile ``name``: the half-open cell [min, max)."""
    s = check_tile_size(tile_size_m)
    ix, iy = parse_tile_name(name, s)
    return np.array([ix * s, iy * s]), np.array([(ix + 1) * s, (iy + 1) * s])


def split_into_tiles(points: np.ndarray, tile_size_m: float) -> dict[tuple[int, int], np.ndarray]:
    """Cell -> indices into ``points`` (N, >=2), cells in sorted order, indices ascending."""
    if len(points) == 0:
        return {}
    cells = cell_of(points, tile_size_m)
    order = np.lexsort((cells[:, 1], cells[:, 0]))
    sorted_cells = cells[order]
    breaks = np.flatnonzero(np.any(np.diff(sorted_cells, axis=0) != 0, axis=1)) + 1
    groups = np.split(order, breaks)
    return {(int(cells[g[0], 0]), int(cells[g[0], 1])): np.sort(g) for g in groups}


def tile_global_map(points: np.ndarray, intensity: np.ndarray | None, tile_size_m: float,
                    out: str | Path, *, frame: str = "map", params: dict | None = None,
                    overwrite: bool = False, progress: Callable[[int, int], None] | None = None):
    """Algorithm 1: cut a global map (N, 3) into tiles written atomically as a grid store at ``out``.

    No point is dropped or duplicated: the tiles' payloads concatenate to the input.
    progress: called ``(tiles written, tiles)`` after each tile.
    Returns the opened :class:`~blockloc.maps.store.MapStore`.
    """
    from blockloc.maps.store import MapWriter

    s = check_tile_size(tile_size_m)
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise MapError(f"points: expected an (N, 3) array, got shape {pts.shape}")
    if len(pts) == 0:
        raise MapError("global map is empty: nothing to tile")
    if not np.isfinite(pts).all():
        raise MapError("global map has non-finite coordinates (NaN/inf): remove them first")
    groups = split_into_tiles(pts, s)
    d = name_decimals(s)
    p = {"tile_size_m": s, "origin": [0.0, 0.0], "name_decimals": d, **(params or {})}
    with MapWriter(out, "grid", frame=frame, params=p, overwrite=overwrite) as w:
        for k, ((ix, iy), idx) in enumerate(groups.items()):
            w.add(tile_name(ix, iy, s, d), pts[idx], None if intensity is None else intensity[idx])
            if progress is not None:
                progress(k + 1, len(groups))
        store = w.commit()
    log.info("tiled %d points into %d tiles of %.3g m", len(pts), len(groups), s)
    return store


def tile_pcd_file(path: str | Path, tile_size_m: float, out: str | Path, *,
                  overwrite: bool = False, progress: Callable[[int, int], None] | None = None):
    """``blockloc map tile``: read a global PCD and write its grid store (progress: as for
    :func:`tile_global_map`)."""
    from blockloc.maps.pcd import read_pcd

    check_tile_size(tile_size_m)
    pts, inten = read_pcd(path)
    if len(pts) == 0:
        raise MapError(f"{path}: holds no points, nothing to tile")
    finite = np.isfinite(pts).all(axis=1)
    if not finite.all():
        log.warning("%s: dropping %d points with NaN/inf coordinates", path, int((~finite).sum()))
        pts, inten = pts[finite], None if inten is None else inten[finite]
    return tile_global_map(pts, inten, tile_size_m, out, params={"source": str(path)},
                           overwrite=overwrite, progress=progress)


# --------------------------------------------------------------------------- voxel sums per tile
#: One voxel of one tile, summed: the voxel's key floor(p / voxel) (int32, x y z), the sums of
#: x, y, z and intensity (float64) and the number of points. Sums of the same voxel from any
#: number of scans add up exactly (unlike centroids of centroids), so a tile's voxel filter can be
#: computed in parts and merged: the tiles hold the voxel filter of the union of all their points.
VOXEL_SUM = np.dtype([("key", "<i4", (3,)), ("sum", "<f8", (4,)), ("count", "<i4")])
_KEY_LIMIT = 2**31 - 1


def voxel_sums(points: np.ndarray, intensity: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Records (M,) of :data:`VOXEL_SUM` of points (N, 3) float64 (map frame, metres) with
    intensity (N,): one per occupied voxel, ascending key order. ``voxel_size_m <= 0``: one
    record per point, input order (no filter)."""
    pts = np.asarray(points, np.float64)
    inten = np.asarray(intensity, np.float64)
    if not voxel_size_m > 0 or len(pts) == 0:
        rec = np.zeros(len(pts), VOXEL_SUM)
        rec["sum"][:, :3], rec["sum"][:, 3], rec["count"] = pts, inten, 1
        return rec
    from blockloc.voxels import voxel_groups

    keys = np.floor(pts / voxel_size_m)
    if np.abs(keys).max() > _KEY_LIMIT:
        raise MapError(f"voxel size {voxel_size_m} m: the map spans more than 2^31 voxels per axis")
    inverse, first, counts = voxel_groups(pts, voxel_size_m)
    return _summed(keys[first], inverse, counts, np.c_[pts, inten])


def merge_voxel_sums(parts: list[np.ndarray], voxel_size_m: float) -> np.ndarray:
    """Records of the same tile (from several scans or chunks, in a fixed order) merged: one per
    voxel, ascending key order, sums added in the parts' order (the same bytes every time)."""
    rec = np.concatenate(parts) if len(parts) != 1 else parts[0]
    if not voxel_size_m > 0 or len(rec) == 0:
        return rec
    from blockloc.voxels import voxel_groups

    # integer keys are grouped as voxels of side 1 around their centres (exact in float64)
    inverse, first, counts = voxel_groups(rec["key"] + 0.5, 1.0)
    sums = np.bincount(inverse, weights=rec["count"], minlength=len(first))
    return _summed(rec["key"][first], inverse, sums.astype(np.int64), rec["sum"])


def _summed(keys, inverse, counts, values) -> np.ndarray:
    m = len(counts)
    rec = np.empty(m, VOXEL_SUM)
    rec["key"] = keys
    for k in range(4):
        rec["sum"][:, k] = np.bincount(inverse, weights=values[:, k], minlength=m)
    rec["count"] = counts
    return rec


def tile_voxel_sums(points: np.ndarray, intensity: np.ndarray | None, tile_size_m: float,
                    voxel_size_m: float) -> list[tuple[tuple[int, int], np.ndarray]]:
    """Points (N, 3) map frame split into tiles, each summed by voxel: [(cell, records)] in
    sorted cell order (intensity None counts as 0)."""
    pts = np.asarray(points, np.float64)
    inten = np.zeros(len(pts)) if intensity is None else np.asarray(intensity, np.float64)
    return [(cell, voxel_sums(pts[idx], inten[idx], voxel_size_m))
            for cell, idx in split_into_tiles(pts, tile_size_m).items()]


def voxel_sum_points(records: np.ndarray, cell: tuple[int, int], tile_size_m: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """A tile's points: voxel centroids (M, 3) float32 and mean intensity (M,) float32.

    A centroid lies in its cell (the mean of points that do); one that float32 rounding moves
    onto or past the cell's border is moved back by a unit in the last place, so every point
    stays in its tile."""
    n = np.maximum(records["count"], 1).astype(np.float64)
    pts = (records["sum"][:, :3] / n[:, None]).astype(np.float32)
    inten = (records["sum"][:, 3] / n).astype(np.float32)
    s = check_tile_size(tile_size_m)
    for axis, i in enumerate(cell):
        lo, hi = np.float32(i * s), np.float32((i + 1) * s)
        while float(lo) < i * s:
            lo = np.nextafter(lo, np.float32(np.inf))
        while float(hi) >= (i + 1) * s:
            hi = np.nextafter(hi, np.float32(-np.inf))
        np.clip(pts[:, axis], lo, hi, out=pts[:, axis])
    return pts, inten


class GridMapBuilder:
    """Streaming grid map in memory: ``add`` keyframe points (map frame) as they come,
    ``finish(out)``.

    Points are binned into tiles and summed by voxel on arrival; a tile's sums are merged
    whenever it holds more than ``compact_points`` records, so memory follows the mapped area,
    not the number of scans. Each tile holds the voxel filter of the union of its points (the
    distributed build, :mod:`blockloc.maps.build_plan`, computes the same in parts).
    """

    def __init__(self, tile_size_m: float = 20.0, voxel_size_m: float = 0.2,
                 compact_points: int = 1_000_000):
        self.tile_size_m = check_tile_size(tile_size_m)
        self.voxel_size_m = float(voxel_size_m)
        self.compact_points = int(compact_points)
        self.num_keyframes = 0
        self._acc: dict[tuple[int, int], list[np.ndarray]] = {}
        self._count: dict[tuple[int, int], int] = {}

    def add(self, points_map: np.ndarray, intensity: np.ndarray | None = None) -> None:
        """One keyframe's points (N, 3) map frame, metres, and intensity (N,) or None."""
        self.num_keyframes += 1
        for cell, rec in tile_voxel_sums(points_map, intensity, self.tile_size_m, self.voxel_size_m):
            self._acc.setdefault(cell, []).append(rec)
            self._count[cell] = self._count.get(cell, 0) + len(rec)
            if self._count[cell] > self.compact_points and self.voxel_size_m > 0:
                merged = merge_voxel_sums(self._acc[cell], self.voxel_size_m)
                self._acc[cell], self._count[cell] = [merged], len(merged)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """The voxel-filtered map so far: points (N, 3) float32, intensity (N,) float32."""
        parts_p, parts_i = [], []
        for cell in sorted(self._acc):
            rec = merge_voxel_sums(self._acc[cell], self.voxel_size_m)
            self._acc[cell], self._count[cell] = [rec], len(rec)
            p, i = voxel_sum_points(rec, cell, self.tile_size_m)
            parts_p.append(p)
            parts_i.append(i)
        if not parts_p:
            return np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
        return np.concatenate(parts_p), np.concatenate(parts_i)

    def finish(self, out: str | Path, *, params: dict | None = None, overwrite: bool = False,
               frame: str = "map"):
        """Write the grid store atomically to ``out``; returns the opened store."""
        if self.num_keyframes == 0:
            raise MapError("no keyframes to build a grid map from (empty session?)")
        pts, inten = self.points()
        p = {"voxel_size_m": self.voxel_size_m, "num_keyframes": self.num_keyframes, **(params or {})}
        return tile_global_map(pts, inten, self.tile_size_m, out, frame=frame, params=p, overwrite=overwrite)


# --------------------------------------------------------------------------- Algorithm 2 window


def heading_sector(velocity_xy: np.ndarray | None, min_speed_m_s: float = 0.1) -> int | None:
    """Sector 0..7 (E, NE, N, NW, W, SW, S, SE; 45 deg each, centred on the axes and diagonals)
    of the horizontal velocity (map frame, m/s), or None when slower than ``min_speed_m_s``."""
    if velocity_xy is None:
        return None
    v = np.asarray(velocity_xy, np.float64)
    if not np.all(np.isfinite(v[:2])) or np.hypot(v[0], v[1]) < min_speed_m_s:
        return None
    angle = math.atan2(v[1], v[0])
    return int(round(angle / (math.pi / 4))) % 8


def grid_window(ix: int, iy: int, n: int, k: int, sector: int | None) -> list[tuple[int, int]]:
    """Cells of the window: (2n+1)^2 around (ix, iy), widened by k cells toward ``sector``.

    Axis sectors (E, N, W, S) add k columns/rows of 2n+1 cells on that side; diagonal sectors add
    them on both sides they face, including the corner block, so the window stays a rectangle
    ((2n+1+k)^2 cells). ``sector`` None: the plain (2n+1)^2 window.
    """
    if n < 0 or k < 0:
        raise MapError(f"grid window n={n}, k={k}: expected non-negative integers")
    x0, x1, y0, y1 = ix - n, ix + n, iy - n, iy + n
    if sector is not None and k > 0:
        dx, dy = SECTOR_DIRECTIONS[sector]
        x1 += k if dx > 0 else 0
        x0 -= k if dx < 0 else 0
        y1 += k if dy > 0 else 0
        y0 -= k if dy < 0 else 0
    return [(x, y) for x in range(x0, x1 + 1) for y in range(y0, y1 + 1)]
