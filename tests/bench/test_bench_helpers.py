"""Helpers of the benchmark suite: map replication (scaling), the rolling-map odometry baseline,
trajectory comparison, the summary's reading of fragments."""

from __future__ import annotations

import json

import numpy as np
import pytest

from blockloc.registration.engines import make_engine

from bench import summary
from bench._track import RollingMapProvider, STATUS_CODES, summarize, trajectory_rmse
from bench.scaling import lattice_offsets, replicate_store, replication_pitch
from blockloc.maps.grid_tiles import tile_bounds
from blockloc.maps.store import MapWriter, open_map


def _points(rng, lo, hi, n):
    return rng.uniform(lo, hi, (n, 3)).astype(np.float32)


@pytest.fixture
def stores(tmp_path):
    rng = np.random.default_rng(3)
    with MapWriter(tmp_path / "grid", "grid", params={"tile_size_m": 10.0}) as w:
        w.add("5.0_5.0", _points(rng, [0, 0, 0], [10, 10, 1], 50))
        w.add("-5.0_15.0", _points(rng, [-10, 10, 0], [0, 20, 1], 30))
        grid = w.commit()
    with MapWriter(tmp_path / "block", "block", params={"block_size_m": 20.0}) as w:
        w.add("000", _points(rng, [-10, 0, 0], [5, 20, 1], 40))
        w.add("001", _points(rng, [0, 0, 0], [10, 10, 1], 20))
        block = w.commit()
    return grid, block


def test_lattice_offsets_start_at_origin_and_count_k_squared():
    offs = lattice_offsets(3, (30.0, 40.0))
    assert offs[0] == (0.0, 0.0)
    assert len(offs) == 9 and len(set(offs)) == 9
    assert max(o[0] for o in offs) == 60.0 and max(o[1] for o in offs) == 80.0


def test_pitch_is_whole_tiles_and_clears_the_map(stores):
    grid, block = stores
    px, py = replication_pitch(block, grid, 10.0)
    assert px % 10.0 == 0 and py % 10.0 == 0
    lo, hi = grid.bounds()
    assert px > hi[0] - lo[0] and py > hi[1] - lo[1]


def test_replicated_grid_renames_tiles_to_their_shifted_cells(stores, tmp_path):
    grid, block = stores
    pitch = replication_pitch(block, grid, 10.0)
    out = replicate_store(grid, tmp_path / "g4", lattice_offsets(2, pitch), 10.0)
    assert len(out) == 4 * len(grid)
    assert out.total_points == 4 * grid.total_points
    for eid in out.ids:  # every tile's points lie in the cell its name says
        pts, _ = out.load(eid)
        lo, hi = tile_bounds(eid, 10.0)
        assert np.all(pts[:, :2] >= lo - 1e-4) and np.all(pts[:, :2] <= hi + 1e-4)
    # the original copy is unchanged
    np.testing.assert_array_equal(out.load("5.0_5.0")[0], grid.load("5.0_5.0")[0])


def test_replicated_grid_rejects_offsets_off_the_tile_lattice(stores, tmp_path):
    grid, _ = stores
    with pytest.raises(ValueError, match="multiple"):
        replicate_store(grid, tmp_path / "bad", [(0.0, 0.0), (15.0, 0.0)], 10.0)


def test_replicated_blocks_get_unique_ids_and_shifted_centroids(stores, tmp_path):
    grid, block = stores
    offs = [(0.0, 0.0), (100.0, 0.0), (0.0, 200.0)]
    out = replicate_store(block, tmp_path / "b3", offs)
    assert len(out) == 6 and len(set(out.ids)) == 6
    c0 = block.centroids()
    c = out.centroids()
    for k, (dx, dy) in enumerate(offs):
        np.testing.assert_allclose(c[2 * k:2 * k + 2, :2], c0[:, :2] + [dx, dy], atol=1e-3)


