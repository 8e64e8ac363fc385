"""The `small` simulated world and its block map, generated once per machine (cached under
$BLOCKLOC_CACHE or ~/.cache/blockloc, the same cache `blockloc demo` uses) and once per session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def small_world():
    """(DemoPaths, Config): <dataset>/map and <dataset>/loc in NCLT layout, and their block map."""
    from blockloc.config import load_config
    from blockloc.demo import DemoPaths, ensure_block_map, ensure_dataset

    cfg = load_config("sim")
    paths = DemoPaths.default()
    ensure_dataset(paths)
    ensure_block_map(paths, cfg)
    return paths, cfg
