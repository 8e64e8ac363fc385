"""A relocalization attempt that global init cannot even start (e.g. a scan too sparse to project)
is a failed attempt, not the end of the tracking run."""

from __future__ import annotations

import numpy as np

from blockloc.config import Config
from blockloc.errors import GlobalInitError
from blockloc.pipeline import LocalizationPipeline


class _Info:
    T_body_lidar = np.eye(4)


class _RaisingLocalizer:
    calls = 0

    def localize(self, *args, **kwargs):
        self.calls += 1
        raise GlobalInitError("scan has 46 occupied cells in the height band (0.3, 3.0) m: expected at least 50")


def test_relocalize_returns_none_and_logs_when_global_init_raises():
    pipe = LocalizationPipeline("unused", cfg=Config())
    pipe.info = _Info()
    pipe.localizer = _RaisingLocalizer()
    pipe.reloc_log = []
    hint = np.eye(4)
    hint[:3, 3] = [10.0, -4.0, 0.0]
    pts = np.random.default_rng(0).normal(0, 5, (30, 3))
    assert pipe.relocalize(pts, hint, np.array([0.0, 0.0, 9.81]), 12.5) is None
    assert pipe.relocalize(pts, None, np.array([0.0, 0.0, 9.81]), 12.6) is None
    assert pipe.localizer.calls == 2
    assert [e["verified"] for e in pipe.reloc_log] == [False, False]
    assert "occupied cells" in pipe.reloc_log[0]["error"] and pipe.reloc_log[0]["hint"]
    assert not pipe.reloc_log[1]["hint"]