def test_rolling_map_keeps_seed_scans_then_keyframes_by_distance():
    rng = np.random.default_rng(0)
    prov = RollingMapProvider(make_engine("ndt", min_points_per_voxel=3), seed_scans=3, keyframe_m=1.0, rebuild_m=1.0)
    assert prov.update(np.zeros(3), None, 0.0).target is None  # no scan yet: nothing to register to
    wall = np.c_[rng.uniform(-20, 20, 3000), np.full(3000, 5.0), rng.uniform(0, 3, 3000)]
    for _ in range(5):  # standing still: only the seed scans are kept
        prov.add_scan(np.zeros(3), wall + rng.normal(0, 0.01, wall.shape))
    assert len(prov.keyframes) == 3
    prov.add_scan(np.array([0.5, 0, 0]), wall)
    assert len(prov.keyframes) == 3  # moved less than keyframe_m
    prov.add_scan(np.array([1.5, 0, 0]), wall)
    assert len(prov.keyframes) == 4
    local = prov.update(np.array([1.5, 0, 0]), None, 1.0)
    assert local.target is not None and local.num_points > 0 and not local.switched
    built = prov.builds
    prov.update(np.array([1.6, 0, 0]), None, 1.1)  # nothing new: no rebuild
    assert prov.builds == built


def test_rolling_map_serves_only_keyframes_within_radius():
    prov = RollingMapProvider(make_engine("ndt", min_points_per_voxel=3), radius_m=10.0, voxel_m=0.05, seed_scans=1,
                              keyframe_m=1.0)
    near = np.c_[np.arange(50.0) * 0.1, np.zeros(50), np.arange(50.0) % 5 * 0.1]
    prov.add_scan(np.zeros(3), near)
    prov.add_scan(np.array([100.0, 0, 0]), near + [100.0, 0, 0])
    local = prov.update(np.array([100.0, 0, 0]), None, 0.0)
    assert 0 < local.num_points <= 50  # the far keyframe only


def test_trajectory_rmse_matches_common_stamps_only():
    a = {"_stamps": np.array([0.0, 0.1, 0.2, 0.3]), "_positions": np.zeros((4, 3))}
    b = {"_stamps": np.array([0.1, 0.3, 0.5]), "_positions": np.array([[3.0, 4, 0], [0, 0, 0], [9, 9, 9]])}
    assert trajectory_rmse(a, b) == pytest.approx(np.sqrt(25 / 2))
    assert trajectory_rmse(a, {"_stamps": np.array([7.0]), "_positions": np.zeros((1, 3))}) is None


def test_summarize_excludes_uninitialized_frames_and_reads_switches():
    z = {"core_ms": np.array([100.0, 10, 12, 14]), "update_ms": np.array([200.0, 11, 13, 30]),
         "registration_ms": np.ones(4), "map_ms": np.zeros(4), "switched": np.array([0, 0, 0, 1]),
         "status": np.array([STATUS_CODES["uninitialized"], 0, 0, 0]), "window": np.array([0, 1, 2, 3]),
         "active_points": np.array([0, 5, 5, 7]), "stamps": np.array([0.1, 0.2, 0.3]),
         "poses": np.tile(np.eye(4), (3, 1, 1)),
         "counters": np.array(json.dumps({"failures": 0, "recoveries": 0, "switches": 1, "rejected": 0,
                                          "imu_only": 0})), "map_stats": np.array("{}")}
    m = summarize(z)
    assert m["core_ms_median"] == 12.0  # the uninitialized first frame is not a tracking cost
    assert m["switch_frames"] == 1 and m["switch_update_ms_p99"] == pytest.approx(30.0)
    assert "ate_trans_rmse_m" not in m  # no ground truth given


