"""Any sequence with poses from a trajectory file: ``with_trajectory(seq, "fastlio.tum")``.

A user's SLAM system (FAST-LIO, LIO-SAM, GLIM, ...) leaves a trajectory file beside the
recording; :func:`with_trajectory` wraps a sequence (a ROS bag, an NCLT session, a scan folder)
so that its ``ground_truth()`` and ``mapping_poses()`` come from that file. The poses are
``T_map_body`` in the trajectory's own frame, which becomes the map frame; its name travels in
``seq.info.map_frame`` (a :class:`TrajectoryInfo`) so map building can record it in the
manifest.

Matching (:func:`match_trajectory`):
- a trajectory without stamps (KITTI without a times file) is paired with the frames by index,
  which needs equal counts;
- a timed trajectory is interpolated at the frames' stamps (a scan folder pairs by index when
  the counts match, see ``scanfolder``);
- a frame the trajectory does not cover is *uncovered*: its stamp lies more than
  ``POSE_TIME_TOLERANCE_S`` outside the trajectory's time range, or inside a gap between two
  poses longer than ``max_gap_s`` (default: 5 x the trajectory's median pose spacing, at least
  1 s). Uncovered frames are named in one warning and listed by ``uncovered_frames()``; map
  building skips them (poses are never extrapolated).
- counts that differ without usable stamps, or stamps that do not overlap at all, raise one
  DatasetError line naming both sources, both counts and both stamp ranges.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Iterator

import numpy as np

from blockloc.datasets.base import ImuData, LidarFrame, SequenceInfo
from blockloc.errors import DatasetError
from blockloc.geometry import Trajectory
from blockloc.trajectory_io import TrajectoryFile, read_trajectory_file
# A frame this far outside the trajectory's time range is still covered (the end pose is held,
# not extrapolated): map building's own tolerance.

log = logging.getLogger(__name__)

# Frames further than this from a trajectory's time range are not given poses (no extrapolation).
POSE_TIME_TOLERANCE_S = 0.05

#: Default gap rule: a gap between poses longer than this many median spacings (and than
#: MIN_GAP_S) leaves the frames inside it uncovered.
GAP_FACTOR = 5.0
MIN_GAP_S = 1.0
#: Names of uncovered frames listed in a warning before "and N more".
_LIST_AT_MOST = 8


@dataclass
class TrajectoryInfo(SequenceInfo):
    """SequenceInfo of a sequence whose poses come from a trajectory file.

    map_frame: name of the trajectory's frame (= the map frame of maps built from it).
    trajectory_source: the trajectory file (or a description), for messages and metadata.
    """

    map_frame: str = "map"
    trajectory_source: str | None = None


def info_with_frame(info: SequenceInfo, map_frame: str, source: str | None) -> TrajectoryInfo:
    """A TrajectoryInfo holding every field of ``info`` plus the trajectory's frame and source."""
    base = {f.name: getattr(info, f.name) for f in fields(SequenceInfo)}
    return TrajectoryInfo(**base, map_frame=map_frame, trajectory_source=source)


def load_trajectory(traj, *, what: str = "trajectory"):
    """A path, :class:`~blockloc.geometry.Trajectory` or ``TrajectoryFile`` -> (Trajectory,
    timed, label). Files are read by ``blockloc.trajectory_io`` (TUM, KITTI, NCLT csv,
    sniffed); ``timed`` is False for a KITTI file without times."""
    if isinstance(traj, Trajectory):
        return traj, True, f"<{what}>"
    if isinstance(traj, TrajectoryFile):
        return traj.trajectory, traj.timed, str(traj.path)
    tf = read_trajectory_file(Path(traj))
    return tf.trajectory, tf.timed, str(tf.path)


def stamp_range(stamps: np.ndarray | None) -> str:
    """'[t0, t1] s' of stamps (3 decimals), or 'no stamps'."""
    if stamps is None or len(stamps) == 0:
        return "no stamps"
    return f"[{float(np.min(stamps)):.3f}, {float(np.max(stamps)):.3f}] s"


