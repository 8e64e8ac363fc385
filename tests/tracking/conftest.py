"""The `small` simulated world and its block map, generated once per machine (cached under
$BLOCKLOC_CACHE or ~/.cache/blockloc, the same cache `blockloc demo` uses) and once per session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def small_world():
    """(SmallWorld, Config): the sim:small sessions (simulated on the fly) and their block map."""
    from blockloc.app.runs import prepare_small_world

    paths, cfg = prepare_small_world()
    return paths, cfg
