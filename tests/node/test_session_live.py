"""The Session hooks a live source uses: IMU fed as it arrives (extend_imu), a restart, and
global init of a frame handed over (reinitialize, exercised with the real session in test_node)."""

from __future__ import annotations

import numpy as np

from blockloc.datasets.base import ImuData, LidarFrame, SequenceInfo
from blockloc.node._assemble import LiveSequence
from blockloc.app.session import Session


class RecordingTracker:
    def __init__(self) -> None:
        self.fed: list[float] = []
        self.resets = 0
        self.initialized = True
        self.lidar_only = False

    def insert_imu(self, t, acc, gyro) -> None:
        self.fed.append(float(t))

    def insert_frame(self, frame):
        from blockloc.tracking.tracker import Diagnostics, Estimate

        return Estimate(frame.index, frame.stamp, np.eye(4), None, np.zeros(3), np.zeros(3), np.zeros(3), Diagnostics())

    def reset(self) -> None:
        self.resets += 1


class NoProvider:
    def close(self) -> None:
        pass


def imu(t):
    t = np.asarray(t, float)
    return t, np.tile([0.0, 0.0, 9.81], (len(t), 1)), np.zeros((len(t), 3))


def frame(i, stamp):
    return LidarFrame(i, stamp, np.zeros((10, 3)), time_offsets=np.linspace(0, 0.1, 10).astype(np.float32))


def test_imu_extended_live_is_fed_once_in_order_and_old_samples_let_go():
    tracker = RecordingTracker()
    s = Session(LiveSequence(SequenceInfo("live"), ImuData(*imu([0.0, 0.01]))), tracker, NoProvider())
    assert s.extend_imu(*imu(np.arange(0.02, 1.0, 0.01))) == 98
    assert s.extend_imu(*imu([0.5, 0.9])) == 0  # not after the last held
    s.step(frame(0, 0.5))  # feeds up to the sweep's end, 0.6
    assert tracker.fed == sorted(tracker.fed) and tracker.fed[-1] <= 0.6 + 1e-9 and len(tracker.fed) == 61
    s.extend_imu(*imu(np.arange(1.0, 5.0, 0.01)))
    s.step(frame(1, 4.0))
    assert len(set(tracker.fed)) == len(tracker.fed)  # no sample twice
    s.extend_imu(*imu([5.0]))
    # what was fed more than 2 s before the last fed sample is let go; the rest stays
    assert s.imu.t[0] >= 4.1 - 2.0 - 0.011 and s.imu.t[-1] == 5.0
    s.step(frame(2, 4.9))
    assert tracker.fed == sorted(set(tracker.fed)) and tracker.fed[-1] == 5.0


def test_restart_forgets_the_imu_and_resets_the_tracker():
    tracker = RecordingTracker()
    s = Session(LiveSequence(SequenceInfo("live"), ImuData(*imu([0.0, 0.01]))), tracker, NoProvider())
    s.extend_imu(*imu(np.arange(0.02, 1.0, 0.01)))
    s.step(frame(0, 0.5))
    s.restart_stream()
    assert tracker.resets == 1 and len(s.imu) == 0
    s.extend_imu(*imu([0.1, 0.2]))  # earlier stamps than before: accepted after the restart
    assert len(s.imu) == 2
