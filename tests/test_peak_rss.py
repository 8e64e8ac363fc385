"""metrics.json's peak_rss_mb belongs to the tracking process, not to whatever started it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork + exec peak inheritance is Linux's")
def test_peak_rss_of_a_child_ignores_a_large_parent():
    ballast = np.ones(500 * 2**20 // 8)  # the parent touches 500 MB before starting the child
    code = "from blockloc.resources import peak_rss_mb; print(peak_rss_mb())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    child_mb = float(out.strip().splitlines()[-1])
    assert ballast.sum() > 0
    assert 10.0 < child_mb < 400.0, child_mb
