"""The events a tracking session emits, and the observer protocol that receives them.

A :class:`~blockloc.session.Session` calls ``start(RunInfo)`` once, ``frame(FrameEvent)`` after
every scan, and ``finish(metrics)`` at the end (also after an error or an interruption, so
observers close their files with what they have).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass
class RunInfo:
    """Static facts about a run.

    sequence: its name (e.g. ``sim:small/loc``). T_body_lidar: (4, 4). map_kind: block | grid.
    map_entries: per block/tile ``{"id", "bounds_min" (3,), "bounds_max" (3,), "centroid" (3,),
    "footprint" (K, 2) or None}``, map frame, metres. tile_size_m: grid maps, else None.
    ground_truth: T_map_body Trajectory or None. config: the config used (plain dict).
    out_dir: the results directory or None.
    """

    sequence: str
    T_body_lidar: np.ndarray
    map_kind: str
    map_entries: list[dict]
    tile_size_m: float | None
    ground_truth: object | None
    config: dict
    out_dir: Path | None


@dataclass
class FrameEvent:
    """One processed scan.

    stamp: sensor time, s. T_map_body: (4, 4), None while not localized (uninitialized, lost).
    covariance: (6, 6) of T_map_body in the Pose3 tangent (rotation rad, translation m; right
    perturbation, body frame), or None. velocity_map: (3,) m/s. status: ok | rejected | imu_only
    | lost | recovered | uninitialized | skipped. diagnostics: the tracker's per-frame fields.
    scan_lidar: (N, 3) float32 deskewed registration input, lidar frame, or None.
    local_map_points: (M, 3) float32 map frame, only on frames where the served local map
    changed (else None). local_map_id: region name. active_entries: ids of the served entries.
    """

    index: int
    stamp: float
    T_map_body: np.ndarray | None
    covariance: np.ndarray | None
    velocity_map: np.ndarray
    status: str
    diagnostics: dict
    scan_lidar: np.ndarray | None = None
    local_map_points: np.ndarray | None = None
    local_map_id: str | None = None
    active_entries: tuple = ()


@runtime_checkable
class RunObserver(Protocol):
    """Receives a run's events (recorders, live views, the results writer)."""

    def start(self, info: RunInfo) -> None: ...

    def frame(self, event: FrameEvent) -> None: ...

    def finish(self, metrics: dict) -> None: ...
