"""Dynamic points: our remover, DUFOMap and the raw map on one sequence in the DynamicMap layout.

``run_dynamic_comparison(seq_dir, work_dir)`` reads the exported scans (``blockloc export
dynamicmap``) once, runs each method on exactly those scans, and scores every cleaned map against
``gt_cloud.pcd`` with the benchmark's definition (``blockloc.evaluation.dynamic_points``, 0.05 m
nearest-neighbour transfer). ``bench/dynamic.py`` is the command; ``bench/lifelong.py`` may call
this function for its ``--dynamic`` section.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

#: DUFOMap's published parameters (its paper and assets/config.toml): voxel 0.1 m, d_s 0.2 m, d_p 1.
DUFOMAP_PARAMS = {"resolution": 0.1, "d_s": 0.2, "d_p": 1}


def _timed(fn):
    """(result, wall s, CPU s of this process, all threads)."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w0, time.process_time() - c0


def _raw(scans, up):
    return [np.ones(len(p), bool) for p, _ in scans]


def _ours(scans, up, params=None):
    from blockloc.maps.dynamic_removal import DynamicParams, static_masks

    return static_masks([(T[:3, 3], p) for p, T in scans], range(len(scans)), params or DynamicParams(), up)


def _dufomap(scans, up, d_p=DUFOMAP_PARAMS["d_p"]):
    from dufomap import dufomap

    d = dufomap(DUFOMAP_PARAMS["resolution"], DUFOMAP_PARAMS["d_s"], d_p,
                num_threads=int(os.environ.get("BENCH_DUFOMAP_THREADS", "0")))
    for p, T in scans:  # points already in the world frame: no transform
        d.run(p, T, cloud_transform=False)
    d.oncePropagateCluster(if_propagate=True, if_cluster=False)  # its offline default: propagate, no clustering
    return [d.segment(p, T, cloud_transform=False) == 0 for p, T in scans]


def _dufomap_dp0(scans, up):
    return _dufomap(scans, up, d_p=0)


#: "DUFOMap d_p 0" is not its published setting: a sensitivity row. With d_p 1 a voxel counts as
#: free only when no unknown voxel is next to it; a 32-beam scan leaves unknown cells between its
#: rings beyond ~10 m, so far objects are never seen free (docs/dynamic_points.md).
METHODS = {"raw map": _raw, "blockloc (voxel evidence)": _ours, "DUFOMap": _dufomap,
           "DUFOMap d_p 0 (not its published setting)": _dufomap_dp0}
#: file names of the cleaned maps (``<slug>_output.pcd``, as the benchmark names method outputs)
SLUGS = {"raw map": "raw", "blockloc (voxel evidence)": "blockloc", "DUFOMap": "dufomap",
         "DUFOMap d_p 0 (not its published setting)": "dufomap_dp0"}


def run_dynamic_comparison(seq_dir: str | Path, work_dir: str | Path | None = None, *,
                           methods: tuple[str, ...] = tuple(METHODS), up=(0.0, 0.0, -1.0)) -> list[dict]:
    """One row per method: name, SA / DA / AA / HA (%), points kept, wall and CPU seconds.

    seq_dir: a DynamicMap folder with ``gt_cloud.pcd``. work_dir: where each cleaned map is
    written as ``<method>_output.pcd`` (None: not written). up: (3,) against gravity in the
    folder's world frame (blockloc's map frame for sim / NCLT exports: z down, so (0, 0, -1))."""
    from blockloc.datasets.dynamicmap import iter_scans, read_gt_cloud
    from blockloc.evaluation.dynamic_points import BENCHMARK_RADIUS_M, dynamic_scores

    scans = list(iter_scans(seq_dir))
    gt_pts, gt_dyn = read_gt_cloud(seq_dir)
    up = np.asarray(up, float)
    rows = []
    for name in methods:
        masks, wall, cpu = _timed(lambda: METHODS[name](scans, up))
        kept = np.concatenate([p[m] for (p, _), m in zip(scans, masks)])
        if work_dir is not None:
            from blockloc.datasets.pointclouds import write_point_cloud

            Path(work_dir).mkdir(parents=True, exist_ok=True)
            slug = SLUGS.get(name, name.split(" ")[0].lower())
            write_point_cloud(Path(work_dir) / f"{slug}_output.pcd", kept.astype(np.float32))
        s = dynamic_scores(gt_pts, gt_dyn, kept, BENCHMARK_RADIUS_M)
        rows.append({"method": name, **s.as_dict(), "kept_points": int(len(kept)),
                     "wall_s": wall, "cpu_s": cpu, "load1": os.getloadavg()[0]})
    return rows
