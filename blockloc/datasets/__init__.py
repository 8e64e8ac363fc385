"""Sequence sources: one protocol (``base.Sequence``) for NCLT sessions, ROS bags and simulations.

``open_sequence(name_or_path, ...)`` resolves ``--seq`` values (see ``registry``). Loaders live in
``nclt`` and ``rosbag``; heavy imports (rosbags, numba) happen only when a loader is used.
"""

from blockloc.datasets.base import ImuData, LidarFrame, Sequence, SequenceInfo
from blockloc.datasets.registry import known_names, open_sequence, resolve_data_root

__all__ = ["ImuData", "LidarFrame", "Sequence", "SequenceInfo", "known_names", "open_sequence",
           "resolve_data_root"]
