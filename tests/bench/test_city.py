"""bench.city's pieces that need no cluster: the preset check and the projection model."""

from __future__ import annotations

import pytest

from bench.city import (TARGET, cpu_model, preset_sessions, process_cpu_bound, projection, reference_run,
                        worker_setup_s)


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


def test_cpu_model_schedules_reading_tasks_on_the_first_free_worker():
    st = {"tasks": {"plan": {"cpu_each": [2.0], "cpu_s": 2.0},
                    "run": {"cpu_each": [4.0, 3.0, 3.0, 2.0], "cpu_s": 12.0},
                    "write": {"cpu_each": [0.5] * 4, "cpu_s": 2.0}}}
    assert cpu_model(st, 1) == pytest.approx(16.0)  # everything in sequence
    # two workers: 2 + (4 | 3 + 3 -> 2 on the first free) = 2 + max(4 + 2, 6) = 8, then writes / 2
    assert cpu_model(st, 2) == pytest.approx(2.0 + 6.0 + 1.0)


def test_worker_setup_is_process_cpu_beyond_the_tasks():
    run = {"stats": {"tasks": {"run": {"cpu_s": 30.0}, "write": {"cpu_s": 2.0}}},
           "workers": [{"cpu_s": 40.0}, {"cpu_s": 32.0}], "client_cpu_s": 6.0}
    assert worker_setup_s(run) == pytest.approx((72.0 - 32.0) / 2)
    # the busiest worker (40 s) or all CPU over 2 cores ((72 + 6) / 2 = 39 s)
    assert process_cpu_bound(run, 2) == pytest.approx(40.0)
    assert process_cpu_bound(run, 1) == pytest.approx(78.0)


def test_reference_run_is_serial_else_the_first_that_completed():
    serial, l2, l1 = {"wall_s": 100.0}, {"wall_s": 60.0}, {"wall_s": 90.0}
    assert reference_run({"local:1": l1, "serial": serial, "local:2": l2}) is serial
    # no serial asked for (a full-city local:2 build): the first run's figures stand in
    assert reference_run({"local:2": l2, "local:1": l1}) is l2
    assert reference_run({"serial": {"error": "exit 1"}, "local:2": l2}) is l2
    assert reference_run({"local:2": {"error": "exit 1"}}) is None


def test_an_unknown_run_is_one_line_before_any_work(tmp_path, capsys):
    from bench.city import main

    assert main(["--preset", "campus", "--runs", "local:2,fast", "--work", str(tmp_path / "w")]) == 2
    assert "--runs 'local:2,fast': expected a comma-separated list of serial" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()


def test_raster_tiles_around_the_drives_are_warmed_into_the_disk_cache(tmp_path, monkeypatch):
    import blockloc.sim.stream as stream
    from bench.city import warm_raster_tiles

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path))
    stream.cached_world.cache_clear()
    try:
        n, _ = warm_raster_tiles("tiny", 2, ["map"], 50, margin_m=10.0)
        world = stream.cached_world(stream.get_preset("tiny"), 2)
        on_disk = sorted(world.material_tiles.dir.glob("*.npy"))
        assert n >= 1 and len(on_disk) == n
    finally:
        stream.cached_world.cache_clear()


def test_recorded_drives_are_written_once_and_the_build_reads_them(tmp_path, monkeypatch):
    import json

    from bench.city import child_build, record_drives

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path / "cache"))
    where = record_drives("tiny", 2, ["map"], 30, tmp_path / "rec")
    sync = where / "map" / "velodyne_sync"
    scans = sorted(sync.glob("*.bin"))
    assert where == tmp_path / "rec" / "tiny-2-30" and len(scans) == 30
    stamp = scans[0].stat().st_mtime_ns
    assert record_drives("tiny", 2, ["map"], 30, tmp_path / "rec") == where  # kept, not written again
    assert scans[0].stat().st_mtime_ns == stamp and not list(where.glob(".*"))
    sizes = {"block_size_m": 100.0, "tile_size_m": 20.0, "voxel_size_m": 0.2, "keyframe_distance_m": 1.0,
             "keyframe_angle_deg": 15.0}
    spec = {"name": "serial", "kind": "block", "preset": "tiny", "seed": 2, "sessions": ["map"],
            "max_frames": 30, "sizes": sizes, "out": str(tmp_path / "map"), "recorded": str(where),
            "cluster": None}
    res = child_build(spec)
    assert res["entries"] >= 1 and res["points"] > 0 and res["stats"]["drives"] == 1
    manifest = json.loads((tmp_path / "map" / "manifest.json").read_text())
    assert str(where / "map") in json.dumps(manifest)  # built from the files, not the simulator
