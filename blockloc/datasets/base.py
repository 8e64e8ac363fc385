"""Types every sequence source yields, and the Sequence protocol.

Frames (all transforms 4x4, ``T_a_b`` maps points from b to a):
- ``map``: the frame ground truth and prior maps live in (NCLT: its local frame, z down).
- ``body``: the frame ground truth poses describe (NCLT: robot body, x fwd, y right, z down).
- ``lidar``: the frame points are given in.  ``imu``: the frame IMU samples are given in.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator, Protocol, runtime_checkable

import numpy as np

from blockloc.geometry import Trajectory


@dataclass
class LidarFrame:
    """One LiDAR sweep.

    index: 0-based position of the frame in its sequence (time order).
    stamp: float seconds, the time the points are expressed at (per-point times are offsets from it).
    points: (N, 3) float32 or float64, lidar frame, metres; finite.
    intensity: (N,) float32 or None.
    time_offsets: (N,) float32 seconds relative to ``stamp`` (may be negative), or None if unknown.
    ring: (N,) uint16 laser/ring id, or None if unknown.
    num_nonfinite: points the loader dropped for a NaN/inf coordinate (counted by the session).
    """

    index: int
    stamp: float
    points: np.ndarray
    intensity: np.ndarray | None = None
    time_offsets: np.ndarray | None = None
    ring: np.ndarray | None = None
    num_nonfinite: int = 0

    def __len__(self) -> int:
        return len(self.points)

    def select(self, mask: np.ndarray) -> "LidarFrame":
        """A frame holding only the points where ``mask`` is True (or at the given indices)."""
        pick = lambda a: None if a is None else a[mask]  # noqa: E731
        return LidarFrame(self.index, self.stamp, self.points[mask], pick(self.intensity),
                          pick(self.time_offsets), pick(self.ring), self.num_nonfinite)


@dataclass
class ImuData:
    """IMU samples, time-ordered, in the imu frame.

    t: (M,) float64 seconds, strictly increasing.
    acc: (M, 3) float64 specific force, m/s^2 (at rest it reads minus gravity).
    gyro: (M, 3) float64 angular rate, rad/s.
    """

    t: np.ndarray
    acc: np.ndarray
    gyro: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    def between(self, t0: float, t1: float) -> "ImuData":
        """Samples with t0 <= t < t1."""
        i0, i1 = np.searchsorted(self.t, [t0, t1], side="left")
        return ImuData(self.t[i0:i1], self.acc[i0:i1], self.gyro[i0:i1])


@dataclass
class SequenceInfo:
    """Static facts about a sequence.

    T_body_lidar, T_body_imu: (4, 4) extrinsics.
    gravity_map: (3,) gravity vector in the map frame, m/s^2 (NCLT, z down: (0, 0, +9.81)).
    lidar_rate_hz: scans a second (a recording's median stamp spacing); 0: unknown (a live source,
    whose gap check learns the period from the stamps).
    """

    name: str
    T_body_lidar: np.ndarray = field(default_factory=lambda: np.eye(4))
    T_body_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    gravity_map: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    lidar_rate_hz: float = 10.0
    imu_rate_hz: float = 100.0

    @property
    def T_imu_lidar(self) -> np.ndarray:
        from blockloc.geometry import inv_T

        return inv_T(self.T_body_imu) @ self.T_body_lidar


@runtime_checkable
class Sequence(Protocol):
    """What every source (NCLT directory, ROS bag, streamed simulation) provides."""

    info: SequenceInfo

    def __len__(self) -> int:
        """Number of LiDAR frames."""

    def frame_stamps(self) -> np.ndarray:
        """(F,) float64 stamps of all frames, time order, without loading points."""

    def frame(self, index: int) -> LidarFrame:
        """The index-th frame (0-based, time order)."""

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[LidarFrame]:
        """Frames start..stop-1 in time order."""

    def imu(self) -> ImuData:
        """All IMU samples of the sequence."""

    def ground_truth(self) -> Trajectory | None:
        """T_map_body poses, or None when the sequence has none."""

    def mapping_poses(self) -> Trajectory | None:
        """T_map_body poses maps are built from: offline-SLAM poses when present, else ground truth."""


def frame_index(index: int, n: int) -> int:
    """``index`` (negative counts from the end) as 0..n-1 of ``n`` frames; IndexError naming both
    when it is out of range."""
    if not -n <= index < n:
        raise IndexError(f"frame {index} out of range for {n} frames")
    return index % n


class FramesByIndex:
    """``frames(start, stop)`` as ``frame(i)`` for each i: the loaders that read a frame at a time."""

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[LidarFrame]:
        stop = len(self) if stop is None else min(stop, len(self))
        for i in range(start, stop):
            yield self.frame(i)


class SequenceView:
    """A sequence seen through a wrapper: ``info``, ``len`` and every attribute are the wrapped
    sequence's (``inner``) unless a subclass changes them."""

    def __init__(self, seq) -> None:
        self.inner = seq
        self.info = seq.info

    def __len__(self) -> int:
        return len(self.inner)

    def __getattr__(self, name):
        if name == "inner" or name.startswith("__"):  # not set yet (unpickling), or a dunder
            raise AttributeError(name)
        return getattr(self.inner, name)


class RangeLimited(SequenceView):
    """A sequence whose frames keep only points with range in [min_range_m, max_range_m] (lidar
    frame), as the NCLT and bag loaders do while reading: for sources that return every point
    (a streamed simulation, whose vehicle-body hits lie within ~1.5 m). Everything else passes
    through."""

    def __init__(self, seq, min_range_m: float, max_range_m: float) -> None:
        super().__init__(seq)
        self.min_range_m, self.max_range_m = float(min_range_m), float(max_range_m)

    def _limit(self, frame: LidarFrame) -> LidarFrame:
        r2 = np.einsum("ij,ij->i", frame.points, frame.points)
        return frame.select((r2 >= self.min_range_m**2) & (r2 <= self.max_range_m**2))

    def frame(self, index: int) -> LidarFrame:
        return self._limit(self.inner.frame(index))

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[LidarFrame]:
        for frame in self.inner.frames(start, stop):
            yield self._limit(frame)


class RemountedSequence(SequenceView):
    """A sequence seen with another ``T_body_lidar`` (4, 4): a mounting estimated when its map was
    built (:mod:`blockloc.maps.mounting`); everything else is the wrapped sequence's."""

    def __init__(self, seq, T_body_lidar: np.ndarray) -> None:
        import dataclasses

        super().__init__(seq)
        self.info = dataclasses.replace(seq.info, T_body_lidar=np.asarray(T_body_lidar, np.float64))
