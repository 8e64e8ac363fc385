"""Map update and versions (``blockloc.maps.changes.update`` / ``.versions``), the safety of an
update against wrong poses, and every new command as a user types it."""

from __future__ import annotations

import hashlib
import json
import re
import subprocess

import numpy as np
import pytest

from blockloc.errors import MapError
from blockloc.maps.changes import versions
from blockloc.maps.changes.pipeline import detect_changes
from blockloc.maps.changes.runs import read_run
from blockloc.maps.changes.update import apply_update, plan_update
from blockloc.maps.store import open_map
from tests.maps import lifelong_world as W

STEP = 2.0  # a scan every 2 m: 25 scans along the street


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _entries(root):
    return {e["id"]: e for e in json.loads((root / "manifest.json").read_text())["entries"]}


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tmp_path_factory.mktemp("update")
    T = W.drive(STEP)
    W.build_map(d / "map", T)
    W.write_scan_folder(d / "nowall", "nowall", T)
    W.write_scan_folder(d / "same", "map", T)
    return d, T


def _result(d, T, day, name, poses=None, status=None):
    run = W.write_run(d / name, d / day, T if poses is None else poses, status or ["ok"] * len(T))
    return detect_changes(open_map(d / "map"), W.ArraySequence(day if day != "same" else "map", T),
                          read_run(run, settle_frames=0)), run


def test_update_rebuilds_only_the_changed_block(base, tmp_path):
    d, T = base
    res, run = _result(d, T, "nowall", "run_nowall")
    plan = plan_update([res], strong_scans=10)
    assert list(plan.blocks) == ["001"]  # the wall stood at x 2..10
    before = _entries(d / "map")
    rec = apply_update(d / "map", plan, [res], runs=[str(run)], out=tmp_path / "map2")
    assert rec["version"] == 2 and rec["changed_blocks"] == ["001"]
    after = _entries(tmp_path / "map2")
    # the unchanged block: same entry, same file, same bytes
    assert after["000"] == before["000"]
    assert _sha(tmp_path / "map2" / after["000"]["file"]) == _sha(d / "map" / "000.pcd") == before["000"]["sha256"]
    # the changed block: a new file, the wall's points gone, the rest kept
    assert after["001"]["file"] == "001.v2.pcd" and (tmp_path / "map2" / "001.pcd").exists()
    old, _ = open_map(d / "map").load("001")
    new, _ = open_map(tmp_path / "map2").load("001")

    def in_wall(p):  # above the lowest 0.6 m: the ground's voxels there are not carved (docs/lifelong.md)
        x0, x1, y0, y1, z0, z1 = W.WALL_W
        return (p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 1] > y0 - 0.1) & (p[:, 1] < y1 + 0.1) & (p[:, 2] > 0.6)

    # all but a few points of voxels held back (seen by fewer than 10 scans: the wall's far corners)
    assert in_wall(old).sum() > 200 and in_wall(new).sum() <= 0.02 * in_wall(old).sum()
    assert len(new) > 0.95 * (len(old) - in_wall(old).sum())

    def behind(p):  # the ground the wall hid from the street on the mapping day
        return (p[:, 0] > 3) & (p[:, 0] < 9) & (p[:, 1] > 6.6) & (p[:, 1] < 10.5) & (p[:, 2] < 0.3)

    # the removal revealed it: the update takes the run's points there (a fresh map holds them)
    gained = behind(new).sum() - behind(old).sum()
    assert gained >= 0.2 * behind(old).sum() and rec["blocks"]["001"]["new_points"] > 0
    # without the revealed points (reveal_m 0) the block gains nothing there
    plan0 = plan_update([res], strong_scans=10, reveal_m=0.0)
    apply_update(d / "map", plan0, [res], runs=[str(run)], out=tmp_path / "map0")
    assert behind(open_map(tmp_path / "map0").load("001")[0]).sum() == behind(old).sum()
    # the source map is untouched (no --out: in place)
    assert _entries(d / "map") == before and not (d / "map" / "versions").exists()
    # detection against the updated map finds the day unchanged
    again = detect_changes(open_map(tmp_path / "map2"), W.ArraySequence("nowall", T),
                           read_run(run, settle_frames=0))
    assert len(again.voxels.removed) == 0


