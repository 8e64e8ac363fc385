"""A map store drawn from above: points coloured by entry, entry outlines, a trajectory."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from blockloc.errors import MapError
from blockloc.fileio import save_figure
from blockloc.maps.store import MapStore

log = logging.getLogger(__name__)


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
    return save_figure(fig, out, dpi=120)
