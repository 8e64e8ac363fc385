"""The one place the node builds its tracking session: the same recipe ``blockloc track`` runs
(:meth:`blockloc.session.Session.from_config` on a map store), fed by a live source.

(The recipe is moving to ``blockloc/app/``; repoint :func:`build_session` there.)
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from blockloc.datasets.base import ImuData, LidarFrame, SequenceInfo


class LiveSequence:
    """A Sequence with no recorded frames: the node hands the session its scans one by one
    (``Session.step``) and its IMU samples as they arrive (``Session.extend_imu``).

    info: extrinsics and gravity (from /tf_static and the map); imu: the samples received before
    the session was made (none: LiDAR-only tracking, as ``track --no-imu``)."""

    def __init__(self, info: SequenceInfo, imu: ImuData) -> None:
        self.info = info
        self._imu = imu

    def __len__(self) -> int:
        return 0

    def frame_stamps(self) -> np.ndarray:
        return np.zeros(0)

    def frame(self, index: int) -> LidarFrame:
        raise IndexError(f"a live source has no recorded frame {index}")

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[LidarFrame]:
        return iter(())

    def imu(self) -> ImuData:
        return self._imu

    def ground_truth(self):
        return None

    def mapping_poses(self):
        return None


def open_store(map_path: str, cfg):
    """The map store at ``map_path`` with the config's remote options (as ``track`` opens it)."""
    from blockloc.maps.store import open_map_from_config

    return open_map_from_config(map_path, cfg.map)


def build_session(cfg, store, map_path: str, info: SequenceInfo, imu: ImuData, *, observers=(), out_dir=None):
    """The Session ``track`` would build for a sequence with ``info`` and ``imu`` in ``store``."""
    from blockloc.session import Session

    return Session.from_config(cfg, LiveSequence(info, imu), store, observers=observers, out_dir=out_dir,
                               facts={"map": str(map_path), "source": "live"})