def test_weak_evidence_is_held_back(base):
    d, T = base
    res, _ = _result(d, T, "nowall", "run_weak")
    plan = plan_update([res], strong_scans=10_000)  # one run never enough
    assert plan.blocks == {} and any(h["block"] == "001" for h in plan.held_back)
    plan2 = plan_update([res, res], strong_scans=10_000)  # two runs are
    assert list(plan2.blocks) == ["001"]


def test_versions_and_rollback(base, tmp_path):
    d, T = base
    import shutil

    shutil.copytree(d / "map", tmp_path / "m")
    root = tmp_path / "m"
    v1_manifest = (root / "manifest.json").read_bytes()
    res, run = _result(d, T, "nowall", "run_versions")
    rec = apply_update(root, plan_update([res], strong_scans=10), [res], runs=[str(run)])
    assert versions.current_version(root) == 2
    hist = versions.history(root)
    assert [h["version"] for h in hist] == [1, 2] and hist[1]["parent"] == 1 and hist[1]["current"]
    assert hist[1]["changed_blocks"] == ["001"] and hist[1]["runs"] == [str(run)]
    assert open_map(root).entry("001").file == "001.v2.pcd"
    versions.rollback(root, 1)
    assert versions.current_version(root) == 1 and open_map(root).entry("001").file == "001.pcd"
    assert json.loads((root / "manifest.json").read_bytes())["entries"] == json.loads(v1_manifest)["entries"]
    versions.rollback(root, 2)  # forward again: nothing was deleted
    assert open_map(root).entry("001").file == "001.v2.pcd" and rec["version"] == 2
    with pytest.raises(MapError, match="--to 7"):
        versions.rollback(root, 7)


@pytest.mark.parametrize("status", ["recovered", "ok"])
def test_a_wrong_segment_does_not_change_the_map(base, status):
    """The day is unchanged; frames 5..16 of the run are 2 m off, marked as just relocalized (then
    skipped by their status and the frames after them) or marked ok (then dropped by the
    consistency gate). Nothing is applied."""
    d, T = base
    P = T.copy()
    P[5:17, 0, 3] += 1.4
    P[5:17, 1, 3] -= 1.4
    st = ["ok"] * len(T)
    st[5] = status
    res, _ = _result(d, T, "same", f"run_wrong_{status}", poses=P, status=st)
    if status == "ok":
        assert res.scans_rejected >= 10
    plan = plan_update([res, res], strong_scans=1)  # even the weakest rule applies nothing
    assert plan.blocks == {} and len(plan.removed) == 0 and len(plan.added) == 0


# --------------------------------------------------------------------------- the commands

def _cli(*args):
    return subprocess.run(["blockloc", *map(str, args)], capture_output=True, text=True)


