"""A relocalization attempt that global init cannot even start (a scan too sparse to project, a map
entry that cannot be read) is a failed attempt, not the end of the tracking run."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from blockloc.datasets.base import ImuData, SequenceInfo
from blockloc.errors import GlobalInitError, MapError
from blockloc.app.session import Session


class _RaisingLocalizer:
    def __init__(self, exc):
        self.exc, self.calls = exc, 0

    def localize(self, *args, **kwargs):
        self.calls += 1
        raise self.exc


def _session(localizer):
    seq = SimpleNamespace(info=SequenceInfo("fake"), imu=lambda: ImuData(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))),
                          ground_truth=lambda: None, frame_stamps=lambda: np.zeros(0))
    return Session(seq, None, SimpleNamespace(close=lambda: None), localizer=localizer)


def test_relocalize_returns_none_and_logs_when_global_init_raises():
    s = _session(_RaisingLocalizer(GlobalInitError("scan has 46 occupied cells in the height band (0.3, 3.0) m: "
                                                   "expected at least 50")))
    hint = np.eye(4)
    hint[:3, 3] = [10.0, -4.0, 0.0]
    pts = np.random.default_rng(0).normal(0, 5, (30, 3))
    assert s.relocalize(pts, hint, np.array([0.0, 0.0, 9.81]), 12.5) is None
    assert s.relocalize(pts, None, np.array([0.0, 0.0, 9.81]), 12.6) is None
    assert s.localizer.calls == 2
    assert [e["verified"] for e in s.reloc_log] == [False, False]
    assert "occupied cells" in s.reloc_log[0]["error"] and s.reloc_log[0]["hint"]
    assert not s.reloc_log[1]["hint"]
    assert s.counters["map_faults"] == 0


def test_a_missing_map_entry_during_relocalization_is_a_counted_map_fault():
    s = _session(_RaisingLocalizer(MapError("/maps/x/007.pcd: missing map file")))
    assert s.relocalize(np.zeros((200, 3)), None, np.array([0.0, 0.0, 9.81]), 3.0) is None
    assert s.counters["map_faults"] == 1 and "007.pcd" in s.reloc_log[0]["error"]
