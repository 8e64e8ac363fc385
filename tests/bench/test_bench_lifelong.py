"""bench/lifelong.py's scoring: one-voxel-tolerant precision / recall, and the update's hash and
size check on two small stores (the bench itself runs minutes: python -m bench.lifelong)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import lifelong as B
from blockloc.maps.changes.detect import pack_keys


def test_precision_recall_with_one_voxel_tolerance():
    truth = pack_keys(np.array([[0, 0, 0], [1, 0, 0], [10, 10, 10]]))
    det = pack_keys(np.array([[0, 0, 1], [5, 5, 5]]))  # one next to the truth, one far off
    r = B._prf(det, truth)
    assert r["precision"] == 0.5 and r["recall"] == pytest.approx(2 / 3)
    assert r["f1"] == pytest.approx(2 * 0.5 * (2 / 3) / (0.5 + 2 / 3))
    empty = B._prf(np.zeros(0, np.int64), truth)
    assert np.isnan(empty["precision"]) and empty["recall"] == 0.0



def test_a_removed_truth_voxel_belongs_to_every_block_that_holds_it():
    from types import SimpleNamespace

    # blocks A and B overlap (both hold voxel 5); an added voxel goes to the nearest keyframe's block
    keys = lambda *xs: np.sort(pack_keys(np.array([[x, 0, 0] for x in xs])))  # noqa: E731
    res = SimpleNamespace(block_keys={"A": keys(1, 5), "B": keys(5, 9)},
                          block_keyframes={"A": np.array([[0.0, 0, 0]]), "B": np.array([[10.0, 0, 0]])})
    owned = B.block_truth(keys(5, 9), keys(18), res, 0.5)  # removed 5 and 9; added at x = 9.25 m
    assert list(owned["A"]) == list(keys(5))  # the removed voxel in both blocks' files: both changed
    assert list(owned["B"]) == list(keys(5, 9, 18))

def _store(root, files: dict, lifelong=None):
    root.mkdir()
    entries = []
    for bid, data in files.items():
        name = f"{bid}.pcd" if lifelong is None or bid not in lifelong["changed_blocks"] else f"{bid}.v2.pcd"
        (root / name).write_bytes(data)
        entries.append({"id": bid, "file": name, "bytes": len(data)})
    man = {"entries": entries}
    if lifelong is not None:
        man["lifelong"] = lifelong
    (root / "manifest.json").write_text(json.dumps(man))
    return root


def test_update_cost_hashes_the_unchanged_blocks(tmp_path):
    old = _store(tmp_path / "old", {"000": b"a" * 100, "001": b"b" * 100, "002": b"c" * 100})
    new = _store(tmp_path / "new", {"000": b"a" * 100, "001": b"B" * 90, "002": b"x" * 100},
                 {"changed_blocks": ["001"], "held_back": [{"block": "002"}]})
    fresh = _store(tmp_path / "fresh", {"000": b"a" * 95, "001": b"b" * 95, "002": b"c" * 100})
    c = B.update_cost(old, new, fresh, 10.0, 4.0)
    # 000 kept its bytes; 002 was not rebuilt yet its bytes differ: reported, not hidden
    assert c["unchanged_identical"] == 1 and c["unchanged_differ"] == ["002"]
    assert c["bytes_updated"] == 290 and c["bytes_fresh"] == 290 and c["bytes_stale"] == 300
    assert c["wall_per_block_s"] == 10.0 and c["cpu_per_block_s"] == 4.0 and c["held_back"] == 1


def test_where_the_false_detections_lie():
    from types import SimpleNamespace

    from blockloc.maps.changes.detect import voxel_keys

    class Volumes:  # one crown: a ball of 2 m radius, its centre 5 m up (world frame, z up)
        center, radii = np.array([[0.0, 0.0, 5.0]]), np.array([[2.0, 2.0, 2.0]])

        def __len__(self):
            return 1

    vol = Volumes()
    terrain = SimpleNamespace(height=lambda x, y: np.full(np.shape(x), 1.0))
    seq = SimpleNamespace(world=SimpleNamespace(volumes=vol, terrain=terrain))
    # map frame = world (x, -y, -z), terrain 1 m up: in the crown; 0.25 m above the terrain;
    # 3.25 m and 0.75 m above it
    pts = np.array([[0.2, 0.2, -5.2], [10.2, 0.2, -1.2], [10.2, 0.2, -4.2], [20.2, 5.2, -1.6]])
    w = B.where_voxels(seq, voxel_keys(pts, 0.5), 0.5)
    assert w == {"vegetation": 1, "ground": 1, "other": 2}


def test_kept_maps_are_keyed_on_the_builder_that_made_them(monkeypatch):
    """A map (and every run on it) kept in --work is filed under a key of the map builder's code and
    the map settings ``map build`` reads: a map built with the nominal LiDAR mounting (an older
    builder's default) is never reused once the builder estimates it."""
    import dataclasses

    import blockloc.app.catalog as catalog

    k1 = B.cache_keys("tiny", 1, 4)
    assert k1 == B.cache_keys("tiny", 1, 4)  # stable: the same code and settings, the same key
    assert B.cache_keys("tiny", 2, 4)["builder"] != k1["builder"]
    assert B.cache_keys("tiny", 1, 2)["builder"] == k1["builder"]  # the stride is not the builder's
    assert B.cache_keys("tiny", 1, 2)["update"] != k1["update"]
    real = catalog.config_for_sequence

    def nominal(name):
        cfg = real(name)
        return dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, calibrate_mounting=False))

    monkeypatch.setattr(catalog, "config_for_sequence", nominal)
    k2 = B.cache_keys("tiny", 1, 4)
    assert k2["builder"] != k1["builder"] and k2["update"] != k1["update"]
    # the builder's code: a change to the mounting estimate is a new key
    monkeypatch.setattr(catalog, "config_for_sequence", real)
    monkeypatch.setattr(B, "BUILDER_MODULES", tuple(m for m in B.BUILDER_MODULES if m != "blockloc.maps.mounting"))
    assert B.cache_keys("tiny", 1, 4)["builder"] != k1["builder"]


