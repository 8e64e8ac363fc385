"""Dynamic-point removal scores: SA, DA, AA of a cleaned map against labelled ground truth.

The DynamicMap Benchmark's definition (KTH-RPL/DynamicMap_Benchmark, ``export_eval_pcd`` and
``evaluate_all.py``): the ground truth is every scan's points together, each labelled static or
dynamic. A method outputs a cleaned map (any points: it may downsample). Each ground-truth point
counts as **kept** when the nearest point of the cleaned map lies within ``radius_m`` of it
(the benchmark uses 0.05 m: half the 0.1 m voxel of the voxel methods), else **removed**. Then

- SA = static points kept / static points (%),
- DA = dynamic points removed / dynamic points (%),
- AA = sqrt(SA * DA), HA = 2 SA DA / (SA + DA).

Pure numpy / scipy on arrays in one frame (metres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The benchmark's distance under which a ground-truth point counts as kept (m).
BENCHMARK_RADIUS_M = 0.05


@dataclass(frozen=True)
class DynamicScores:
    """SA, DA, AA, HA in percent (nan when a class is empty) and the counts they come from."""

    sa: float
    da: float
    aa: float
    ha: float
    static_points: int
    dynamic_points: int
    static_kept: int
    dynamic_removed: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def kept_mask(gt_points: np.ndarray, cleaned_points: np.ndarray, radius_m: float = BENCHMARK_RADIUS_M) -> np.ndarray:
    """(N,) bool: ground-truth points (N, 3) whose nearest cleaned-map point (M, 3) lies within
    ``radius_m`` (the benchmark's nearest-neighbour label transfer). An empty map keeps nothing."""
    from scipy.spatial import cKDTree

    gt = np.asarray(gt_points, np.float64).reshape(-1, 3)
    cl = np.asarray(cleaned_points, np.float64).reshape(-1, 3)
    if not len(cl) or not len(gt):
        return np.zeros(len(gt), bool)
    dist, _ = cKDTree(cl).query(gt, k=1, distance_upper_bound=radius_m * (1 + 1e-9), workers=-1)
    return dist <= radius_m


def scores_from_mask(gt_dynamic: np.ndarray, kept: np.ndarray) -> DynamicScores:
    """Scores from (N,) bool ground truth (True = dynamic) and (N,) bool kept."""
    dyn = np.asarray(gt_dynamic, bool).reshape(-1)
    kept = np.asarray(kept, bool).reshape(-1)
    if len(dyn) != len(kept):
        raise ValueError(f"{len(dyn)} labels for {len(kept)} kept flags")
    n_static, n_dynamic = int((~dyn).sum()), int(dyn.sum())
    static_kept = int((~dyn & kept).sum())
    dynamic_removed = int((dyn & ~kept).sum())
    sa = 100.0 * static_kept / n_static if n_static else math.nan
    da = 100.0 * dynamic_removed / n_dynamic if n_dynamic else math.nan
    aa = math.sqrt(sa * da) if n_static and n_dynamic else math.nan
    ha = 2 * sa * da / (sa + da) if n_static and n_dynamic and sa + da > 0 else math.nan
    return DynamicScores(sa, da, aa, ha, n_static, n_dynamic, static_kept, dynamic_removed)


def dynamic_scores(gt_points: np.ndarray, gt_dynamic: np.ndarray, cleaned_points: np.ndarray,
                   radius_m: float = BENCHMARK_RADIUS_M) -> DynamicScores:
    """SA / DA / AA of ``cleaned_points`` (M, 3) against ``gt_points`` (N, 3) labelled
    ``gt_dynamic`` (N,) bool, nearest-neighbour transfer within ``radius_m`` (module docstring)."""
    return scores_from_mask(gt_dynamic, kept_mask(gt_points, cleaned_points, radius_m))