def test_summary_reads_the_global_init_row_and_says_not_measured(tmp_path, monkeypatch):
    monkeypatch.setattr(summary, "FRAG", tmp_path)
    assert summary.global_init_row() is None
    (tmp_path / "global_init.md").write_text(
        "| method | frames | success | median trans. error (m) | median rot. error (deg) | median time (s) |\n"
        "|---|---|---|---|---|---|\n| bbs | 10 | 90% | 0.5 | 1 | 0.2 |\n| bbs+s0 | 10 | 99% | 0.027 | 0.05 | 0.15 |\n")
    assert summary.global_init_row() == {"error_m": 0.027, "time_s": 0.15, "success": "99%"}
    text = summary.build()
    assert "0.15 s" in text and "**beat**" in text
    assert "not measured" in text  # no tracking.json here
    assert summary.verdict(20.0, 14.28) == "**trail**" and summary.verdict(None, 1.0) == "not measured"
    # sections are appended: a later table with the method is the newer measurement, and wins
    (tmp_path / "global_init.md").write_text(
        "Measured 2026-11-22.\n\n"
        "| method | frames | success | median trans. error (m) | median time (s) |\n|---|---|---|---|---|\n"
        "| bbs+s0 | 10 | 99% | 0.027 | 0.15 |\n\n"
        "| method | frames | success | median trans. error (m) | median time (s) |\n|---|---|---|---|---|\n"
        "| bbs+s0 | 100 | 100% | 0.081 | 3.23 |\n")
    assert summary.global_init_row() == {"error_m": 0.081, "time_s": 3.23, "success": "100%"}
    # a fragment first dated before the realistic simulator says so in the summary's rows
    assert summary.measured_on("global_init") == " (earlier simulator, 2026-11-22)"
    assert "global_init (earlier simulator, 2026-11-22)" in summary.build()
    (tmp_path / "global_init.md").write_text("Measured 2026-12-02.\n")
    assert summary.measured_on("global_init") == "" and summary.measured_on("missing") == ""


def test_assemble_points_plot_links_at_the_fragments_folder(tmp_path, monkeypatch):
    import bench.__main__ as entry

    frags = tmp_path / "docs" / "bench"
    frags.mkdir(parents=True)
    (frags / "scaling.md").write_text("## Scaling\n\nMeasured 2026-12-02.\n\n## Scaling, again\n")
    (frags / "sim.md").write_text("## Simulator\n\nMeasured 2026-11-22.\n")
    (frags / "extra.md").write_text("## Extra\n")
    (frags / "headline.md").write_text("## Headline figures\n\n| what | value | section |\n|---|---|---|\n"
                                       "| time | 3 s | [scaling](scaling.md) |\n\n![plot](scaling.png)\n"
                                       "![abs](https://x.org/a.png)\n")
    monkeypatch.setattr(entry, "ROOT", tmp_path)
    monkeypatch.setattr(entry, "FRAGMENTS", frags)
    text = entry.assemble().read_text()
    # the headline table first, its links turned to the fragments folder
    assert text.index("## Headline figures") < text.index("## Sections")
    assert "[scaling](bench/scaling.md)" in text and "![plot](bench/scaling.png)" in text
    assert "![abs](https://x.org/a.png)" in text  # absolute links are left alone
    # then one row per fragment: its section titles, its first date, a link; ORDER first
    assert "| Scaling; Scaling, again | 2026-12-02 | [bench/scaling.md](bench/scaling.md) |" in text
    assert "| Simulator | 2026-11-22 (earlier simulator" in text
    assert text.index("[bench/sim.md]") < text.index("[bench/scaling.md]") < text.index("[bench/extra.md]")
    assert "bench/headline.md" not in text and "Measured" not in text  # sections stay in their files


def test_run_fragment_lists_every_part_with_its_time_and_exit(tmp_path, monkeypatch):
    import time

    import bench.__main__ as entry

    monkeypatch.setattr(entry, "FRAGMENTS", tmp_path)
    entry.write_run_fragment({"ndt": (90.0, 0), "campus": (3000.0, 1)}, time.gmtime(0), 3090.0, 0.5)
    text = (tmp_path / "run.md").read_text()
    assert "took **52 min**" in text
    assert "| ndt | 1.5 | 0 |" in text and "| campus | 50.0 | 1 |" in text