def test_segment_errors_and_the_worst_tenth_against_the_stale_map(tmp_path, monkeypatch):
    """Per-stretch RMS position error of a run against its session's truth, and the table's
    "worst tenth vs stale": the largest stretch-wise excess over the stale map's run."""
    from types import SimpleNamespace

    import blockloc.app.catalog as catalog
    from blockloc.geometry import Trajectory
    from blockloc.trajectory_io import write_tum

    stamps = np.arange(20) * 0.1
    truth = np.repeat(np.eye(4)[None], 20, axis=0)
    truth[:, 0, 3] = stamps
    monkeypatch.setattr(catalog, "open_sequence",
                        lambda name, **kw: SimpleNamespace(ground_truth=lambda: Trajectory(stamps, truth)))
    est = truth.copy()
    est[10:, 1, 3] = 0.05  # the second half 5 cm off to the side
    (tmp_path / "run").mkdir()
    write_tum(tmp_path / "run" / "poses.tum", Trajectory(stamps, est))
    seg = B.segment_errors("tiny", 1, "loc_m12", tmp_path / "run", parts=2)
    assert seg == pytest.approx([0.0, 0.05])
    r = {"preset": "tiny", "seed": 1, "stride": 4, "frames": 0, "load1_start": 1.0, "load1_end": 1.0, "wall_s": 60,
         "loc": {name: {"ate_trans_rmse_m": 0.03, "ate_rot_rmse_deg": 0.1, "failures": 0, "rejected": 0,
                        "frames": 20, "segments": s} for name, s in
                 (("stale", [0.02, 0.03]), ("updated", [0.01, 0.05]), ("fresh", [0.02, 0.02]))},
         "mapping_error": {"map": 0.06, "map_m12": 0.05}}
    args = SimpleNamespace(sessions="loc_m12", parts="loc", dynamic=False)
    text = "\n".join(B.render(r, args, [], "test machine", []))
    assert "| updated | 0.030 | 0.10 | 0 | 0 | 20 | +0.020 |" in text
    assert "| fresh | 0.030 | 0.10 | 0 | 0 | 20 | +0.000 |" in text and "| stale | 0.030 | 0.10 | 0 | 0 | 20 | - |" in text
    assert "(`map`) 0.060 m, fresh (`map_m12`) 0.050 m" in text