def test_cli_changes_update_info_rollback(base, tmp_path):
    d, T = base
    import shutil

    shutil.copytree(d / "map", tmp_path / "map")
    m = tmp_path / "map"
    run1 = W.write_run(tmp_path / "run1", d / "nowall", T, ["ok"] * len(T))
    run2 = W.write_run(tmp_path / "run2", d / "nowall", T, ["ok"] * len(T))
    r = _cli("map", "changes", "--map", m, "--run", run1)
    assert r.returncode == 0, r.stderr
    doc = json.loads((run1 / "changes.json").read_text())
    assert doc["sequence"] == str(d / "nowall") and doc["totals"]["removed_voxels"] > 20
    assert {b["block"]: b["confirmed"] for b in doc["blocks"]} == {"000": False, "001": True}
    sha_000 = _sha(m / "000.pcd")
    r = _cli("map", "update", m, "--run", run1, "--run", run2)
    assert r.returncode == 0, r.stderr
    assert "version 2" in r.stdout and "block 001" in r.stdout
    # the line adds up: before - removed + added = after (it showed "added 0 voxels" beside a
    # block that grew: the points seen behind what was removed were not counted anywhere)
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("block 001:"))
    mt = re.match(r"block 001: removed (\d+) voxels \((\d+) points\), added (\d+) voxels; (\d+) points added "
                 r"\(in added voxels and seen behind removed ones\), (\d+) -> (\d+) points$", line)
    assert mt, line
    _, p_rm, _, p_add, before, after = map(int, mt.groups())
    assert p_rm > 0 and before - p_rm + p_add == after == open_map(m).entry("001").num_points
    assert open_map(m).entry("000").sha256 == sha_000 and open_map(m).entry("001").file == "001.v2.pcd"
    r = _cli("map", "info", m, "--quick")
    assert r.returncode == 0 and "* v2 (parent v1)" in r.stdout and "blocks 001" in r.stdout
    r = _cli("map", "info", m, "--quick", "--json")
    assert [v["version"] for v in json.loads(r.stdout)["versions"]] == [1, 2]
    r = _cli("map", "rollback", m, "--to", "1")
    assert r.returncode == 0 and open_map(m).entry("001").file == "001.pcd"
    r = _cli("map", "rollback", m, "--to", "9")
    assert r.returncode == 2 and r.stderr.strip().startswith("error: --to 9") and "Traceback" not in r.stderr
    r = _cli("map", "changes", "--map", m, "--run", tmp_path / "nope")
    assert r.returncode == 2 and "error: --run" in r.stderr and "poses.tum" in r.stderr
    r = _cli("map", "update", m, "--run", run1, "--out", d / "nowall")
    assert r.returncode == 2 and "already exists" in r.stderr


def _tracked_in(run, map_path):
    """Record in ``run``'s metrics.json the map it was tracked in, as ``blockloc track`` does."""
    metrics = run / "metrics.json"
    metrics.write_text(json.dumps({**json.loads(metrics.read_text()), "map": str(map_path)}))


def test_cli_a_sequence_shorter_than_the_run_is_refused_before_any_work(base, tmp_path):
    """``--seq`` with fewer scans than the run tracked (another recording, a cut copy): one line
    naming --seq, its scan count and the run's frame count, exit 2, nothing detected nor written
    (it was an IndexError, exit 1, once the detection reached the first frame past its end)."""
    import shutil

    d, T = base
    shutil.copytree(d / "map", tmp_path / "map")
    m = tmp_path / "map"
    short = W.write_scan_folder(tmp_path / "short", "nowall", T[:12])
    run = W.write_run(tmp_path / "run", d / "nowall", T, ["ok"] * len(T))
    _tracked_in(run, m)
    manifest = (m / "manifest.json").read_bytes()
    r = _cli("map", "changes", "--map", m, "--run", run, "--seq", short)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0] == (f"error: --seq {short}: 12 scans, fewer than the {len(T)} frames the run {run} tracked "
                        "(expected the sequence it was tracked on)"), lines
    assert not (run / "changes.json").exists()
    # update: the second run's sequence checked before the first run is detected
    r = _cli("map", "update", m, "--run", run, "--run", run, "--seq", d / "nowall", "--seq", short)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"error: --seq {short}: 12 scans"), r.stderr
    assert (m / "manifest.json").read_bytes() == manifest and not (m / "versions").exists()
    # the sequence the run records, cut since: named as the run's
    cut = W.write_run(tmp_path / "run_cut", short, T, ["ok"] * len(T))
    _tracked_in(cut, m)
    r = _cli("map", "changes", "--map", m, "--run", cut)
    assert r.returncode == 2 and r.stderr.strip() == (
        f"error: --run {cut}: its sequence {short}: 12 scans, fewer than the {len(T)} frames the run {cut} "
        "tracked (expected the sequence it was tracked on)"), r.stderr