def _gi_method(success, failed=()):
    return {"frames": 10, "success": success, "err_m": 0.03, "err_deg": 0.05, "time_s": 0.4, "nodes": 1e5,
            "failed": list(failed)}


def test_global_init_notes_follow_the_figures():
    from bench.global_init import notes

    small = {"methods": {"bbs+s0": _gi_method(0.9, [(463, 4.3)]), "bbs": _gi_method(0.2)}, "reloc": None}
    text = notes(small, {"map_points": 10, "methods": {}, "reloc": {"place index": {
        "frames": 10, "success": 0.9, "time_s": 1.25, "wrong_verified": 1}}})
    assert "**missed**" in text  # 90% success is below the 98% target
    assert "failure reproduces" in text  # plain BBS at 20%
    assert "463 (4.30 m off)" in text
    assert "no hint (place index): 90% of 10 frames, 1.2 s median, 1 wrong verified" in text
    good = notes({"methods": {"bbs+s0": _gi_method(1.0), "bbs": _gi_method(1.0)}, "reloc": None}, None)
    assert "met)" in good and "does not reproduce" in good and "Failed frames" not in good


def test_fragments_from_before_the_realistic_sim_are_flagged(tmp_path, monkeypatch):
    import bench.__main__ as entry

    monkeypatch.setattr(entry, "FRAGMENTS", tmp_path)
    monkeypatch.setattr(entry, "ROOT", tmp_path)
    (tmp_path / "docs").mkdir()
    (tmp_path / "sim.md").write_text("## Simulator\n\nCommand: `python -m bench.sim`, run 2026-11-22 11:46 UTC.\n")
    (tmp_path / "ndt.md").write_text("## NDT registration\n\nCommand: `python -m bench.ndt` (2026-12-02 01:42 UTC).\n")
    rows = {line.split(" | ")[0]: line for line in entry.assemble().read_text().splitlines()}
    assert "2026-11-22 (earlier simulator" in rows["| Simulator"]
    assert "earlier simulator" not in rows["| NDT registration"]


def _segment(tmp_path, name, start, n, failures, backends=("block",)):
    from bench.campus import _write_json

    d = tmp_path / name
    d.mkdir()
    z = {"index": np.arange(start, start + n), "core_ms": np.full(n, 5.0 + start), "stamps": start + np.arange(n) * 0.1,
         "poses": np.tile(np.eye(4), (n, 1, 1)),
         "counters": np.array(json.dumps({"failures": failures, "rejected": 1})),
         "map_stats": np.array(json.dumps({"resident_mb": float(start)}))}
    for b in backends:
        np.savez(d / f"{b}.npz", **z)
    _write_json(d / "progress.json", {"command": f"seg {start}", "sequence": "sim:campus/loc@1", "backends": list(backends),
                                      "start": start, "frames_done": n, "wall_s": 10.0 * n, "updated": f"t{start}",
                                      "load_now": 1.0, "load_mean": 1.0, "finished": True})
    return d


def test_merge_states_joins_consecutive_segments_and_refuses_a_gap(tmp_path):
    from bench.campus import merge_states

    a, b = _segment(tmp_path, "a", 0, 3, failures=0), _segment(tmp_path, "b", 3, 2, failures=2)
    merge_states([b, a], tmp_path / "m")  # given out of order: sorted by start
    z = np.load(tmp_path / "m" / "block.npz")
    assert z["index"].tolist() == [0, 1, 2, 3, 4]
    assert z["core_ms"].tolist() == [5.0] * 3 + [8.0] * 2
    assert json.loads(str(z["counters"])) == {"failures": 2, "rejected": 2}
    assert json.loads(str(z["map_stats"]))["resident_mb"] == 3.0  # the last segment's
    prog = json.loads((tmp_path / "m" / "progress.json").read_text())
    assert (prog["start"], prog["frames_done"], prog["wall_s"]) == (0, 5, 30.0)
    assert prog["scan_wall_ms"] == 10_000.0
    assert [s["start"] for s in prog["segments"]] == [0, 3]
    gap = _segment(tmp_path, "c", 9, 2, failures=0)
    with pytest.raises(SystemExit, match="does not continue"):
        merge_states([a, gap], tmp_path / "m2")


