"""A map store drawn from above: each block or tile as its real footprint, coloured, with a
legend; the stored points coloured the same way; a trajectory.

A block's stored bounds reach as far as its keyframes saw (sensor range), so on a real map they
are several times the block size and nearly all overlap; its footprint is where the block is
used: the convex hull of its keyframe positions, buffered by ``buffer_m``. A block without
recorded keyframes (the released block-map layout) gets the hull of the cells where its points
are densest. A grid tile's footprint is its cell.
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


def _hull(xy: np.ndarray) -> np.ndarray:
    """Convex hull (K, 2) of points (N, 2), counter-clockwise; degenerate inputs give what they
    span (a segment or a point)."""
    from scipy.spatial import ConvexHull, QhullError

    xy = np.unique(np.asarray(xy, float).reshape(-1, 2), axis=0)
    if len(xy) < 3:
        return xy
    try:
        return xy[ConvexHull(xy).vertices]
    except QhullError:  # collinear: the segment's two ends
        d = xy - xy.mean(axis=0)
        axis = np.linalg.svd(d, full_matrices=False)[2][0]
        t = d @ axis
        return xy[[int(np.argmin(t)), int(np.argmax(t))]]


def buffered_hull(xy: np.ndarray, buffer_m: float, segments: int = 24) -> np.ndarray:
    """The convex hull (K, 2) of points (N, 2) grown by ``buffer_m`` metres (the hull of discs
    of that radius around them; a single point gives a disc)."""
    a = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    disc = buffer_m * np.c_[np.cos(a), np.sin(a)]
    core = _hull(xy)
    return _hull((core[:, None, :] + disc[None]).reshape(-1, 2))


def dense_cells_hull(points_xy: np.ndarray, cell_m: float) -> np.ndarray:
    """Hull (K, 2) of the cells of side ``cell_m`` holding at least the median count of the
    occupied cells (where the points are densest: near the keyframes that saw them)."""
    cells = np.floor(np.asarray(points_xy, float) / cell_m).astype(np.int64)
    keys, counts = np.unique(cells, axis=0, return_counts=True)
    dense = keys[counts >= np.median(counts)]
    corners = np.array([[0, 0], [1, 0], [0, 1], [1, 1]])
    return _hull(((dense[:, None, :] + corners[None]) * cell_m).reshape(-1, 2))


def polygon_area(poly: np.ndarray) -> float:
    """Area (m^2) of a simple polygon (K, 2), shoelace formula."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def entry_footprint(store: MapStore, entry: MapEntry, points: np.ndarray | None = None,
                    buffer_m: float = 5.0) -> np.ndarray:
    """The footprint (K, 2) of one block or tile, map frame xy, metres (see the module docstring).
    ``points``: the entry's points (N, 3), needed only for a block without keyframes."""
    if store.kind == "grid":
        from blockloc.maps.grid_tiles import tile_bounds

        s = float(store.params["tile_size_m"])
        lo, _ = tile_bounds(entry.id, s)
        return np.asarray(lo, float) + s * np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    if entry.keyframes is not None and len(entry.keyframes):
        return buffered_hull(entry.keyframes[:, :2], buffer_m)
    if points is not None and len(points):
        size = float(store.params.get("block_size_m") or 40.0)
        return dense_cells_hull(np.asarray(points)[:, :2], max(size / 10.0, 1.0))
    return buffered_hull(entry.centroid[None, :2], buffer_m)


def map_figure(store: MapStore, trajectory=None, max_points: int = 200_000, title: str | None = None,
               buffer_m: float = 5.0):
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
        poly = entry_footprint(store, e, pts, buffer_m)
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
        handles.append(Patch(facecolor="none", edgecolor="none",
                             label=f"footprint: keyframe hull + {buffer_m:g} m"))
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
