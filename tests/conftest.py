"""Shared fixtures: the workplace's real data and cached simulated datasets."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

# Machines here are shared and noisy: hypothesis checks properties, not speed.
settings.register_profile("blockloc", deadline=None, derandomize=True)
settings.load_profile("blockloc")

REPO = Path(__file__).resolve().parent.parent


def shared_data_dir() -> Path:
    """``../shared/data`` beside the repo, or $BLOCKLOC_SHARED_DATA."""
    env = os.environ.get("BLOCKLOC_SHARED_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = shared_data_dir()
    if not path.exists():
        pytest.fail(f"real test data not found at {path}: set BLOCKLOC_SHARED_DATA")
    return path