def test_served_clients_pick_up_a_new_version_when_they_open_the_map_again(base, tmp_path):
    """``map serve`` reads files per request: a client that opens the map after an update (or a
    rollback) gets that version; one still holding the old version reads its old block files
    (a version's files are never rewritten)."""
    import shutil

    from blockloc.maps.server import MapServer

    d, T = base
    shutil.copytree(d / "map", tmp_path / "m")
    root = tmp_path / "m"
    res, run = _result(d, T, "nowall", "run_served")
    with MapServer(root) as srv:
        old = open_map(srv.url, cache_dir=tmp_path / "cache")
        old_pts, _ = old.load("001")
        apply_update(root, plan_update([res], strong_scans=10), [res], runs=[str(run)])
        new = open_map(srv.url, cache_dir=tmp_path / "cache")
        assert new.entry("001").file == "001.v2.pcd" and new.entry("000").sha256 == old.entry("000").sha256
        assert len(new.load("001")[0]) < len(old_pts)
        np.testing.assert_array_equal(old.load("001")[0], old_pts)  # the old version still reads
        versions.rollback(root, 1)
        assert open_map(srv.url, cache_dir=tmp_path / "cache").entry("001").file == "001.pcd"


def test_the_place_index_is_rebuilt_for_the_new_version(base, tmp_path):
    import shutil

    from blockloc.global_init.place_index import (PlaceIndex, build_place_index, load_place_index,
                                                   write_place_index)

    d, T = base
    shutil.copytree(d / "map", tmp_path / "m")
    root = tmp_path / "m"
    g = np.array([0.0, 0.0, -9.81])
    _, idx1 = write_place_index(root, g)
    res, run = _result(d, T, "nowall", "run_index")
    apply_update(root, plan_update([res], strong_scans=10), [res], runs=[str(run)],
                 place_index=lambda staged: build_place_index(staged, g).to_bytes())
    store = open_map(root)
    assert store.extras["place_index.npz"].file == "place_index.v2.npz"
    idx2 = load_place_index(store, g, build_missing=False)
    fresh = build_place_index(store, g)  # what the new version's blocks give
    assert isinstance(idx2, PlaceIndex) and np.array_equal(idx2.bits, fresh.bits)
    assert not np.array_equal(idx2.bits, idx1.bits)  # the wall's bits are gone
    versions.rollback(root, 1)  # the old version keeps its own index
    assert load_place_index(open_map(root), g, build_missing=False).to_bytes() == idx1.to_bytes()


def test_the_app_recipe_updates_with_the_runs_sequence_and_config(base, tmp_path):
    """``blockloc.app.lifelong`` (what ``map update`` runs): the run's sequence opened from the name
    its metrics.json records, the config that fits it; the place index of the new version built
    with that config's ``global_init`` settings and the sequence's gravity."""
    import shutil

    from blockloc.app.assemble import place_index_params
    from blockloc.app.lifelong import detect_run_changes, open_block_store, update_map
    from blockloc.global_init.place_index import build_place_index, load_place_index, write_place_index

    d, T = base
    shutil.copytree(d / "map", tmp_path / "m")
    root = tmp_path / "m"
    run = W.write_run(tmp_path / "run", d / "nowall", T, ["ok"] * len(T))
    found = detect_run_changes(open_block_store(root), run)
    assert found.sequence_name == str(d / "nowall") and found.result.scans_used > 0
    g = np.asarray(found.sequence.info.gravity_map, float)
    params = place_index_params(found.config.global_init)
    write_place_index(root, g, params)
    rec = update_map(root, [found, found], runs=[str(run), str(run)])
    assert rec["version"] == 2 and rec["changed_blocks"] == ["001"]
    store = open_map(root)
    assert store.extras["place_index.npz"].file == "place_index.v2.npz"
    assert load_place_index(store, g, build_missing=False).to_bytes() == build_place_index(store, g, params).to_bytes()
    with pytest.raises(MapError, match="no run"):
        update_map(root, [], runs=[])


