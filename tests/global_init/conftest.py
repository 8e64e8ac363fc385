"""Fixtures of the global-init tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def small_world():
    """(DemoPaths, Config): the cached `small` world in NCLT layout and its block map (as
    tests/tracking uses; built once per machine)."""
    from blockloc.demo import prepare_small_world

    return prepare_small_world()