def test_a_joined_run_is_finished_when_its_last_segment_is(tmp_path):
    """A first segment stopped where a second one took over (its own bound not reached) does not
    leave the joined run 'not finished'; a last segment that is still running does."""
    from bench.campus import _write_json, merge_states

    a, b = _segment(tmp_path, "a", 0, 3, failures=0), _segment(tmp_path, "b", 3, 2, failures=0)
    for d, finished, stop in ((a, False, 10), (b, True, 5)):
        prog = json.loads((d / "progress.json").read_text())
        _write_json(d / "progress.json", prog | {"finished": finished, "stop": stop})
    merge_states([a, b], tmp_path / "m")
    prog = json.loads((tmp_path / "m" / "progress.json").read_text())
    assert prog["finished"] is True and prog["stop"] == 5
    _write_json(b / "progress.json", json.loads((b / "progress.json").read_text()) | {"finished": False})
    merge_states([a, b], tmp_path / "m2")
    assert json.loads((tmp_path / "m2" / "progress.json").read_text())["finished"] is False


def test_merge_states_keeps_the_backends_every_segment_ran(tmp_path):
    from bench.campus import merge_states

    first = _segment(tmp_path, "a", 0, 3, failures=0, backends=("block", "block@vgicp"))
    rest = _segment(tmp_path, "b", 3, 2, failures=1)
    merge_states([first, rest], tmp_path / "m")
    prog = json.loads((tmp_path / "m" / "progress.json").read_text())
    assert prog["backends"] == ["block"] and prog["frames_done"] == 5
    assert not (tmp_path / "m" / "block@vgicp.npz").exists()
    other = _segment(tmp_path, "c", 3, 2, failures=0, backends=("grid",))
    with pytest.raises(SystemExit, match="does not continue"):
        merge_states([first, other], tmp_path / "m2")


def test_exact_sequence_switches_only_the_named_error_sources_off():
    from bench.campus import exact_sequence
    from blockloc.app.catalog import open_sequence

    base = open_sequence("sim:tiny/loc@3")
    ext = exact_sequence("tiny", "loc", 3, ["extrinsic"])
    # the world (and so the map built from it) is the same; only the mounting error is gone
    assert np.array_equal(base.world.facades, ext.world.facades)
    assert ext.preset.lidar == base.preset.lidar and ext.preset.imu == base.preset.imu
    assert ext.preset.extrinsic_error_m == 0.0 and base.preset.extrinsic_error_m > 0.0
    assert not np.allclose(base.T_body_lidar_true, ext.T_body_lidar_true)
    sensor = exact_sequence("tiny", "loc", 3, ["lidar", "imu"])
    assert sensor.preset.lidar.range_tail_prob == 0.0 < base.preset.lidar.range_tail_prob
    assert sensor.preset.imu.scale_factor_sigma == 0.0 < base.preset.imu.scale_factor_sigma
    assert sensor.preset.detail == base.preset.detail and sensor.preset.extrinsic_error_m > 0.0


def test_exact_slam_maps_from_exact_poses_in_their_own_cache_dir():
    from bench.campus import default_map_dir, exact_sequence
    from blockloc.config import load_config
    from blockloc.app.catalog import open_sequence

    base = open_sequence("sim:tiny/map@3").mapping_poses()
    exact = exact_sequence("tiny", "map", 3, ["slam"])
    mp, gt = exact.mapping_poses(), exact.ground_truth()
    assert np.allclose(mp.poses, gt.poses) and not np.allclose(base.poses, gt.poses, atol=1e-3)
    cfg = load_config("sim").map
    assert default_map_dir("tiny", 3, cfg, exact=("slam",)) != default_map_dir("tiny", 3, cfg)


