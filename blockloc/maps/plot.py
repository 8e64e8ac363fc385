"""A map store drawn from above: each block or tile as its real footprint, coloured, with a
legend; the stored points coloured the same way; a trajectory.

A block's stored bounds reach as far as its keyframes saw (sensor range), so on a real map they
are several times the block size and nearly all overlap; it is drawn as its footprint, where the
block is used (:func:`blockloc.maps.summary.entry_footprint`: the hull of its keyframe
positions, grown by a margin). A block without recorded keyframes (the released block-map
layout) gets the hull of the cells where its points are densest. A grid tile is its cell.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from blockloc.errors import MapError
from blockloc.fileio import save_figure
from blockloc.maps.store import MapEntry, MapStore

log = logging.getLogger(__name__)

#: Blocks/tiles named one by one in the legend; more get one legend line for all.
LEGEND_MAX_ENTRIES = 12


def dense_cells_hull(points_xy: np.ndarray, cell_m: float) -> np.ndarray:
    """Convex hull (K, 2) of the cells of side ``cell_m`` holding at least the median count of
    the occupied cells: where a block's points are densest, near the keyframes that saw them."""
    from scipy.spatial import ConvexHull, QhullError

    cells = np.floor(np.asarray(points_xy, float) / cell_m).astype(np.int64)
    keys, counts = np.unique(cells, axis=0, return_counts=True)
    dense = keys[counts >= np.median(counts)]
    corners = np.array([[0, 0], [1, 0], [0, 1], [1, 1]])
    pts = ((dense[:, None, :] + corners[None]) * cell_m).reshape(-1, 2).astype(float)
    try:
        return pts[ConvexHull(pts).vertices]
    except QhullError:  # a single row of cells: their box
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])


def polygon_area(poly: np.ndarray) -> float:
    """Area (m^2) of a simple polygon (K, 2), shoelace formula."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def plot_footprint(store: MapStore, entry: MapEntry, points: np.ndarray) -> np.ndarray:
    """The outline (K, 2) drawn for one entry, map frame xy, metres: its footprint
    (:func:`blockloc.maps.summary.entry_footprint`), or for a block without recorded keyframes the
    hull of its densest cells (``points`` (N, 3), its points)."""
    from blockloc.maps.summary import entry_footprint

    poly = entry_footprint(store, entry)
    if poly is not None:
        return poly
    if len(points):
        size = float(store.params.get("block_size_m") or 40.0)
        return dense_cells_hull(np.asarray(points)[:, :2], max(size / 10.0, 1.0))
    return np.asarray(entry.centroid, float)[None, :2]


def map_figure(store: MapStore, trajectory=None, max_points: int = 200_000, title: str | None = None):
    """(matplotlib Figure, {entry id: footprint (K, 2)}) of the map from above: subsampled points
    and footprints coloured by entry, entry ids, a legend, and the trajectory (a ``Trajectory``,
    (N, 3) positions, or None)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Polygon

    rng = np.random.default_rng(0)
    fig, ax = plt.subplots(figsize=(10, 10))
    n = len(store.entries)
    cmap = plt.get_cmap("tab20" if n > 10 else "tab10")
    per_entry = max(max_points // max(n, 1), 200)
    unit = "block" if store.kind == "block" else "tile"
    footprints: dict[str, np.ndarray] = {}
    handles = []
    for k, e in enumerate(store.entries):
        color = cmap(k % cmap.N)
        try:
            pts, _ = store.load(e.id)
        except MapError as exc:
            log.warning("%s", exc)
            pts = np.zeros((0, 3), np.float32)
        poly = plot_footprint(store, e, pts)
        footprints[e.id] = poly
        if len(pts) > per_entry:
            pts = pts[rng.choice(len(pts), per_entry, replace=False)]
        ax.scatter(pts[:, 0], pts[:, 1], s=0.2, color=color, alpha=0.35, linewidths=0, rasterized=True)
        if len(poly) >= 3:
            ax.add_patch(Polygon(poly, closed=True, facecolor=(*color[:3], 0.18), edgecolor=color, lw=1.2))
        if store.kind == "block":
            ax.annotate(e.id, poly.mean(axis=0), ha="center", va="center", fontsize=9, weight="bold")
        if n <= LEGEND_MAX_ENTRIES:
            handles.append(Patch(facecolor=(*color[:3], 0.3), edgecolor=color,
                                 label=f"{unit} {e.id} ({e.num_points:,} points)"))
    if n > LEGEND_MAX_ENTRIES:
        handles.append(Patch(facecolor="0.85", edgecolor="0.4", label=f"{n} {unit}s (one colour each)"))
    if store.kind == "block":
        handles.append(Patch(facecolor="none", edgecolor="none", label="footprint: hull of the block's keyframes"))
    if trajectory is not None:
        pos = trajectory.positions if hasattr(trajectory, "positions") else np.asarray(trajectory)
        ax.plot(pos[:, 0], pos[:, 1], "k-", lw=1.0)
        ax.plot(*pos[0, :2], "go")
        handles += [Line2D([], [], color="k", lw=1.0, label="trajectory"),
                    Line2D([], [], color="g", marker="o", ls="", label="start")]
    ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.85)
    ax.set_title(title or f"{store.kind} map: {n} {unit}s, {store.total_points:,} points")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    fig.tight_layout()
    return fig, footprints


def plot_map(store: MapStore, out: str | Path, trajectory=None, max_points: int = 200_000,
             title: str | None = None) -> Path:
    """The :func:`map_figure` of ``store`` saved to ``out`` (PNG, or the format of its suffix)."""
    fig, _ = map_figure(store, trajectory, max_points=max_points, title=title)
    return save_figure(fig, out, dpi=120)
