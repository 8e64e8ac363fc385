"""bench.city's pieces that need no cluster: the preset check and the projection model."""

from __future__ import annotations

import pytest

from bench.city import TARGET, preset_sessions, projection


def test_missing_preset_is_one_line():
    with pytest.raises(SystemExit, match="no 'nowhere' simulated preset in blockloc.sim.presets"):
        preset_sessions("nowhere")
    assert preset_sessions("campus") == (["map"], "loc")


def test_projection_scales_counts_and_divides_work():
    serial = {"stats": {"path_m": 10_000.0, "tasks": {
        "plan": {"count": 1, "seconds": 10.0}, "candidate": {"count": 100, "seconds": 500.0},
        "merge": {"count": 10, "seconds": 5.0}, "write": {"count": 80, "seconds": 8.0}}},
        "bounds": [[0.0, 0.0, 0.0], [1000.0, 1000.0, 10.0]]}  # 10 km over 1 km^2
    pj = projection(serial, {"task_overhead_s": 0.001}, "block")
    rows = pj["rows"]
    assert rows["candidate"]["count"] == pytest.approx(100 * TARGET["path_km"] / 10.0)
    assert rows["write"]["count"] == pytest.approx(80 * TARGET["area_km2"] / 1.0)
    assert rows["candidate"]["cost_s"] == pytest.approx(5.0)
    w8, w32, w128 = (pj["times_s"][w] for w in TARGET["workers"])
    assert w8 > w32 > w128 >= pj["merge_chain_s"] + pj["tasks"] * 0.001
    assert w8 == pytest.approx(pj["work_s"] / 8 + pj["tasks"] * 0.001 + pj["merge_chain_s"])
