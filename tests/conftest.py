"""Shared fixtures: the workplace's real data and cached simulated datasets."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings


def pytest_configure(config):
    # A suite started as a background job of a non-interactive shell (`cmd &`, as CI runners and
    # nohup do) inherits SIGINT ignored, and so would every blockloc it starts: the Ctrl-C tests
    # would then see an ignored signal (which blockloc rightly leaves ignored). Ctrl-C as a user
    # at a terminal has it: Python's default handler, which children inherit as SIG_DFL.
    import signal

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    _numba_cache_of_this_worker()


def _numba_cache_of_this_worker() -> None:
    """Each pytest-xdist worker (and every blockloc it starts) keeps its numba kernels in a cache
    of its own: two processes compiling the same cached kernel at once can leave a file the other
    loads and crashes on (numba issue #4807; seen here as a segfault in the NDT kernel on a fresh
    checkout). Kept between runs, so a second run compiles nothing."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if not worker or "NUMBA_CACHE_DIR" in os.environ:
        return
    path = Path.home() / ".cache" / "blockloc-tests" / "numba" / worker
    path.mkdir(parents=True, exist_ok=True)
    os.environ["NUMBA_CACHE_DIR"] = str(path)
    import sys

    if "numba" in sys.modules:  # read when a cached function is first located, not at import
        sys.modules["numba"].config.CACHE_DIR = str(path)

# Machines here are shared and noisy: hypothesis checks properties, not speed.
settings.register_profile("blockloc", deadline=None, derandomize=True)
settings.load_profile("blockloc")

REPO = Path(__file__).resolve().parent.parent

# tests/mutate.py is a script (planted-bug runs), not a test module.
collect_ignore = ["mutate.py"]


def shared_data_dir() -> Path:
    """``../shared/data`` beside the repo, or $BLOCKLOC_SHARED_DATA."""
    env = os.environ.get("BLOCKLOC_SHARED_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


def require_shared_data(path: Path) -> Path:
    """``path`` if it exists; else skip the test (a developer without the data), or fail it when
    CI=true (CI always has ../shared/data beside its clone: a missing copy there is an error)."""
    if path.exists():
        return path
    msg = f"real test data not found at {path}: set BLOCKLOC_SHARED_DATA"
    if os.environ.get("CI", "").strip().lower() == "true":
        pytest.fail(msg + " (CI=true: the data must be there)")
    pytest.skip(msg)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The workplace's real data directory (see ``require_shared_data`` for when it is absent)."""
    return require_shared_data(shared_data_dir())
