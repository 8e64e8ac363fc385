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