def test_the_app_recipe_places_scans_with_the_maps_mounting(base, tmp_path, monkeypatch):
    """Issue 41: ``track`` tracks with the LiDAR mounting the map's build estimated
    (``map.use_map_mounting``, default true), so ``map changes`` / ``update`` read the run's scans
    with that mounting too, not the sequence's nominal one; a map without an estimate leaves the
    sequence as it is."""
    import blockloc.app.lifelong as lifelong
    from blockloc.geometry import xyzrpy_to_T

    d, T = base
    run = W.write_run(tmp_path / "run", d / "nowall", T, ["ok"] * len(T))
    seen = []
    real = lifelong.detect_changes

    def spy(store, seq, *args, **kw):
        seen.append(seq)
        return real(store, seq, *args, **kw)

    monkeypatch.setattr(lifelong, "detect_changes", spy)
    store = open_map(d / "map")
    lifelong.detect_run_changes(store, run)
    nominal = np.asarray(seen[-1].info.T_body_lidar)
    X = xyzrpy_to_T(0.02, -0.01, 0.0, 0.0, 0.0, np.deg2rad(0.5)) @ nominal
    monkeypatch.setattr(store, "params", {**store.params, "mounting": {"map": {"T_body_lidar": X.tolist()}}})
    found = lifelong.detect_run_changes(store, run)
    assert np.allclose(seen[-1].info.T_body_lidar, X) and not np.allclose(X, nominal)
    assert found.result.scans_used > 0


def test_only_coherent_changes_are_applied_scattered_voxels_are_held_back():
    """Strong voxels are applied only inside a 26-connected change of ``min_change_m3`` or more (one
    changed object, the detector's rule for confirming a block); voxels scattered over the block
    (each seen free in many scans: false removals along a facade) never carve it."""
    from types import SimpleNamespace

    from blockloc.maps.changes.detect import pack_keys
    from blockloc.maps.changes.update import coherent

    wall = pack_keys(np.array([[i, 0, k] for i in range(10) for k in range(4)]))  # 40 voxels: 5 m^3
    lone = pack_keys(np.array([[30, 30, 0], [40, 0, 2], [50, 5, 1], [50, 7, 1]]))  # none touching another
    removed = np.unique(np.concatenate([wall, lone]))
    kept, _, scattered, _ = coherent(removed, removed[:0], 0.5, 3.0)
    assert np.array_equal(kept, np.sort(wall)) and np.array_equal(scattered, np.sort(lone))
    # removed and added voxels of one object count together (a car moved by half its length)
    car_rm = pack_keys(np.array([[i, 10, k] for i in range(3) for k in range(4)]))  # 12 voxels, 1.5 m^3
    car_ad = pack_keys(np.array([[i, 10, k] for i in range(3, 6) for k in range(4)]))
    rk, ak, _, _ = coherent(np.sort(car_rm), np.sort(car_ad), 0.5, 3.0)
    assert len(rk) == 12 and len(ak) == 12
    voxels = SimpleNamespace(voxel_m=0.5, removed=removed, removed_free=np.full(len(removed), 50),
                             added=np.zeros(0, np.int64), added_hits=np.zeros(0, np.int64))
    res = SimpleNamespace(voxels=voxels, block_keys={"000": removed}, block_keyframes={"000": np.zeros((1, 3))})
    plan = plan_update([res])
    assert np.array_equal(plan.removed, np.sort(wall)) and plan.blocks["000"]["scattered_voxels"] == 4
    assert any(h.get("scattered_voxels") == 4 and "coherent" in h["reason"] for h in plan.held_back)
    only_lone = SimpleNamespace(voxels=SimpleNamespace(**{**vars(voxels), "removed": np.sort(lone),
                                                          "removed_free": np.full(4, 50)}),
                                block_keys={"000": np.sort(lone)}, block_keyframes={"000": np.zeros((1, 3))})
    plan = plan_update([only_lone], min_block_voxels=1)
    assert plan.blocks == {} and len(plan.removed) == 0 and plan.held_back[0]["scattered_voxels"] == 4
    assert list(plan_update([only_lone], min_block_voxels=1, min_change_m3=0).blocks) == ["000"]  # rule off


