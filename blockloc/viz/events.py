"""What a tracking run tells its observers: one :class:`RunInfo`, a :class:`FrameEvent` per frame, metrics.

The session engine calls ``observer.start(info)`` once, ``observer.frame(event)`` for every frame
(localized or not) and ``observer.finish(metrics)`` at the end, also after an exception mid-run.
Observers (:class:`blockloc.viz.mcap_recorder.McapRecorder`, :class:`blockloc.viz.live.LiveServer`)
only read the events; the arrays they hold must not be modified by the observer.

Frames: ``map`` (the prior map's frame), ``body`` (the frame ground truth and ``poses.tum``
describe; ``base_link`` in the ROS messages), ``lidar``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, Sequence, runtime_checkable

import numpy as np

from blockloc.errors import BlocklocError, OutputWriteError

if TYPE_CHECKING:
    from blockloc.geometry import Trajectory

log = logging.getLogger(__name__)

class VizError(BlocklocError):
    """A recording, live view, layout or report cannot be written (bad path, port in use, bad input)."""


STATUSES = ("ok", "rejected", "imu_only", "lost", "recovered", "uninitialized", "skipped")


@dataclass
class RunInfo:
    """The run's fixed facts, given once before the first frame.

    sequence: a readable name, e.g. ``"sim:small/loc"``. T_body_lidar: (4, 4) lidar -> body.
    map_kind: ``"block"`` or ``"grid"``. map_entries: one dict per block/tile with ``id`` (str),
    ``bounds_min``/``bounds_max``/``centroid`` ((3,) map frame, metres) and ``footprint``
    ((K, 2) closed-or-open polygon in map x/y, metres, or None: then the bounds' rectangle is drawn).
    tile_size_m: the tile edge of a grid map, else None. ground_truth: ``T_map_body`` over time or
    None. config: the config actually used, as a plain dict. out_dir: the results folder or None.
    """

    sequence: str
    T_body_lidar: np.ndarray
    map_kind: str
    map_entries: list[dict]
    tile_size_m: float | None = None
    ground_truth: "Trajectory | None" = None
    config: dict = field(default_factory=dict)
    out_dir: Path | None = None


@dataclass
class FrameEvent:
    """One frame's outcome.

    index: frame index in the sequence. stamp: sensor time of the scan, seconds.
    T_map_body: (4, 4) or None when not localized (``uninitialized`` / ``lost``).
    covariance: (6, 6) marginal covariance of T_map_body in GTSAM's Pose3 tangent order
    (rotation rad, translation m), body frame, right perturbation ``T = T_hat * Exp(xi)``; or None.
    velocity_map: (3,) m/s, map frame. status: one of :data:`STATUSES`.
    diagnostics: flat dict of plain values (fitness, window_size, switched, block_id, update_ms,
    registration_ms, smoother_ms, map_ms, deskew_ms, num_points, ...).
    scan_lidar: (N, 3) float32, the deskewed registration input in the lidar frame, or None.
    local_map_points: (M, 3) float32 map frame, only on frames where the served local map changed.
    local_map_id: the served region's name. active_entries: ids of the served blocks/tiles.
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
    """Receives a run as it happens. ``finish`` also closes files/servers and must be safe to call
    after an exception mid-run (and more than once)."""

    def start(self, info: RunInfo) -> None: ...

    def frame(self, event: FrameEvent) -> None: ...

    def finish(self, metrics: dict) -> None: ...


class ObserverGroup:
    """Several observers as one: each call goes to every member in order.

    A member that raises in ``frame`` is logged and dropped for the rest of the run (a broken
    viewer must not stop tracking); ``finish`` reaches every member, even one dropped earlier, so
    its files are closed.
    """

    def __init__(self, observers: Sequence[RunObserver]) -> None:
        self.observers = list(observers)
        self._active = list(self.observers)

    def start(self, info: RunInfo) -> None:
        for obs in self.observers:
            obs.start(info)

    def frame(self, event: FrameEvent) -> None:
        for obs in list(self._active):
            try:
                obs.frame(event)
            except OutputWriteError:  # the results cannot be written: the run stops (whole rows kept)
                raise
            except Exception:
                log.exception("observer %s failed on frame %d; it gets no more frames",
                              type(obs).__name__, event.index)
                self._active.remove(obs)

    def finish(self, metrics: dict) -> None:
        errors = []
        for obs in self.observers:
            try:
                obs.finish(metrics)
            except Exception as exc:  # finish every member before reporting
                if isinstance(exc, (OSError, BlocklocError)):  # a file it could not write: one line
                    log.error("observer %s could not finish: %s", type(obs).__name__, exc)
                else:
                    log.exception("observer %s failed to finish", type(obs).__name__)
                errors.append(exc)
        if errors:
            raise errors[0]
