"""Which blocks/tiles should be resident: the four map policies as small pure state machines.

Each policy (``POLICIES``, built by :func:`make_policy`) turns the robot's position (map frame, metres), velocity (m/s) and time (s) into a
*region*: a sorted tuple of store entry ids. ``select`` advances the policy's state (call it once
per frame); ``peek`` answers the same question for a hypothetical future position without
changing state; ``ahead`` predicts the next region the robot will need when it keeps its
velocity for ``horizon_m`` metres (used to prefetch), or None.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from blockloc.errors import MapError
from blockloc.maps.grid_tiles import (SECTOR_NAMES, cell_of, grid_window, heading_sector,
                                      parse_tile_name, tile_name)

Region = tuple  # sorted tuple of entry ids


class GlobalPolicy:
    """Everything: the baseline every claim is measured against."""

    name = "global"

    def __init__(self, ids: Sequence[str]):
        self.region: Region = tuple(sorted(ids))

    @classmethod
    def for_store(cls, store, **_settings) -> "GlobalPolicy":
        return cls(store.ids)

    def select(self, position, velocity, stamp) -> Region:
        return self.region

    def peek(self, position, velocity) -> Region:
        return self.region

    def ahead(self, position, velocity, horizon_m) -> Region | None:
        return None

    def region_name(self, region: Region) -> str:
        return "global"


def _ray(position, velocity, horizon_m: float, step_m: float):
    """Points along the horizontal motion ray from ``position``, every ``step_m`` up to
    ``horizon_m`` (the first sample just ahead), or an empty list when not moving."""
    if velocity is None:
        return []
    v = np.asarray(velocity, np.float64)[:2]
    speed = float(np.hypot(*v))
    if not np.isfinite(speed) or speed < 1e-3 or horizon_m <= 0:
        return []
    u = v / speed
    p = np.asarray(position, np.float64)
    n = max(int(math.ceil(horizon_m / step_m)), 1)
    out = []
    for i in range(1, n + 1):
        q = p.copy()
        q[:2] = p[:2] + u * min(i * step_m, horizon_m)
        out.append(q)
    return out


class BlockPolicy:
    """The block that covers the robot best, with hysteresis.

    With ``keyframes`` (per block, the (K, 3) sensor positions it was built from) the distance of a
    block is that of its nearest keyframe: the block whose mapping drive passed closest, so the
    one whose points surround the robot. (The block-map paper's nearest centroid can pick a block
    built on a parallel street whose centroid happens to be nearer: measured on the campus world,
    fitness fell from 0.72 to 0.38 before the switch to a block scoring 0.97 there.) Without
    keyframes (the released layout) the distance is the centroid's. The active block changes only
    when another one is nearer by more than ``hysteresis_m``, so a robot driving along the border
    of two blocks does not flip between them.

    With ``blend_m`` > 0 the region also holds the nearest other block that has a keyframe within
    ``blend_m`` of the robot (at most two blocks): near the end of a block's drive its points lie
    behind the robot, and a single block there measurably degrades the fit (campus, one block:
    position error RMSE 0.09 m in the 20 scans around a switch against 0.04 m far from one; the
    global map 0.04 m at both). The region is the sorted tuple of the block ids.
    """

    name = "block"

    def __init__(self, ids: Sequence[str], centroids: np.ndarray, hysteresis_m: float = 5.0,
                 keyframes: Sequence[np.ndarray | None] | None = None, blend_m: float = 0.0):
        if len(ids) == 0:
            raise MapError("block map has no blocks")
        if hysteresis_m < 0:
            raise MapError(f"switch hysteresis {hysteresis_m!r} m: expected >= 0")
        if not blend_m >= 0:
            raise MapError(f"block blend distance {blend_m!r} m: expected >= 0")
        from scipy.spatial import cKDTree

        self.ids = list(ids)
        self.centroids = np.asarray(centroids, np.float64).reshape(-1, 3)
        # a block without keyframes is represented by its centroid
        anchors = [self.centroids[i:i + 1] if keyframes is None or keyframes[i] is None
                   or len(keyframes[i]) == 0 else np.asarray(keyframes[i], np.float64).reshape(-1, 3)
                   for i in range(len(self.ids))]
        self._block_of = np.concatenate([np.full(len(a), i) for i, a in enumerate(anchors)])
        self.tree = cKDTree(np.concatenate(anchors))
        self._trees = [cKDTree(a) for a in anchors]
        self.hysteresis_m = float(hysteresis_m)
        self.blend_m = float(blend_m)
        self.current: int | None = None

    @classmethod
    def for_store(cls, store, *, switch_hysteresis_m: float = 5.0, block_blend_m: float = 15.0,
                  **_settings) -> "BlockPolicy":
        if store.kind != "block":
            raise MapError(f"{store.path}: the 'block' backend needs a block map, this is a "
                           f"{store.kind} map (use --map-backend grid, srt or global)")
        return cls(store.ids, store.centroids(), switch_hysteresis_m,
                   keyframes=[e.keyframes for e in store.entries], blend_m=block_blend_m)

    def _choose(self, position, current: int | None) -> int:
        p = np.asarray(position, np.float64)
        d_new, a = self.tree.query(p)
        j = int(self._block_of[a])
        if current is None or j == current:
            return j
        d_cur, _ = self._trees[current].query(p)
        return j if d_new + self.hysteresis_m < d_cur else current

    def _region(self, current: int, position) -> Region:
        if self.blend_m <= 0:
            return (self.ids[current],)
        p = np.asarray(position, np.float64)
        others = {int(self._block_of[a]) for a in self.tree.query_ball_point(p, self.blend_m)} - {current}
        if not others:
            return (self.ids[current],)
        nearest = min(others, key=lambda j: (self._trees[j].query(p)[0], j))
        return tuple(sorted((self.ids[current], self.ids[nearest])))

    def select(self, position, velocity, stamp) -> Region:
        self.current = self._choose(position, self.current)
        return self._region(self.current, position)

    def reset(self) -> None:
        """Forget the current block (the robot jumped: no hysteresis toward where it was)."""
        self.current = None

    def peek(self, position, velocity) -> Region:
        return self._region(self._choose(position, self.current), position)

    @property
    def primary(self) -> str | None:
        """The block the robot is in (the first of a blended pair is not necessarily it)."""
        return None if self.current is None else self.ids[self.current]

    def ahead(self, position, velocity, horizon_m) -> Region | None:
        if velocity is None:
            return None
        v = np.asarray(velocity, np.float64)
        speed = float(np.linalg.norm(v))
        if not np.isfinite(speed) or speed < 1e-3:
            return None
        region = self.peek(np.asarray(position, np.float64) + v / speed * horizon_m, velocity)
        return region if self.current is None or region != self._region(self.current, position) else None

    def region_name(self, region: Region) -> str:
        return "+".join(region)


class GridPolicy:
    """Grid-puzzle Algorithm 2: (2n+1)^2 tiles around the robot's tile, widened by k tiles toward
    the heading sector (8 sectors of 45 degrees); recomputed only after the robot has moved more
    than s/2 from where the window was last computed."""

    name = "grid"

    def __init__(self, ids: Sequence[str], tile_size_m: float, n: int = 1, k: int = 1):
        self.tile_size_m = float(tile_size_m)
        self.n, self.k = int(n), int(k)
        self.cells = {parse_tile_name(i, self.tile_size_m): i for i in ids}
        self.anchor: np.ndarray | None = None
        self.region: Region | None = None
        self.centre: tuple[int, int] | None = None
        self.sector: int | None = None

    @classmethod
    def for_store(cls, store, *, grid_n: int = 2, grid_k: int = 1, **_settings) -> "GridPolicy":
        return cls(store.ids, grid_tile_size(store, "grid"), grid_n, grid_k)

    def _window(self, position, velocity) -> tuple[Region, tuple[int, int], int | None]:
        cell = tuple(int(v) for v in cell_of(np.asarray(position, float)[None, :2], self.tile_size_m)[0])
        sector = heading_sector(None if velocity is None else np.asarray(velocity)[:2])
        cells = grid_window(cell[0], cell[1], self.n, self.k, sector)
        return tuple(sorted(self.cells[c] for c in cells if c in self.cells)), cell, sector

    def select(self, position, velocity, stamp) -> Region:
        p = np.asarray(position, np.float64)[:2]
        if self.anchor is None or np.linalg.norm(p - self.anchor) > self.tile_size_m / 2:
            self.region, self.centre, self.sector = self._window(position, velocity)
            self.anchor = p.copy()
        return self.region

    def peek(self, position, velocity) -> Region:
        return self._window(position, velocity)[0]

    def ahead(self, position, velocity, horizon_m) -> Region | None:
        """The window at the point where the robot, keeping its heading, next moves more than
        s/2 from the current anchor (where the window will be recomputed)."""
        if self.anchor is None:
            return None
        for q in _ray(position, velocity, horizon_m, self.tile_size_m / 20):
            if np.linalg.norm(q[:2] - self.anchor) > self.tile_size_m / 2:
                return self.peek(q, velocity)
        return None

    def region_name(self, region: Region) -> str:
        if self.centre is None:
            return "grid"
        sec = "-" if self.sector is None else SECTOR_NAMES[self.sector]
        return f"{tile_name(*self.centre, self.tile_size_m)}/{sec}"


class SrtPolicy:
    """SRT-PM: every tile within radius R' of the robot (tiles whose square intersects the disk)
    merged into one partial map, recomputed when the robot enters a new cell or after T seconds."""

    name = "srt"

    def __init__(self, ids: Sequence[str], tile_size_m: float, radius_m: float = 60.0,
                 rebuild_period_s: float = 10.0):
        if not radius_m > 0:
            raise MapError(f"SRT radius {radius_m!r} m: expected a positive number")
        self.tile_size_m = float(tile_size_m)
        self.radius_m = float(radius_m)
        self.rebuild_period_s = float(rebuild_period_s)
        s = self.tile_size_m
        self.ids = list(ids)
        cells = np.array([parse_tile_name(i, s) for i in ids], np.float64).reshape(-1, 2)
        self.cell_min = cells * s
        self.cell_max = (cells + 1) * s
        self.cell: tuple[int, int] | None = None
        self.built_at: float = -math.inf
        self.last_stamp: float = -math.inf
        self.region: Region | None = None

    @classmethod
    def for_store(cls, store, *, srt_radius_m: float = 60.0, srt_rebuild_period_s: float = 10.0,
                  **_settings) -> "SrtPolicy":
        return cls(store.ids, grid_tile_size(store, "srt"), srt_radius_m, srt_rebuild_period_s)

    def _tiles(self, position) -> Region:
        p = np.asarray(position, np.float64)[:2]
        nearest = np.clip(p, self.cell_min, self.cell_max)
        inside = np.linalg.norm(nearest - p, axis=1) <= self.radius_m
        return tuple(sorted(self.ids[i] for i in np.flatnonzero(inside)))

    def select(self, position, velocity, stamp) -> Region:
        self.last_stamp = float(stamp)
        cell = tuple(int(v) for v in cell_of(np.asarray(position, float)[None, :2], self.tile_size_m)[0])
        if self.region is None or cell != self.cell or stamp - self.built_at >= self.rebuild_period_s:
            self.region = self._tiles(position)
            self.cell, self.built_at = cell, float(stamp)
        return self.region

    def peek(self, position, velocity) -> Region:
        return self._tiles(position)

    def ahead(self, position, velocity, horizon_m) -> Region | None:
        """The next partial map, if the robot keeps its velocity: built where it enters the next
        cell or where the period T runs out, whichever comes first within ``horizon_m``."""
        if self.cell is None or velocity is None:
            return None
        v = np.asarray(velocity, np.float64)[:2]
        speed = float(np.hypot(*v))
        if not np.isfinite(speed) or speed < 1e-3:
            return None
        d_expiry = speed * max(self.built_at + self.rebuild_period_s - self.last_stamp, 0.0)
        for q in _ray(position, velocity, min(horizon_m, d_expiry), self.tile_size_m / 20):
            cell = tuple(int(c) for c in cell_of(q[None, :2], self.tile_size_m)[0])
            if cell != self.cell:
                return self._tiles(q)
        if d_expiry <= horizon_m:
            q = np.asarray(position, np.float64).copy()
            q[:2] += v / speed * d_expiry
            return self._tiles(q)
        return None

    def region_name(self, region: Region) -> str:
        return "srt" if self.cell is None else f"srt:{tile_name(*self.cell, self.tile_size_m)}"


def grid_tile_size(store, backend: str) -> float:
    """The tile size of a grid store, or MapError saying the backend needs a grid map."""
    if store.kind != "grid":
        raise MapError(f"{store.path}: the '{backend}' backend needs a grid map, this is a "
                       f"{store.kind} map (build one with 'blockloc map build --kind grid')")
    size = float(store.params.get("tile_size_m", 0) or 0)
    if not size > 0:
        raise MapError(f"{store.path}: grid map without a positive tile_size_m parameter")
    return size


#: Map backends by name: a new backend is a policy class with ``for_store`` plus one line here.
POLICIES = {"block": BlockPolicy, "grid": GridPolicy, "srt": SrtPolicy, "global": GlobalPolicy}
BACKENDS = tuple(POLICIES)


def make_policy(backend: str, store, /, **settings):
    """The policy ``backend`` (block | grid | srt | global) for ``store``.

    settings: the policies' keywords, named as in the ``map`` config section (switch_hysteresis_m,
    block_blend_m, grid_n, grid_k, srt_radius_m, srt_rebuild_period_s); each policy takes the
    ones it knows and ignores the rest (so ``**dataclasses.asdict(map_cfg)`` can be passed).
    """
    cls = POLICIES.get(backend)
    if cls is None:
        raise MapError(f"map backend {backend!r}: expected one of {', '.join(POLICIES)}")
    if len(store.entries) == 0:
        raise MapError(f"{store.path}: the map has no blocks or tiles")
    return cls.for_store(store, **settings)
