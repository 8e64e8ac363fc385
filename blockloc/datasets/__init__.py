"""Sequence sources: one protocol (``base.Sequence``) for NCLT sessions, ROS bags, scan folders
and simulations.

Loaders live in ``nclt``, ``rosbag`` and ``scanfolder``; heavy imports (rosbags, numba) happen only
when a loader is used. Which loader a ``--seq`` value names is the catalogue's job
(:mod:`blockloc.app.catalog`: ``open_sequence``, ``SequenceRef``).
"""

from blockloc.datasets.base import ImuData, LidarFrame, Sequence, SequenceInfo

__all__ = ["ImuData", "LidarFrame", "Sequence", "SequenceInfo"]
