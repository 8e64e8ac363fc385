"""A windowed scene (large worlds) renders a scan the same whichever scans the process cast
before: a map build on several workers renders each keyframe in whichever process runs it."""

from __future__ import annotations

import numpy as np

from blockloc.sim.presets import get_preset
from blockloc.sim.stream import SimSequence

HALF_M = 12.0  # the window's half size: cells of 8.4 m, the tiny drive crosses several


def _xy(seq, index: int) -> np.ndarray:
    return seq.trajectory.T_world_flu(np.array([index * seq.period_s]))[0][:2, 3]


def test_a_windowed_scan_does_not_depend_on_the_scans_cast_before():
    preset = get_preset("tiny", scene_window_m=HALF_M)
    fresh = SimSequence(preset, "map", 1)
    near = len(fresh) // 3
    # a frame 2..4 m before: the window the scene had before would still have been in use there
    before = next(j for j in range(near - 1, 0, -1)
                  if 2.0 < np.abs(_xy(fresh, j) - _xy(fresh, near)).max() < 4.0)
    a = fresh.frame(near)
    other = SimSequence(preset, "map", 1)
    other.frame(len(other) - 1)
    other.frame(before)
    b = other.frame(near)
    assert len(a.points) > 100
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.intensity, b.intensity)