def test_the_fresh_map_with_the_stale_maps_mapping_error(tmp_path):
    """``map_m12`` drives the mapping route on the same clock as ``map``: its truth agrees pose for
    pose, so the month-0 mapping poses stamped on the 12-month day are map_m12's truth carrying the
    stale map's mapping error (and not map_m12's own, which differs)."""
    from blockloc.app.catalog import open_sequence
    from blockloc.trajectory_io import read_tum

    m0, m12 = open_sequence("sim:tiny/map@1"), open_sequence("sim:tiny/map_m12@1")
    got = read_tum(B.same_error_poses("tiny", 1, tmp_path / "p.tum"))
    own = m12.mapping_poses()
    np.testing.assert_allclose(got.stamps, own.stamps, atol=1e-5)
    np.testing.assert_allclose(got.poses, m0.mapping_poses().poses, atol=1e-6)
    err = lambda P: np.linalg.norm(P[:, :3, 3] - m12.ground_truth().interpolate(got.stamps)[:, :3, 3], axis=1)  # noqa: E731
    e_same, e_own = err(got.poses), err(own.poses)
    assert 0.01 < np.sqrt(np.mean(e_same ** 2)) and np.abs(e_same - e_own).max() > 0.01


def test_a_given_run_is_scored_alone(tmp_path):
    # --run scores one given run on its --map: nothing built or tracked, so detect only
    for bad in (["--run", "r"], ["--run", "r", "--map", "m"], ["--run", "r", "--map", "m", "--parts", "detect",
                                                                "--sessions", "loc_m3,loc_m12"]):
        with pytest.raises(SystemExit) as e:
            B.main([*bad, "--work", str(tmp_path)])
        assert e.value.code == 2


def test_the_track_part_gives_the_detectors_cost_per_frame_and_per_scan():
    """``--parts track``: the cost changes.json records while tracking (p50 / p99 / max per frame
    tracked and per scan used, the frames blocks joined on, the classification at the end)."""
    from types import SimpleNamespace

    st = lambda a, b, c: {"p50": a, "p99": b, "max": c}  # noqa: E731
    t = {"frames": 200, "stride": 4, "scans_used": 41, "scans_rejected": 0, "load_1min": 2.0,
         "per_frame_cpu_ms": st(0.3, 31.6, 204), "per_frame_wall_ms": st(0.4, 40.0, 250),
         "per_scan_cpu_ms": st(24.3, 110.0, 163), "per_scan_wall_ms": st(30.0, 120.0, 170),
         "per_scan_no_join_cpu_ms": st(24.0, 60.0, 70), "join_frames": 2, "join_cpu_ms": st(150.0, 200.0, 204),
         "update_ms_median": 4.3, "update_ms_p99": 8.9, "wall_s": 4.0, "cpu_s": 2.9, "final_wall_s": 1.6,
         "final_cpu_s": 1.58, "wall_ms_per_frame_tracked": 20.0, "cpu_ms_per_frame_tracked": 14.7,
         "process_wall_s": 30.0, "process_cpu_s": 11.0, "blocks_loaded": 2, "blocks_in_map": 2}
    r = {"preset": "tiny", "seed": 1, "stride": 4, "frames": 0, "load1_start": 1.0, "load1_end": 1.0, "wall_s": 60,
         "track": t}
    args = SimpleNamespace(sessions="loc_m12", parts="track", dynamic=False, detect_frames=200)
    text = "\n".join(B.render(r, args, [], "test machine", []))
    assert "`python -m bench.lifelong --preset tiny --seed 1 --stride 4 --parts track --detect-frames 200`" in text
    assert "| detection CPU per frame tracked | 0.3 ms | 31.6 ms | 204 ms | 0.4 / 40.0 ms |" in text
    assert "| detection CPU per scan used | 24.3 ms | 110.0 ms | 163 ms | 30.0 / 120.0 ms |" in text
    assert "| ... the 2 frames blocks joined on | 150.0 ms | 200.0 ms | 204 ms | - |" in text
    assert "| the classification at the end | 1.60 s | 1.58 s |" in text and "2 of the map's 2" in text


def test_update_groups_and_their_names():
    """``--update-from`` repeats, '+' joins the runs of one update; the default keeps its old names."""
    import argparse

    assert B._update_group("loc_m3+map_m12") == "loc_m3+map_m12" and B._update_group("map_m12+map_m12") == "map_m12"
    with pytest.raises(argparse.ArgumentTypeError, match="loc_m4"):
        B._update_group("loc_m4")
    assert B._group_tag("loc_m3") == "" and B._group_tag("loc_m3+map_m12") == "_loc_m3_map_m12"


