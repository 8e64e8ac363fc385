"""Open a ``--seq`` value as a Sequence (names and paths: see :mod:`blockloc.datasets.refs`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from blockloc.datasets.base import Sequence
from blockloc.datasets.refs import SequenceRef


def open_sequence(name_or_path: str | Path, *, data_root: str | Path | None = None,
                  dataset_cfg: Any = None, lidar_topic: str | None = None,
                  imu_topic: str | None = None, poses=None, poses_frame: str | None = None) -> Sequence:
    """Open a sequence by name or path.

    dataset_cfg: the dataset settings (range limits, hits use, topics, data root); explicit
    arguments override it. poses: a trajectory file (or Trajectory) that gives the sequence its
    ground truth and mapping poses. Raises DatasetError with one line naming the expected path
    when data are missing, or listing the known names for an unknown name.
    """
    return SequenceRef.parse(name_or_path).open(data_root=data_root, dataset_cfg=dataset_cfg,
                                                lidar_topic=lidar_topic, imu_topic=imu_topic,
                                                poses=poses, poses_frame=poses_frame)
