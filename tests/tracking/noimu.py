"""A sequence with its IMU withheld: the LiDAR-only tests' view of a simulated session."""

from __future__ import annotations

import numpy as np

from blockloc.datasets.base import ImuData


class WithoutImu:
    """Wraps any ``Sequence``; everything passes through except ``imu()``, which is empty."""

    def __init__(self, seq) -> None:
        self._seq = seq
        self.info = seq.info

    def __len__(self) -> int:
        return len(self._seq)

    def __getattr__(self, name):
        return getattr(self._seq, name)

    def imu(self) -> ImuData:
        return ImuData(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