def test_where_the_updated_map_trails_the_fresh_one(tmp_path, monkeypatch):
    """Per tenth of loc_m12: the stale map's blocks it drives in, what the update did to each, and
    the true changes in the sensor's reach; rendered beside each tenth's error against the fair fresh map."""
    from types import SimpleNamespace

    import blockloc.app.catalog as catalog
    import blockloc.maps.store as store_mod
    import blockloc.sim.changes as sim_changes
    from blockloc.geometry import Trajectory
    from blockloc.trajectory_io import write_tum

    stamps = np.arange(20) * 0.1
    truth = np.repeat(np.eye(4)[None], 20, axis=0)
    truth[:, 0, 3] = stamps * 100  # 0 .. 190 m along x
    monkeypatch.setattr(catalog, "open_sequence",
                        lambda name, **kw: SimpleNamespace(ground_truth=lambda: Trajectory(stamps, truth)))
    entries = {"A": np.array([[0.0, 0, 0]]), "B": np.array([[100.0, 0, 0]]), "C": np.array([[180.0, 0, 0]])}
    monkeypatch.setattr(store_mod, "open_map", lambda p: SimpleNamespace(
        ids=list(entries), entry=lambda b: SimpleNamespace(keyframes=entries[b], centroid=entries[b][0])))
    # one change: a wall 150-151 m along, 5 m aside (map frame): within 40 m of 120 m and on, not of 110 m
    change = SimpleNamespace(kind="wall_added", box_map=lambda: [150.0, 151.0, 5.0, 6.0, -3.0, 0.0])
    monkeypatch.setattr(sim_changes, "open_session", lambda P, s, S: SimpleNamespace(changes=lambda: [change]))
    upd = tmp_path / "upd"
    upd.mkdir()
    (upd / "manifest.json").write_text(json.dumps({"lifelong": {"changed_blocks": ["B"], "held_back": [
        {"block": "B", "weak_voxels": 3}, {"block": "C", "weak_voxels": 9}]}}))
    (tmp_path / "run").mkdir()
    write_tum(tmp_path / "run" / "poses.tum", Trajectory(stamps, truth))
    w = B.where_worse("small", 1, tmp_path / "map", upd, tmp_path / "run", parts=10)
    assert w[0] == {"blocks": {"A": "-"}, "changes_in_reach": 0, "change_kinds": []}
    assert w[5]["blocks"] == {"B": "changed"}  # 100 and 110 m: B's, which the update rebuilt
    assert w[9]["blocks"] == {"C": "held back"}  # held back, never rebuilt
    near = [k for k, x in enumerate(w) if x["changes_in_reach"]]
    assert near == [6, 7, 8, 9] and w[7]["change_kinds"] == ["wall_added"]
    seg = lambda v: {"ate_trans_rmse_m": 0.03, "ate_rot_rmse_deg": 0.1, "failures": 0, "rejected": 0,  # noqa: E731
                     "frames": 20, "segments": [v] * 10}
    r = {"loc": {"stale": seg(0.05), "updated": seg(0.04), "fresh": seg(0.02),
                 "fresh_same_error, the stale map's mapping error": seg(0.03)}, "where": {"loc_m3": w}}
    text = "\n".join(B._where_lines(r))
    assert "| 7 | 0.050 | 0.040 | 0.020 | 0.030 | +0.010 | B (changed) | 1 (wall_added) |" in text
    assert "| 1 | 0.050 | 0.040 | 0.020 | 0.030 | +0.010 | A (-) | 0 (-) |" in text


def test_a_removed_truth_voxel_still_filled_today_is_told_apart():
    """The removed truth scored beside the truth: a voxel today's returns fill in half of the scans
    that see it or more (a fence the removed car stood against) is still filled."""
    seen = (np.array([1, 2, 3, 4]), np.array([4, 4, 4, 0]))
    occupied = (np.array([1, 2, 4]), np.array([3, 1, 2]))
    got = B.still_filled(np.array([1, 2, 3, 4, 5]), seen, occupied)
    assert got.tolist() == [True, False, False, True, False]  # 3 of 4; 1 of 4; never; hit, rays not counted