def test_weak_voxels_joined_to_an_applied_change_are_applied_with_it():
    """Hysteresis: a removed wall's far end, seen through by too few scans alone, is applied with
    the wall it belongs to; weak voxels touching no applied change stay held back."""
    from types import SimpleNamespace

    from blockloc.maps.changes.detect import pack_keys
    from blockloc.maps.changes.update import grow

    wall = np.sort(pack_keys(np.array([[i, 0, k] for i in range(10) for k in range(4)])))  # strong: 5 m^3
    end = np.sort(pack_keys(np.array([[i, 0, k] for i in range(10, 13) for k in range(4)])))  # weak, touching
    apart = np.sort(pack_keys(np.array([[i, 20, k] for i in range(10) for k in range(4)])))  # weak, alone
    weak = np.union1d(end, apart)
    rm, ad, rm_left, ad_left = grow(wall, wall[:0], weak, wall[:0])
    assert np.array_equal(rm, np.union1d(wall, end)) and np.array_equal(rm_left, apart) and not len(ad)
    # through plan_update: one run, the wall's middle seen through in 30 scans, the rest in 6
    removed = np.unique(np.concatenate([wall, weak]))
    free = np.where(np.isin(removed, wall), 30, 6)
    voxels = SimpleNamespace(voxel_m=0.5, removed=removed, removed_free=free, added=np.zeros(0, np.int64),
                             added_hits=np.zeros(0, np.int64), dynamic=np.zeros(0, np.int64))
    res = SimpleNamespace(voxels=voxels, block_keys={"000": removed}, block_keyframes={"000": np.zeros((1, 3))})
    plan = plan_update([res])
    assert np.array_equal(plan.removed, np.union1d(wall, end)) and plan.grown == len(end)
    assert plan.blocks["000"]["held_back_voxels"] == len(apart)
    assert np.array_equal(plan_update([res], grow_weak=False).removed, wall)


def _yawed(T: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """T (N, 4, 4) with each rotation turned by yaw_rad (N,) about the map's z."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    Rz = np.zeros((len(T), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    out = T.copy()
    out[:, :3, :3] = Rz @ T[:, :3, :3]
    return out


def test_another_drive_of_the_mapping_day_confirms_no_block_and_updates_nothing(base, tmp_path):
    """Block precision where nothing changed (the bench's ``unchanged`` part, month 0's ``loc``
    drive, in small): another drive of the mapping day (1.5 m to the side, scans at other places)
    whose run poses carry tracking-sized errors (2 cm, 0.1 deg): ``map changes`` confirms no block
    and ``map update`` from it rebuilds nothing, even taking one run as evidence enough. The same drive on the day the wall is
    gone confirms the wall's block: the drive sees enough to find a change that is there."""
    import shutil

    d, T = base
    T2 = W.drive(STEP)
    T2[:, 0, 3] += 0.7
    T2[:, 1, 3] -= 1.5
    rng = np.random.default_rng(7)
    poses = _yawed(T2, np.deg2rad(rng.normal(0.0, 0.1, len(T2))))
    poses[:, :3, 3] += rng.normal(0.0, 0.02, (len(T2), 3))
    shutil.copytree(d / "map", tmp_path / "map")
    m = tmp_path / "map"
    W.write_scan_folder(tmp_path / "day0", "map", T2)
    run = W.write_run(tmp_path / "run", tmp_path / "day0", poses, ["ok"] * len(T2))
    r = _cli("map", "changes", "--map", m, "--run", run)
    assert r.returncode == 0, r.stderr
    doc = json.loads((run / "changes.json").read_text())
    assert doc["scans_used"] == len(T2) - 10 and doc["scans_rejected"] == 0  # trusted after 10 ok frames
    assert {b["block"]: b["confirmed"] for b in doc["blocks"]} == {"000": False, "001": False}
    gone = detect_changes(open_map(m), W.ArraySequence("nowall", T2),
                          read_run(W.write_run(tmp_path / "gone", tmp_path / "day0", poses, ["ok"] * len(T2))))
    assert gone.scans_used == doc["scans_used"]
    assert {b["block"]: b["confirmed"] for b in gone.blocks} == {"000": False, "001": True}
    before = _entries(m)
    # one run is evidence enough here (--min-runs 1: every detected voxel is strong): nothing to apply
    r = _cli("map", "update", m, "--run", run, "--min-runs", "1")
    assert r.returncode == 0, r.stderr
    assert "0 blocks rebuilt" in r.stdout
    after = _entries(m)
    assert all(after[b]["sha256"] == before[b]["sha256"] == _sha(m / after[b]["file"]) for b in before)
