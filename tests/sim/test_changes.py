"""The changing world (``blockloc.sim.changes``): later days with labelled structure changes."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess

import numpy as np
import pytest

from blockloc.datasets.nclt import NCLT_POINT_DTYPE, NcltSequence
from blockloc.errors import SimError
from blockloc.sim.changes import (LABEL_CHANGED, LABEL_MOVING, LABEL_STATIC, read_point_labels,
                                  sessions_for_months)
from blockloc.sim.changes import open_session as open_sim_sequence
from blockloc.sim.writer import generate_dataset

SEED, STEPS = 1, 60


def _tree_hashes(root):
    out = {}
    for dirpath, _, files in os.walk(root):
        for f in files:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, root)] = hashlib.sha256(open(p, "rb").read()).hexdigest()
    return out


def test_sessions_for_months():
    assert sessions_for_months((3, 12)) == ("loc_m3", "loc_m12", "map_m12")
    with pytest.raises(SimError, match="--months 5"):
        sessions_for_months((5,))


def test_changes_are_deterministic_and_grow_over_the_year():
    m3 = open_sim_sequence("small", "loc_m3", SEED, azimuth_steps=STEPS)
    m12 = open_sim_sequence("small", "loc_m12", SEED, azimuth_steps=STEPS)
    again = open_sim_sequence("small", "loc_m12", SEED, azimuth_steps=STEPS)
    k3 = {c.kind for c in m3.changes()}
    k12 = {c.kind for c in m12.changes()}
    assert {"construction_site", "hedge_cut", "parked_car"} <= k3 and "building_added" not in k3
    assert {"building_added", "building_removed", "wall_added", "hedge_cut"} <= k12
    assert "construction_site" not in k12  # the site became the building
    assert [c.to_json() for c in m12.changes()] == [c.to_json() for c in again.changes()]
    assert m12.info.name == f"sim:small/loc_m12@{SEED}" and m12.date != m3.date
    # same route as loc, another day: the trajectory is loc's, the scans are not
    loc = open_sim_sequence("small", "loc", SEED, azimuth_steps=STEPS)
    assert len(loc) == len(m12)
    np.testing.assert_allclose(loc.trajectory.T_map_body(np.array([5.0])), m12.trajectory.T_map_body(np.array([5.0])))


def test_labels_say_what_each_point_hit():
    seq = open_sim_sequence("small", "loc_m12", SEED, azimuth_steps=STEPS)
    added = [c for c in seq.changes() if c.kind == "building_added"][0]
    x0, x1, y0, y1, z0, z1 = added.box_map()
    counts = np.zeros(3, int)
    inside_changed = inside_total = 0
    gt = seq.ground_truth()
    for i in range(0, len(seq), 40):
        frame, lab = seq.frame_labels(i)
        assert lab.shape == (len(frame.points),) and lab.dtype == np.uint8
        counts += np.bincount(lab, minlength=3)
        T_map_lidar = gt.poses[np.searchsorted(gt.stamps, frame.stamp)] @ seq.info.T_body_lidar
        p = frame.points @ T_map_lidar[:3, :3].T + T_map_lidar[:3, 3]
        inside = ((p[:, 0] > x0 + 0.3) & (p[:, 0] < x1 - 0.3) & (p[:, 1] > y0 + 0.3) & (p[:, 1] < y1 - 0.3)
                  & (p[:, 2] > z0 + 0.3) & (p[:, 2] < z1 - 1.0))
        inside_total += int(inside.sum())
        inside_changed += int((lab[inside] == LABEL_CHANGED).sum())
    assert counts[LABEL_STATIC] > 10 * counts[LABEL_CHANGED] > 0 and counts[LABEL_MOVING] > 0
    # points inside the new building's box are (nearly all) labelled changed
    assert inside_total > 50 and inside_changed > 0.9 * inside_total


def test_written_sessions_carry_labels_and_leave_existing_bytes_alone(tmp_path):
    plain = generate_dataset("tiny", SEED, tmp_path / "plain", max_frames=3, azimuth_steps=STEPS)
    more = generate_dataset("tiny", SEED, tmp_path / "more", max_frames=3, azimuth_steps=STEPS, months=(3, 12))
    a, b = _tree_hashes(plain), _tree_hashes(more)
    for k, h in a.items():
        # sim.json and blockloc's ownership marker list the sessions and files: they differ
        if k not in ("sim.json", ".blockloc-output.json"):
            assert b[k] == h, k  # map/ and loc/ are byte-identical with the new sessions beside them
    meta = json.loads((more / "sim.json").read_text())
    assert sorted(meta["sessions"]) == ["loc", "loc_m12", "loc_m3", "map", "map_m12"]
    for s in ("loc_m3", "loc_m12", "map_m12"):
        seq = NcltSequence(more / s)
        assert len(seq) == 3
        doc = json.loads((more / s / "changes.json").read_text())
        assert doc["session"] == s and doc["changes"] and all(len(c["box_map"]) == 6 for c in doc["changes"])
        scans = sorted((more / s / "velodyne_sync").glob("*.bin"))
        assert len(scans) == 3
        for path in scans:  # one label per point of the scan file, in its order
            lab = read_point_labels(more / s, int(path.stem))
            assert lab.shape == (len(np.fromfile(path, dtype=NCLT_POINT_DTYPE)),)
    with pytest.raises(SimError, match="nclt format only"):
        generate_dataset("tiny", SEED, tmp_path / "bag", "rosbag1", max_frames=1, months=(3,))


def test_cli_sim_months(tmp_path):
    r = subprocess.run(["blockloc", "sim", "--preset", "tiny", "--out", str(tmp_path / "d"), "--azimuth-steps", "8",
                        "--months", "7"], capture_output=True, text=True)
    assert r.returncode == 2 and "error: --months 7" in r.stderr and not (tmp_path / "d").exists()
    r = subprocess.run(["blockloc", "sim", "--preset", "tiny", "--out", str(tmp_path / "d"), "--azimuth-steps", "8",
                        "--months", "3"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    d = tmp_path / "d"
    assert sorted(p.name for p in d.iterdir()) == [".blockloc-output.json", "loc", "loc_m3", "map", "sim.json"]
    scans = sorted((d / "loc_m3" / "velodyne_sync").glob("*.bin"))
    labels = sorted((d / "loc_m3" / "point_labels").glob("*.npy"))
    assert len(scans) == len(labels) > 100 and [p.stem for p in scans] == [p.stem for p in labels]
    assert json.loads((d / "loc_m3" / "changes.json").read_text())["month"] == 3


def test_sim_names_open_the_changed_days():
    from blockloc.app.catalog import SequenceRef, open_sequence

    seq = open_sequence("sim:tiny/loc_m12@3")
    assert seq.info.name == "sim:tiny/loc_m12@3" and len(seq) > 0
    # their default map is the mapping day's
    assert SequenceRef.parse("sim:tiny/loc_m12@3").mapping_source() == "sim:tiny/map@3"


def test_map_m12_carries_a_mapping_error_like_the_mapping_day():
    """The fresh reference map's drive is mapped as the mapping day was: a smooth offline-SLAM
    error of the preset's size, its own stream (not the mapping day's), the same for a seed."""
    def err(session, seed=SEED):
        seq = open_sim_sequence("tiny", session, seed)
        mp, gt = seq.mapping_poses(), seq.ground_truth()
        assert np.array_equal(mp.stamps, gt.stamps)
        return np.linalg.norm(mp.poses[:, :3, 3] - gt.poses[:, :3, 3], axis=1)

    e_map, e_m12, e_loc = err("map"), err("map_m12"), err("loc_m12")
    assert np.all(e_loc == 0)  # a localization day: ground truth
    # the same size of error (tiny preset: slam_error_m 0.03 per axis), not the same values
    assert 0.3 < np.sqrt(np.mean(e_m12 ** 2)) / np.sqrt(np.mean(e_map ** 2)) < 3.0 and e_m12.max() > 0.01
    n = min(len(e_map), len(e_m12))
    assert not np.allclose(e_map[:n], e_m12[:n])
    assert np.array_equal(err("map_m12"), e_m12)  # deterministic by seed
