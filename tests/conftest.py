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

_PREBUILD: list = []


def pytest_sessionstart(session):
    """The whole suite on several workers: the small world's block map (cached under
    BLOCKLOC_CACHE, built once behind a lock: ``blockloc.app.runs.ensure_block_map``) is started
    in a process of its own before the workers start. Otherwise the first worker to need it builds
    it while the second, needing it too, waits idle for minutes; now both run other tests
    meanwhile. Only the controller of a whole-suite run does it (not a worker, not a run of
    chosen files: those may not need the map at all)."""
    import subprocess
    import sys

    config = session.config
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None):
        return
    if [Path(a).resolve() for a in config.args] != [REPO / t for t in config.getini("testpaths")]:
        return
    env = dict(os.environ, NUMBA_CACHE_DIR=str(Path.home() / ".cache" / "blockloc-tests" / "numba" / "prebuild"))
    _PREBUILD.append(subprocess.Popen(
        [sys.executable, "-c", "from blockloc.app.runs import prepare_small_world; prepare_small_world()"],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))


def pytest_sessionfinish(session):
    for proc in _PREBUILD:  # a run stopped early: the build is let go (its writer leaves no map)
        if proc.poll() is None:
            proc.terminate()
            proc.wait(60)


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