@dataclass
class TrajectoryMatch:
    """How a trajectory was matched to a sequence's frames.

    trajectory: T_map_body poses to use (restamped to the frame stamps when ``by_index``).
    uncovered: (K,) int64 frame indices the trajectory does not cover (mapping skips them).
    by_index: pose i was paired with frame i.
    """

    trajectory: Trajectory
    uncovered: np.ndarray
    by_index: bool


def covered_mask(stamps: np.ndarray, traj: Trajectory, *, tolerance_s: float = POSE_TIME_TOLERANCE_S,
                 max_gap_s: float | None = None) -> np.ndarray:
    """(F,) bool: which stamps (F,) the trajectory covers (see the module docstring)."""
    t = np.asarray(stamps, np.float64)
    ts = traj.stamps
    inside = (t >= ts[0] - tolerance_s) & (t <= ts[-1] + tolerance_s)
    if len(ts) < 2:
        return inside
    spacing = np.diff(ts)
    if max_gap_s is None:
        max_gap_s = max(GAP_FACTOR * float(np.median(spacing)), MIN_GAP_S)
    j = np.clip(np.searchsorted(ts, t, side="right"), 1, len(ts) - 1)
    on_pose = (np.abs(t - ts[j - 1]) <= 1e-9) | (np.abs(t - ts[j]) <= 1e-9)
    in_gap = (t > ts[0]) & (t < ts[-1]) & (spacing[j - 1] > max_gap_s) & ~on_pose
    return inside & ~in_gap


def match_trajectory(frame_stamps: np.ndarray | None, traj: Trajectory, *, timed: bool = True,
                     num_frames: int | None = None, pair_equal_counts: bool = False,
                     traj_name: str = "trajectory", seq_name: str = "sequence",
                     max_gap_s: float | None = None) -> TrajectoryMatch:
    """Match a trajectory (T_map_body) to frames with stamps (F,) (None: stamps unknown, then
    ``num_frames`` gives F).

    Pairs by index when the trajectory is untimed or the stamps are unknown (counts must be
    equal), or when ``pair_equal_counts`` and the counts are equal; otherwise interpolates by
    time. Raises DatasetError (one line: both names, both counts, both stamp ranges) when the
    two cannot be matched.
    """
    n_pose = len(traj)
    n_frame = num_frames if frame_stamps is None else len(frame_stamps)
    if n_pose == 0:
        raise DatasetError(f"{traj_name}: no poses, expected one or more to match the frames of "
                           f"{seq_name}")

    def cannot(why: str) -> DatasetError:
        frames = "unknown stamps" if frame_stamps is None else stamp_range(frame_stamps)
        poses = stamp_range(traj.stamps) if timed else "no stamps"
        return DatasetError(f"{traj_name}: {n_pose} poses ({poses}) cannot be matched to the "
                            f"{n_frame if n_frame is not None else '?'} scans of {seq_name} "
                            f"({frames}): {why}")

    by_index = (not timed) or frame_stamps is None or (pair_equal_counts and n_pose == n_frame)
    if by_index:
        if n_frame is None:
            raise cannot("the scans have no stamps")
        if n_pose != n_frame:
            raise cannot("counts differ and " + ("the poses have no stamps (a times file?)"
                                                 if not timed else "the scans have no stamps"))
        if frame_stamps is None:  # the scans take the poses' stamps
            return TrajectoryMatch(traj, np.zeros(0, np.int64), True)
        stamps = np.asarray(frame_stamps, np.float64)
        if timed:
            diff = float(np.max(np.abs(stamps - traj.stamps)))
            if diff > POSE_TIME_TOLERANCE_S:
                log.warning("%s: pose i paired with scan i of %s (equal counts); their stamps "
                            "differ by up to %.3f s", traj_name, seq_name, diff)
        return TrajectoryMatch(Trajectory(stamps, traj.poses), np.zeros(0, np.int64), True)
    stamps = np.asarray(frame_stamps, np.float64)
    covered = covered_mask(stamps, traj, max_gap_s=max_gap_s)
    if not covered.any():
        raise cannot("no scan stamp lies within the poses' time range")
    return TrajectoryMatch(traj, np.flatnonzero(~covered).astype(np.int64), False)


