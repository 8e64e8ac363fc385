"""The one place the node builds its tracking session: the same recipe ``blockloc track`` runs
(:func:`blockloc.app.assemble.build_session` on a store opened by
:func:`blockloc.app.assemble.open_store`, as :func:`blockloc.app.runs.open_session` does), fed
by a live source; and the gravity of a map the node has no sequence for.
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
    from blockloc.app.assemble import open_store as open_map_store

    return open_map_store(map_path, cfg.map)


def check_backend(store, cfg, backend: str | None = None) -> None:
    """MapError unless the map policy ``backend`` (default ``map.backend``) can serve ``store``:
    checked when the node starts, as ``track`` does before its first frame (the node builds its
    session on the first scan)."""
    from blockloc.app.assemble import check_backend as check

    check(store, backend or cfg.map.backend, cfg.map)


def build_session(cfg, store, map_path: str, info: SequenceInfo, imu: ImuData, *, backend: str | None = None,
                  observers=(), out_dir=None):
    """The Session ``track`` would build for a sequence with ``info`` and ``imu`` in ``store``
    (map policy ``backend``, default ``map.backend``)."""
    from blockloc.app.assemble import build_session as build

    return build(cfg, LiveSequence(info, imu), store, backend=backend, observers=observers, out_dir=out_dir,
                 facts={"map": str(map_path), "source": "live"})


def map_gravity(store) -> np.ndarray | None:
    """Gravity (3,) in the map frame, m/s^2, of a map store: the one its place index was built
    for, else that of the sequence the map was built from (its manifest's ``sequence``), else
    None (unknown)."""
    from blockloc.app.catalog import open_sequence
    from blockloc.errors import BlocklocError
    from blockloc.global_init.place_index import PLACE_INDEX_NAME, PlaceIndex

    if store.has_extra(PLACE_INDEX_NAME):
        return np.asarray(PlaceIndex.from_bytes(store.load_extra(PLACE_INDEX_NAME)).gravity_map, float)
    from blockloc.app.runs import mapping_sequence

    source = mapping_sequence(store.params)
    if source:
        try:
            return np.asarray(open_sequence(str(source)).info.gravity_map, float)
        except BlocklocError:
            pass
    return None
