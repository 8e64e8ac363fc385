"""A kidnapped robot: two stretches of one session spliced as if the second followed the first.

At the splice the robot jumps (teleports) to where the second stretch starts; the IMU, the clock
and the frame indices run on as if nothing happened. Ground truth follows the jump.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Iterator

import numpy as np

from blockloc.datasets.base import ImuData, LidarFrame
from blockloc.geometry import Trajectory


class SplicedSequence:
    """Frames ``first`` = (a0, a1) of ``seq``, then frames ``second`` = (b0, b1) shifted back in time
    so that b0 comes one frame period after a1 - 1. A ``Sequence`` (see ``blockloc.datasets.base``)."""

    def __init__(self, seq, first: tuple[int, int], second: tuple[int, int]):
        self.seq = seq
        self.first, self.second = first, second
        stamps = np.asarray(seq.frame_stamps(), float)
        period = float(np.median(np.diff(stamps)))
        # Second-stretch times minus shift_s are the spliced times.
        self.shift_s = float(stamps[second[0]] - (stamps[first[1] - 1] + period))
        self.splice_stamp = float(stamps[second[0]] - self.shift_s)
        self.splice_index = first[1] - first[0]
        self._map = [(i, 0.0) for i in range(*first)] + [(i, self.shift_s) for i in range(*second)]
        self._stamps = np.array([stamps[i] - s for i, s in self._map])
        self.info = replace(seq.info, name=f"{seq.info.name}[{first[0]}:{first[1]}+{second[0]}:{second[1]}]")

    def __len__(self) -> int:
        return len(self._map)

    def frame_stamps(self) -> np.ndarray:
        return self._stamps.copy()

    def frame(self, index: int) -> LidarFrame:
        i, shift = self._map[index]
        f = self.seq.frame(i)
        return LidarFrame(index, f.stamp - shift, f.points, f.intensity, f.time_offsets, f.ring)

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[LidarFrame]:
        for k in range(start, len(self) if stop is None else min(stop, len(self))):
            yield self.frame(k)

    def imu(self) -> ImuData:
        imu = self.seq.imu()
        stamps = np.asarray(self.seq.frame_stamps(), float)
        a = imu.between(stamps[self.first[0]] - 1.0, self.splice_stamp)
        b = imu.between(self.splice_stamp + self.shift_s, stamps[self.second[1] - 1] + 1.0)
        return ImuData(np.concatenate([a.t, b.t - self.shift_s]), np.concatenate([a.acc, b.acc]),
                       np.concatenate([a.gyro, b.gyro]))

    def ground_truth(self) -> Trajectory:
        gt = self.seq.ground_truth()
        stamps = np.asarray(self.seq.frame_stamps(), float)
        in_a = (gt.stamps >= stamps[self.first[0]] - 1.0) & (gt.stamps < self.splice_stamp)
        in_b = (gt.stamps >= self.splice_stamp + self.shift_s) & (gt.stamps <= stamps[self.second[1] - 1] + 1.0)
        return Trajectory(np.concatenate([gt.stamps[in_a], gt.stamps[in_b] - self.shift_s]),
                          np.concatenate([gt.poses[in_a], gt.poses[in_b]]))

    def mapping_poses(self) -> Trajectory | None:
        return None
