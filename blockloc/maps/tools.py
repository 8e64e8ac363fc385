"""What the ``blockloc map`` commands do, apart from argument parsing: build, summarize, plot."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from blockloc.errors import MapError
from blockloc.maps.store import MapStore, open_map

log = logging.getLogger(__name__)

PCD_POINT_BYTES = 16  # x y z intensity, float32


def build_map(seq, kind: str, out: str | Path, map_cfg, *, overwrite: bool = False,
              progress: bool = True, max_frames: int | None = None) -> MapStore:
    """Build a block or grid store from a mapping sequence with the ``MapConfig`` parameters."""
    if kind == "block":
        from blockloc.maps.block_maps import build_block_map_from_sequence

        return build_block_map_from_sequence(
            seq, block_size_m=map_cfg.block_size_m, keyframe_distance_m=map_cfg.keyframe_distance_m,
            keyframe_angle_deg=map_cfg.keyframe_angle_deg, voxel_size_m=map_cfg.voxel_size_m, out=out,
            progress=progress, overwrite=overwrite, max_frames=max_frames)
    if kind == "grid":
        from blockloc.maps.grid_tiles import build_grid_map_from_sequence

        return build_grid_map_from_sequence(
            seq, tile_size_m=map_cfg.tile_size_m, keyframe_distance_m=map_cfg.keyframe_distance_m,
            keyframe_angle_deg=map_cfg.keyframe_angle_deg, voxel_size_m=map_cfg.voxel_size_m, out=out,
            progress=progress, overwrite=overwrite, max_frames=max_frames)
    raise MapError(f"map kind {kind!r}: expected block or grid")


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


def print_summary(summary: dict[str, Any], console) -> None:
    from rich.table import Table

    t = Table(title=f"{summary['kind']} map {summary['path']}", show_header=False)
    t.add_column("", style="bold")
    t.add_column("")
    unit = "blocks" if summary["kind"] == "block" else "tiles"
    t.add_row(unit, f"{summary['entries']:,}")
    t.add_row("points", f"{summary['points']:,}")
    t.add_row("bytes", f"{summary['bytes']:,} ({summary['bytes'] / 2**20:.1f} MiB, headers "
                       f"{summary['header_overhead_pct']:.2f}%)")
    ppe = summary["points_per_entry"]
    t.add_row(f"points per {unit[:-1]}", f"min {ppe['min']:,}  median {ppe['median']:,.0f}  "
                                         f"max {ppe['max']:,}")
    t.add_row("bounds", f"{summary['bounds_min']} .. {summary['bounds_max']}")
    if "overlap_ratio" in summary:
        t.add_row("overlap", f"{100 * summary['overlap_ratio']:.1f}% of stored points repeat "
                             "another entry's")
    params = {k: v for k, v in summary["parameters"].items() if not isinstance(v, (dict, list))}
    t.add_row("parameters", ", ".join(f"{k}={v}" for k, v in params.items()))
    if summary["legacy_layout"]:
        t.add_row("layout", "released block-map layout (no manifest, no checksums)")
    console.print(t)


def plot_map(store: MapStore, out: str | Path, trajectory=None, max_points: int = 200_000,
             title: str | None = None) -> Path:
    """PNG of the blocks/tiles from above: subsampled points coloured by entry, entry outlines,
    block centroids, and the trajectory (a ``Trajectory``, (N, 3) positions, or None)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    out = Path(out)
    rng = np.random.default_rng(0)
    fig, ax = plt.subplots(figsize=(10, 10))
    cmap = plt.get_cmap("tab10")
    per_entry = max(max_points // max(len(store.entries), 1), 200)
    for k, e in enumerate(store.entries):
        color = cmap(k % 10)
        try:
            pts, _ = store.load(e.id)
        except MapError as exc:
            log.warning("%s", exc)
            pts = np.zeros((0, 3), np.float32)
        if len(pts) > per_entry:
            pts = pts[rng.choice(len(pts), per_entry, replace=False)]
        ax.scatter(pts[:, 0], pts[:, 1], s=0.2, color=color, alpha=0.5, linewidths=0, rasterized=True)
        if store.kind == "grid":
            s = float(store.params["tile_size_m"])
            from blockloc.maps.grid_tiles import tile_bounds

            lo, _ = tile_bounds(e.id, s)
            ax.add_patch(Rectangle(lo, s, s, fill=False, lw=0.4, color="0.5"))
        else:
            ax.add_patch(Rectangle(e.bounds_min[:2], *(e.bounds_max[:2] - e.bounds_min[:2]),
                                   fill=False, lw=1.0, color=color))
            ax.plot(*e.centroid[:2], "k+", ms=10)
            ax.annotate(e.id, e.centroid[:2], textcoords="offset points", xytext=(4, 4), fontsize=9)
    if trajectory is not None:
        pos = trajectory.positions if hasattr(trajectory, "positions") else np.asarray(trajectory)
        ax.plot(pos[:, 0], pos[:, 1], "k-", lw=1.0, label="trajectory")
        ax.plot(*pos[0, :2], "go", label="start")
        ax.legend(loc="upper right")
    unit = "blocks" if store.kind == "block" else "tiles"
    ax.set_title(title or f"{store.kind} map: {len(store.entries)} {unit}, {store.total_points:,} points")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    fig.tight_layout()
    tmp = out.with_name(out.name + ".tmp.png")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    tmp.replace(out)
    return out

