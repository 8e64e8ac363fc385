"""Sequence sources: one protocol (``base.Sequence``) for NCLT sessions, ROS bags and simulations.

``open_sequence(name_or_path, ...)`` opens ``--seq`` values, parsed once by ``refs.SequenceRef``. Loaders live in
``nclt`` and ``rosbag``; heavy imports (rosbags, numba) happen only when a loader is used.
"""

from blockloc.datasets.base import ImuData, LidarFrame, Sequence, SequenceInfo
from blockloc.datasets.refs import SequenceRef, known_names, resolve_data_root
from blockloc.datasets.registry import open_sequence

__all__ = ["ImuData", "LidarFrame", "Sequence", "SequenceInfo", "SequenceRef", "known_names", "open_sequence",
           "resolve_data_root"]
