"""A synthetic run's report inputs (metrics, trajectories, diagnostics, map points, plots)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from blockloc.geometry import Trajectory
from tests.viz.synthetic import block_entries, make_run


def report_inputs(out: Path, *, with_gt: bool = True, with_images: bool = True) -> dict:
    from blockloc.evaluation.plots import plot_errors_over_time, plot_trajectories

    run = make_run(duration_s=21.0, scan_points=10, lost_frames=tuple(range(60, 72)), with_gt=with_gt)
    loc = run.localized
    rng = np.random.default_rng(5)
    est = Trajectory(np.array([e.stamp for e in loc]),
                     np.array([e.T_map_body for e in loc]))
    est.poses[:, :2, 3] += rng.normal(scale=0.05, size=(len(loc), 2))
    diagnostics = []
    for e in run.events:
        d = dict(e.diagnostics, index=e.index, stamp=e.stamp)
        if e.index in (90, 91):
            d["status"] = "rejected"
        diagnostics.append(d)
    # Map: points on the block walls and scattered "trees", as a top view would show them.
    walls = []
    for ent in block_entries():
        lo, hi = ent["bounds_min"], ent["bounds_max"]
        t = rng.uniform(0, 1, 3000)
        walls += [np.c_[lo[0] + 2 + (hi[0] - lo[0] - 4) * t, np.full(3000, lo[1] + 3)],
                  np.c_[np.full(3000, hi[0] - 3), lo[1] + 2 + (hi[1] - lo[1] - 4) * t]]
    walls.append(rng.uniform(-38, 38, size=(8000, 2)))
    map_xy = np.vstack(walls)
    images = {}
    if with_images and with_gt:
        gt = run.info.ground_truth
        G = gt.interpolate(est.stamps)
        err = np.linalg.norm(G[:, :3, 3] - est.positions, axis=1)
        images["trajectories"] = plot_trajectories(out / "trajectories.png", gt.positions[:, :2], est.positions[:, :2], err)
        images["errors"] = plot_errors_over_time(out / "errors.png", est.stamps, err, np.zeros_like(err))
    metrics = {"sequence": "synthetic:circle", "backend": "block", "map": "/maps/synthetic", "frames": len(run.events),
               "estimated": len(loc), "failures": 1, "recoveries": 1, "switches": 4, "update_ms_median": 22.4,
               "update_ms_p99": 25.0, "ate_trans_rmse_m": 0.071, "ate_trans_max_m": 0.19, "ate_rot_rmse_deg": 0.0,
               "init": {"mode": "gt"}, "map_stats": {"loads": 4, "cache_hits": 12}, "notes": ["matched 198 of 198"],
               "relocalizations": [{"stamp": 1007.2, "verified": True}], "duration_s": 21.0, "path_length_m": 126.0}
    return dict(metrics=metrics, estimate=est, ground_truth=run.info.ground_truth, diagnostics=diagnostics,
                config=run.info.config, map_xy=map_xy, map_entries=run.info.map_entries, images=images)
