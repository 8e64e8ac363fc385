"""What a map store holds: counts, bytes, bounds, overhead and the overlap between entries."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from blockloc.maps.store import MapStore

log = logging.getLogger(__name__)

PCD_POINT_BYTES = 16  # x y z intensity, float32


def overlap_ratio(store: MapStore, voxel_size_m: float | None = None) -> float:
    """Share of stored points that duplicate another entry's points: 1 - (distinct voxels over the
    whole map) / (sum over entries of their distinct voxels), voxels of ``voxel_size_m`` (default:
    the map's voxel size, else 0.2 m). 0 for a partition such as grid tiles."""
    v = float(voxel_size_m or store.params.get("voxel_size_m") or 0.2)
    keys, total = [], 0
    for e in store.entries:
        pts, _ = store.load(e.id)
        if len(pts) == 0:
            continue
        k = np.unique(np.floor(pts.astype(np.float64) / v).astype(np.int64), axis=0)
        keys.append(k)
        total += len(k)
    if total == 0:
        return 0.0
    distinct = len(np.unique(np.concatenate(keys), axis=0))
    return 1.0 - distinct / total


def map_summary(store: MapStore, with_overlap: bool = True) -> dict[str, Any]:
    """One JSON-able dict: kind, entries, points, bytes, bounds, overhead and overlap."""
    lo, hi = store.bounds()
    payload = store.total_points * PCD_POINT_BYTES
    out = {
        "path": str(store.path), "kind": store.kind, "frame": store.frame, "version": store.version,
        "legacy_layout": store.legacy, "entries": len(store.entries), "points": store.total_points,
        "bytes": store.total_bytes,
        "header_overhead_pct": 100.0 * (store.total_bytes - payload) / payload if payload else 0.0,
        "bounds_min": [round(float(v), 3) for v in lo], "bounds_max": [round(float(v), 3) for v in hi],
        "points_per_entry": {
            "min": int(min(e.num_points for e in store.entries)) if store.entries else 0,
            "median": float(np.median([e.num_points for e in store.entries])) if store.entries else 0,
            "max": int(max(e.num_points for e in store.entries)) if store.entries else 0,
        },
        "parameters": store.params,
    }
    if with_overlap:
        out["overlap_ratio"] = overlap_ratio(store)
    return out


def entry_footprint(store: MapStore, entry, margin_m: float | None = None) -> np.ndarray | None:
    """(K, 2) polygon, map frame x/y metres, of the area an entry serves, or None when unknown.

    Grid tiles: the tile's square. Blocks: the convex hull of the keyframe positions the block was
    built from, grown by ``margin_m`` (default: a tenth of the block size, at least 2 m): where the
    robot is when this block is the one served. A block's stored bounds are not that: its points
    reach sensor range, so the bounds of neighbouring blocks nearly all overlap. Blocks of the
    released layout (no keyframes) have no footprint (None).
    """
    if store.kind == "grid":
        from blockloc.maps.grid_tiles import tile_bounds

        lo, hi = tile_bounds(entry.id, float(store.params["tile_size_m"]))
        return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]], np.float64)
    if entry.keyframes is None or len(entry.keyframes) == 0:
        return None
    if margin_m is None:
        margin_m = max(0.1 * float(store.params.get("block_size_m", 20.0) or 20.0), 2.0)
    angles = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    ring = margin_m * np.c_[np.cos(angles), np.sin(angles)]
    pts = (np.asarray(entry.keyframes, np.float64)[:, None, :2] + ring[None]).reshape(-1, 2)
    from scipy.spatial import ConvexHull, QhullError

    try:
        return pts[ConvexHull(pts).vertices]
    except QhullError:  # all keyframes on a line: the grown segment's box
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])


def map_points_xy(store: MapStore, max_points: int = 150_000) -> np.ndarray:
    """(K, 2) map x/y of at most about ``max_points`` points, strided entry by entry (the whole
    map is never loaded at once; entries that fail to load are skipped)."""
    from blockloc.errors import MapError

    per_entry = max(max_points // max(len(store.entries), 1), 1)
    parts = []
    for e in store.entries:
        try:
            pts, _ = store.load(e.id)
        except MapError as exc:
            log.warning("%s", exc)
            continue
        stride = max(1, len(pts) // per_entry)
        parts.append(np.asarray(pts[::stride, :2], np.float32))
    return np.concatenate(parts) if parts else np.zeros((0, 2), np.float32)
