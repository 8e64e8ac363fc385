"""Top-down picture of a simulated world with its session routes (matplotlib, PNG)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

_COLORS = {"building": "#6b6b6b", "wall": "#b03020", "fence": "#8a6d3b", "pole": "#222222",
           "trunk": "#4a3000", "crown": "#2e8b3a", "car": "#1f5fbf", "bin": "#7f3fbf"}
_ROUTE_COLORS = ["#d62728", "#ff7f0e", "#9467bd", "#17becf"]


def render_world(preset: str, seed: int, out: str | Path, sessions: tuple[str, ...] | None = None,
                 dpi: int = 110) -> Path:
    """Draw the world from above (terrain height shaded, roads, objects, corridors) and the
    ground-truth routes of ``sessions`` (default: all of the preset); writes ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from blockloc.sim.presets import get_preset
    from blockloc.sim.stream import SimSequence, cached_world, scene_movables

    p = get_preset(preset)
    world = cached_world(p, int(seed))
    x0, x1, y0, y1 = world.extent
    sx, sy = p.size_m
    fig_w = 12.0
    fig, ax = plt.subplots(figsize=(fig_w, fig_w * sy / sx * 0.92 + 0.8))
    gx, gy = np.meshgrid(np.linspace(x0, x1, 300), np.linspace(y0, y1, 300))
    h = world.terrain.height(gx, gy)
    im = ax.imshow(h, extent=(x0, x1, y0, y1), origin="lower", cmap="YlGn_r", alpha=0.55)
    fig.colorbar(im, ax=ax, fraction=0.025, pad=0.01, label="terrain height (m)")
    for xr in world.roads.xs:
        ax.fill_betweenx([y0, y1], xr - world.roads.width_m / 2, xr + world.roads.width_m / 2,
                         color="#cfcfcf", lw=0, zorder=1)
    for yr in world.roads.ys:
        ax.fill_between([x0, x1], yr - world.roads.width_m / 2, yr + world.roads.width_m / 2,
                        color="#cfcfcf", lw=0, zorder=1)
    for c in world.cells:
        if c["type"] == "field":
            cx0, cx1, cy0, cy1 = c["rect"]
            ax.text((cx0 + cx1) / 2, (cy0 + cy1) / 2, "open field", ha="center", va="center",
                    fontsize=7, color="#555555", zorder=2)
    ms = 0.5 if sx > 500 else 2.0
    from matplotlib.collections import PolyCollection

    for name in ("building", "wall", "fence"):  # boxes: 8 vertices each, the first 4 at the bottom
        if name in world.meshes:
            V = world.meshes[name][0].reshape(-1, 8, 3)[:, :4, :2]
            ax.add_collection(PolyCollection(V, facecolors=_COLORS[name], edgecolors=_COLORS[name],
                                             linewidths=2.5 if name == "wall" else 0.6,
                                             zorder=3, label=name))
    if "crown" in world.meshes:
        from blockloc.sim.world import _ICO_V

        C = world.meshes["crown"][0].reshape(-1, len(_ICO_V), 3)
        ctr = C.mean(axis=1)
        r = np.abs(C[:, :, 0] - ctr[:, None, 0]).max(axis=1)
        from matplotlib.collections import EllipseCollection

        ax.add_collection(EllipseCollection(2 * r, 2 * r, 0, units="xy", offsets=ctr[:, :2],
                                            transOffset=ax.transData, facecolors=_COLORS["crown"],
                                            alpha=0.7, zorder=3))
        ax.scatter([], [], s=20, c=_COLORS["crown"], label="tree")
    if "pole" in world.meshes:
        P = world.meshes["pole"][0].reshape(-1, 17, 3).mean(axis=1)
        ax.scatter(P[:, 0], P[:, 1], s=ms * 2, c=_COLORS["pole"], lw=0, zorder=3, label="pole")
    mv = scene_movables(world, p.sessions[0], base=True)
    for kind in ("car", "bin"):
        sel = mv.kind == kind
        ax.scatter(mv.xy[sel, 0], mv.xy[sel, 1], s=ms * 3, c=_COLORS[kind], marker="s", lw=0,
                   zorder=3, label=f"{kind} (movable)")
    names = sessions or p.sessions
    for k, s in enumerate(names):
        seq = SimSequence(p, s, int(seed))
        traj = seq.trajectory
        xy = traj.samples[::10, 1:3]
        ax.plot(xy[:, 0], xy[:, 1], color=_ROUTE_COLORS[k % 4], lw=1.4 if k == 0 else 1.0,
                zorder=4 + k, alpha=0.9,
                label=f"{s}: {traj.path_length() / 1000:.2f} km, {traj.duration / 60:.1f} min")
        ax.plot(*xy[0], marker="o", color=_ROUTE_COLORS[k % 4], ms=6, zorder=8)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m, world frame z up; NCLT map: y and z flipped)")
    ax.set_ylabel("y north (m)")
    ax.set_title(f"blockloc sim '{p.name}' seed {seed}: {sx:.0f} m x {sy:.0f} m, "
                 f"{world.num_triangles() / 1000:.0f}k triangles; corridors in red")
    ax.legend(loc="upper right", fontsize=7, markerscale=4, framealpha=0.85)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.stem + ".tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    os.replace(tmp, out)
    return out
