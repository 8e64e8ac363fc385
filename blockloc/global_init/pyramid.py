"""Multi-resolution max pyramid with an admissible bound (sliding-window max).

Level h of the pyramid holds, at cell i, the max of the base raster over the 2^h x 2^h window
starting at i: ``P_h[i, j] = max M[i .. i + 2^h - 1, j .. j + 2^h - 1]`` (Cartographer's fast
correlative scan matcher). A search node at level h with translation offset o stands for the 2^h x
2^h translations o .. o + 2^h - 1; its bound sum_k P_h[c_k + o] is >= the score sum_k M[c_k + t] of
every translation t it stands for, so no node holding the optimum is ever pruned. A strided block
max (one value per 2^h block, as hdl_global_localization does) is not admissible: a translation that
is not a multiple of 2^h reads cells from two blocks.

All levels share the base cell lattice and one array origin ``origin - (2^H - 1)``: the window
reaching forward from a cell left of the raster may still cover occupied cells. Because every level
is a max, the pyramid of a union of map pieces is the element-wise max of the pieces' pyramids, so
per-piece pyramids (cached per map entry) assemble exactly into a region's pyramid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blockloc.global_init.projection import Raster


@dataclass
class Pyramid:
    """levels: (H+1, NX, NY) uint8; origin: (2,) int64 global cell index of levels[:, 0, 0]."""

    origin: np.ndarray
    levels: np.ndarray
    resolution: float

    @property
    def num_levels(self) -> int:
        return self.levels.shape[0]


def build_pyramid(raster: Raster, num_levels: int) -> Pyramid:
    """Pyramid of ``num_levels`` levels (level 0 = the raster) with windows 1, 2, 4, ... cells."""
    pad = (1 << (num_levels - 1)) - 1
    base = np.zeros((raster.grid.shape[0] + pad, raster.grid.shape[1] + pad), dtype=np.uint8)
    base[pad:, pad:] = raster.grid
    levels = np.empty((num_levels,) + base.shape, dtype=np.uint8)
    levels[0] = base
    for h in range(1, num_levels):
        levels[h] = _next_level(levels[h - 1], h)
    return Pyramid(np.asarray(raster.origin, np.int64) - pad, levels, raster.resolution)


def _next_level(prev: np.ndarray, h: int) -> np.ndarray:
    """Level h from level h-1: window 2^h at i = max(window 2^(h-1) at i, at i + 2^(h-1)), both axes."""
    half = 1 << (h - 1)
    cur = prev.copy()
    np.maximum(cur[:-half], prev[half:], out=cur[:-half])
    out = cur.copy()
    np.maximum(out[:, :-half], cur[:, half:], out=out[:, :-half])
    return out


def assemble(pyramids: list[Pyramid], lo: np.ndarray, hi: np.ndarray, num_levels: int | None = None) -> Pyramid:
    """Pyramid over global cells [lo, hi) (2,) int64: element-wise max of the pieces overlapping it
    (only the lowest ``num_levels`` levels when given, e.g. 1 for the base raster)."""
    if not pyramids:
        raise ValueError("no pyramids to assemble")
    lo = np.asarray(lo, np.int64)
    hi = np.asarray(hi, np.int64)
    H = pyramids[0].num_levels if num_levels is None else min(num_levels, pyramids[0].num_levels)
    out = np.zeros((H,) + tuple(int(v) for v in (hi - lo)), dtype=np.uint8)
    for p in pyramids:
        a = np.maximum(lo, p.origin)
        b = np.minimum(hi, p.origin + np.array(p.levels.shape[1:]))
        if np.any(b <= a):
            continue
        dst = out[:, a[0] - lo[0]:b[0] - lo[0], a[1] - lo[1]:b[1] - lo[1]]
        src = p.levels[:H, a[0] - p.origin[0]:b[0] - p.origin[0], a[1] - p.origin[1]:b[1] - p.origin[1]]
        np.maximum(dst, src, out=dst)
    return Pyramid(lo, out, pyramids[0].resolution)


def extend(pyramid: Pyramid, num_levels: int) -> Pyramid:
    """The same pyramid with levels added on top up to ``num_levels`` (large search windows).

    Computed on the assembled crop: a level-h value needs the level h-1 values 2^(h-1) cells ahead,
    which the crop holds for every cell a search reads (the crop spans the scan's reach past the
    window on every side, and the nodes of the added levels read only inside it); cells past the crop
    edge count as 0, so bounds there stay admissible only for reads within the crop, the only ones made.
    """
    have = pyramid.num_levels
    if num_levels <= have:
        return pyramid
    levels = np.empty((num_levels,) + pyramid.levels.shape[1:], dtype=np.uint8)
    levels[:have] = pyramid.levels
    for h in range(have, num_levels):
        levels[h] = _next_level(levels[h - 1], h)
    return Pyramid(pyramid.origin, levels, pyramid.resolution)
