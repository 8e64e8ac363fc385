"""Finding 7: a fresh clone without ``../shared/data`` runs the test suite: the tests that need the
real data skip with a clear reason; under ``CI=true`` (where the data must be present) they fail."""

from __future__ import annotations

import os
import subprocess
import sys

from .cases import case
from .conftest import REPO

REAL_DATA_TEST = "tests/datasets/test_pointclouds.py::test_opencalib_fixture"


def _pytest(tmp_path, **env) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k != "CI"}
    environ.update(BLOCKLOC_SHARED_DATA=str(tmp_path / "no-such-data"), **env)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-n", "0", "-p", "no:cacheprovider", REAL_DATA_TEST],
                          capture_output=True, text=True, cwd=REPO, env=environ, timeout=300)


@case(7, "a test that needs ../shared/data on a machine without it", "skipped, the reason names "
      "the path and BLOCKLOC_SHARED_DATA (was: an error failing the run)")
def test_without_shared_data_the_test_skips(tmp_path):
    r = _pytest(tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "1 skipped" in r.stdout and "BLOCKLOC_SHARED_DATA" in r.stdout and "no-such-data" in r.stdout


@case(7, "the same under CI=true", "the test errors, the run fails, naming the path (CI must have the data)")
def test_without_shared_data_under_ci_the_test_fails(tmp_path):
    r = _pytest(tmp_path, CI="true")
    assert r.returncode == 1, r.stdout + r.stderr
    assert "1 error" in r.stdout and "no-such-data" in r.stdout and "CI=true" in r.stdout
