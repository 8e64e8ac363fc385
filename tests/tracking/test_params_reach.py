"""Every field of the ``tracking`` config section reaches the code that uses it.

The section is the tracker's own dataclass (``blockloc.tracking.params.TrackingParams``); a field
renamed on one side only would stop being read. A recording subclass notes every field the
factory and both estimator variants read over a few frames that take every branch a setting
steers (an accepted scan with the odometry factor, rejected scans, the LiDAR-only retries)."""

from __future__ import annotations

import dataclasses

import numpy as np

from blockloc.config import Config, TrackingConfig
from blockloc.datasets.base import SequenceInfo
from blockloc.tracking.params import TrackingParams
from blockloc.app.assemble import make_tracker as tracker_from_config
from tests.tracking.test_tracker_branches import GRAVITY, T_START, FixedProvider, ScriptedRegistration, _frame

# Declared, loaded and checked, but read by no estimator (every scan is a keyframe).
NOT_USED = {"keyframe_distance_m"}


class Recording(TrackingParams):
    read: set

    def __getattribute__(self, name):
        if name in TrackingParams.__dataclass_fields__:
            object.__getattribute__(self, "read").add(name)
        return object.__getattribute__(self, name)


class PoorFit(ScriptedRegistration):
    """The guess back as the pose, with a fitness below any gate from call ``from_call`` on."""

    def __init__(self, from_call):
        super().__init__()
        self.from_call = from_call

    def align(self, target, source_points, T_init):
        res = super().align(target, source_points, T_init)
        if self.calls - 1 >= self.from_call:
            res.fitness = 0.0
        return res


def _drive(use_imu: bool, read: set) -> None:
    cfg = Config()
    section = Recording(**{f.name: getattr(cfg.tracking, f.name) for f in dataclasses.fields(TrackingParams)})
    object.__setattr__(section, "read", read)
    section.use_odometry_factor = True
    read.discard("use_odometry_factor")
    cfg.tracking = section
    tr = tracker_from_config(cfg, SequenceInfo("x", gravity_map=GRAVITY), map_provider=FixedProvider(),
                             registration=PoorFit(from_call=3), use_imu=None if use_imu else False)
    assert tr.lidar_only is (not use_imu)
    tr.initialize(T_START, 0.0, velocity_map=np.zeros(3))
    for k in range(1, 7):
        for t in np.arange(0.1 * (k - 1), 0.1 * k, 0.01):
            tr.insert_imu(float(t), -GRAVITY, np.zeros(3))
        tr.insert_frame(_frame(k, 0.1 * k))
    assert tr.counters["rejected"] >= 3 and tr.counters["failures"] == 1
    if not use_imu:
        assert tr.counters["rotation_retries"] >= 1


def test_the_tracking_section_is_the_trackers_dataclass():
    assert TrackingConfig is TrackingParams
    assert isinstance(Config().tracking, TrackingParams)


def test_every_tracking_field_reaches_the_estimators():
    read: set = set()
    _drive(True, read)
    _drive(False, read)
    fields = {f.name for f in dataclasses.fields(TrackingParams)}
    assert NOT_USED <= fields
    assert fields - NOT_USED - read == set()
    assert not NOT_USED & read  # a field put to use belongs out of NOT_USED