def test_exact_parts_that_shape_the_map_get_their_own_map(capsys):
    from bench.campus import main

    # one robot drives both sessions: its mounting and sensor errors are in the map too, so
    # switching them off must not reuse a map built with them
    with pytest.raises(SystemExit):
        main(["--exact", "extrinsic", "--map", "/nonexistent"])
    assert "builds its own map" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--exact", "imu,bogus"])
    assert "expected a comma list" in capsys.readouterr().err


def test_budget_lowpass_keeps_slow_error_and_removes_jitter(tmp_path, capsys):
    from bench.campus_budget import LOWPASS_SCANS, lowpass, main

    rng = np.random.default_rng(0)
    t = np.arange(2000) / 10.0
    slow = np.stack([0.05 * np.sin(2 * np.pi * t / 60.0)] * 3, axis=1)
    jitter = rng.normal(0.0, 0.05, (2000, 3))
    k = LOWPASS_SCANS
    assert np.abs(lowpass(slow)[k:-k] - slow[k:-k]).max() < 0.002
    assert lowpass(jitter)[k:-k].std() < 0.3 * jitter.std()
    with pytest.raises(SystemExit):
        main(["--run", f"none={tmp_path}", "--out", str(tmp_path / "x.md")])
    assert "bench.campus --state directory" in capsys.readouterr().err


@pytest.mark.parametrize("debug", [False, True])
def test_a_user_error_in_a_benchmark_is_one_line_unless_debugging(debug):
    """An unknown --set key reaches the top of ``python -m bench.campus`` as a ConfigError: one
    line naming the key and a non-zero exit, the traceback only with BLOCKLOC_DEBUG."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {k: v for k, v in os.environ.items() if k != "BLOCKLOC_DEBUG"}
    if debug:
        env["BLOCKLOC_DEBUG"] = "1"
    p = subprocess.run([sys.executable, "-m", "bench.campus", "--set", "registration.bogus=1", "--max-frames", "1"],
                       cwd=Path(__file__).resolve().parents[2], env=env, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode != 0
    assert "unknown key 'bogus'" in p.stderr
    assert ("Traceback" in p.stderr) == debug
    if not debug:
        assert len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_realism_scattered_share_by_surroundings():
    from bench.realism import scattered_by_surroundings

    rows = [{"surroundings": "field", "scattered_share": 0.4},
            {"surroundings": "buildings+field", "scattered_share": 0.5},
            {"surroundings": "buildings", "scattered_share": 0.2},
            {"surroundings": "park", "scattered_share": float("nan")}]
    lines = scattered_by_surroundings(rows)
    assert lines[2] == "| an open quad (field) within 8 m | 2 | 45.0% |"
    assert lines[3] == "| no open quad within 8 m | 1 | 20.0% |"
    assert lines[4] == "| all | 3 | 40.0% |"


def test_benchmark_engine_names_stand_for_registration_settings():
    from bench._track import engine_settings
    from blockloc.config import load_config

    assert engine_settings("ndt") == {"method": "ndt"}
    one = load_config("sim", overrides={"registration": engine_settings("vgicp1")}).registration
    assert one.method == "vgicp" and one.voxel_grids == 1
    assert load_config("sim", overrides={"registration": engine_settings("vgicp")}).registration.voxel_grids == 2


def test_campus_report_names_what_stopped_a_run_short():
    from bench.campus import _bound

    assert _bound({"max_frames": 8300, "minutes": 120.0}, 8300) == "the run was bounded to --max-frames 8,300"
    assert _bound({"max_frames": 8300, "minutes": 20.0}, 5000) == "the loop is bounded to --minutes 20"
    assert _bound({"minutes": 20.0}, 5000) == "the loop is bounded to --minutes 20"  # older progress files