def warn_uncovered(uncovered: np.ndarray, names, traj_name: str, traj: Trajectory) -> None:
    """One warning naming the frames (``names[i]`` for frame i) a trajectory does not cover."""
    if len(uncovered) == 0:
        return
    listed = ", ".join(str(names[int(i)]) for i in uncovered[:_LIST_AT_MOST])
    more = f" and {len(uncovered) - _LIST_AT_MOST} more" if len(uncovered) > _LIST_AT_MOST else ""
    log.warning("%s (%s) does not cover %d scan(s): %s%s; they are skipped for mapping "
                "(poses are not extrapolated)", traj_name, stamp_range(traj.stamps),
                len(uncovered), listed, more)


class TrajectorySequence:
    """A sequence whose ``ground_truth()`` and ``mapping_poses()`` come from a trajectory.

    Frames, stamps and IMU are the wrapped sequence's; other attributes (``path``, ``close``)
    are passed through. ``uncovered_frames()``: frame indices the trajectory does not cover.
    """

    def __init__(self, seq, traj, *, frame_name: str | None = None,
                 max_gap_s: float | None = None):
        self.inner = seq
        trajectory, timed, label = load_trajectory(traj)
        inner_name = seq.info.name
        self._match = match_trajectory(np.asarray(seq.frame_stamps(), np.float64), trajectory,
                                       timed=timed, traj_name=label, seq_name=inner_name,
                                       max_gap_s=max_gap_s)
        self.info = info_with_frame(seq.info, frame_name or "map", label)
        warn_uncovered(self._match.uncovered, [f"frame {i}" for i in range(len(seq))], label,
                       self._match.trajectory)

    def __len__(self) -> int:
        return len(self.inner)

    def frame_stamps(self) -> np.ndarray:
        return self.inner.frame_stamps()

    def frame(self, index: int) -> LidarFrame:
        return self.inner.frame(index)

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[LidarFrame]:
        return self.inner.frames(start, stop)

    def imu(self) -> ImuData:
        return self.inner.imu()

    def ground_truth(self) -> Trajectory:
        return self._match.trajectory

    def mapping_poses(self) -> Trajectory:
        return self._match.trajectory

    def uncovered_frames(self) -> np.ndarray:
        """(K,) int64 indices of frames the trajectory does not cover (skip them for mapping)."""
        return self._match.uncovered.copy()

    def __getattr__(self, name):
        # only called for attributes not found here: the wrapped sequence's (path, close, ...)
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)


def with_trajectory(seq, traj, frame_name: str | None = None, *, max_gap_s: float | None = None):
    """``seq`` (any Sequence) with ground truth and mapping poses from ``traj``.

    traj: a trajectory file path (TUM, KITTI with or without times, NCLT csv), a
    :class:`~blockloc.geometry.Trajectory` or a ``TrajectoryFile``; poses T_map_body of the
    sequence's body frame. frame_name: the trajectory's frame, recorded as ``info.map_frame``
    (default "map"; for a scan folder, its extrinsics.yaml ``map_frame`` if set). A sequence
    with a ``with_poses`` method (a scan folder) is reopened with these poses (so equal counts
    pair by index); any other sequence is wrapped in a :class:`TrajectorySequence` (poses
    interpolated at its frame stamps).
    """
    if isinstance(seq, TrajectorySequence):
        seq = seq.inner
    if hasattr(seq, "with_poses"):  # a sequence that reopens itself with poses (a scan folder)
        return seq.with_poses(traj, frame_name=frame_name, max_gap_s=max_gap_s)
    return TrajectorySequence(seq, traj, frame_name=frame_name, max_gap_s=max_gap_s)
