"""Change detection (``blockloc.maps.changes``) on a small synthetic world with known changes:
a wall removed, a box added, a pedestrian crossing (``tests/maps/lifelong_world.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.maps.changes.detect import (Evidence, cluster_sizes, pack_keys, ray_free_keys, ray_margins,
                                          unpack_keys, without_lowest)
from blockloc.maps.changes.pipeline import detect_changes
from blockloc.maps.changes.runs import read_run, trusted_mask
from tests.maps import lifelong_world as W


def _centres(keys, voxel_m):
    return (unpack_keys(keys) + 0.5) * voxel_m


def _inside(c, box, pad=0.6):
    x0, x1, y0, y1, z0, z1 = box
    return ((c[:, 0] > x0 - pad) & (c[:, 0] < x1 + pad) & (c[:, 1] > y0 - pad) & (c[:, 1] < y1 + pad)
            & (c[:, 2] > z0 - pad) & (c[:, 2] < z1 + pad))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    d = tmp_path_factory.mktemp("lifelong")
    T = W.drive(1.0)
    store = W.build_map(d / "map", T)
    return d, T, store


@pytest.fixture(scope="module")
def detected(world):
    d, T, store = world
    run = W.write_run(d / "run", d / "seq", T, ["ok"] * len(T))
    return detect_changes(store, W.ArraySequence("run", T), read_run(run, settle_frames=0))


def test_keys_round_trip_and_rays():
    ijk = np.array([[0, 0, 0], [-5, 7, -1], [100000, -100000, 3]])
    np.testing.assert_array_equal(unpack_keys(pack_keys(ijk)), ijk)
    free = ray_free_keys(np.zeros(3), np.array([[10.0, 0.2, 0.2]]), 0.5, 1.0)
    got = unpack_keys(free)
    # the ray crosses x voxels 0..17 (stops 1 m short of x = 10), never the endpoint's
    assert got[:, 0].min() == 0 and got[:, 0].max() == 17 and (got[:, 1:] == 0).all()
    # a ray ending on the ground far away stops marking free space far short of it
    m = ray_margins(np.zeros(3), np.array([[20.0, 0, -1.2], [5.0, 0, 3.0]]), np.array([0, 0, 1.0]), 1.0)
    assert m[0] == pytest.approx(0.3 / (1.2 / np.hypot(20, 1.2))) and m[1] == 1.0
    assert list(cluster_sizes(pack_keys(np.array([[0, 0, 0], [1, 1, 1], [5, 5, 5]])))) == [2, 2, 1]


def test_the_ground_surface_is_never_carvable():
    # two columns: cells 5, 6, 9 and 3, 4 along z; the map frame's up is -z (NCLT) or +z
    k = np.sort(pack_keys(np.array([[0, 0, 5], [0, 0, 6], [0, 0, 9], [1, 0, 3], [1, 0, 4]])))
    down = unpack_keys(without_lowest(k, np.array([0, 0, -1.0])))
    assert sorted(map(tuple, down)) == [(0, 0, 5), (0, 0, 6), (1, 0, 3)]
    up = unpack_keys(without_lowest(k, np.array([0, 0, 1.0])))
    assert sorted(map(tuple, up)) == [(0, 0, 6), (0, 0, 9), (1, 0, 4)]


def test_one_scan_never_decides():
    ev = Evidence(0.5, 1.0)
    wall = np.c_[np.full(50, 10.0), np.linspace(-2, 2, 50), np.zeros(50)]
    ev.add_scan(np.zeros(3), wall)
    L = ev.logodds(0.85, -0.4)
    assert ev.scans == 1 and L.max() == pytest.approx(0.85) and L.min() == pytest.approx(-0.4)


def test_trusted_frames_skip_what_follows_a_loss():
    st = ["ok"] * 5 + ["lost", "recovered"] + ["ok"] * 5
    m = trusted_mask(st, 2)
    assert m.tolist() == [False, False, True, True, True, False, False, False, False, True, True, True]


def test_detects_the_removed_wall_and_car_the_added_box_and_the_pedestrian(detected):
    res = detected
    vc = res.voxels
    rm, ad, dy = (_centres(k, vc.voxel_m) for k in (vc.removed, vc.added, vc.dynamic))
    assert res.scans_used == len(W.drive(1.0)) and res.scans_rejected == 0
    # removed: the wall and the parked car, nothing else
    in_wall, in_car = _inside(rm, W.WALL_W), _inside(rm, W.CAR_C)
    assert in_wall.sum() >= 40 and in_car.sum() >= 10 and (in_wall | in_car).all()
    # the car's lowest metre too (the ground's voxel and its neighbour above; half-metre voxels)
    assert (rm[in_car, 2] < 1.0).sum() >= 4
    # added: the box and nothing else, down to its lowest metre (which shares voxels with the
    # map's ground, or touches them)
    assert len(ad) >= 20 and _inside(ad, W.BOX_B).all()
    assert (ad[:, 2] < 1.0).sum() >= 6
    # the pedestrian is dynamic, never added; nothing of the static world is
    ped = np.abs(dy[:, 0] - W.PED_X) < 1.0
    assert ped.sum() >= 10
    # the rest is the ground the car hid, seen in some scans and crossed by rays just above it in
    # others (a voxel off the map has no fine cells to tell the two apart): only reported
    assert (_inside(dy[~ped], W.CAR_C, 0.5) & (dy[~ped, 2] < 0.5)).all()
    ped_box = (W.PED_X - 0.3, W.PED_X + 0.3, -9, 9, 0, 1.7)
    assert not _inside(ad, ped_box).any()
    by = {b["block"]: b for b in res.blocks}
    # the wall is in block 001 (x >= 0), the box in block 000 (x < 0)
    assert by["000"]["added_voxels"] == len(ad) and by["001"]["added_voxels"] == 0
    assert by["001"]["removed_voxels"] == len(rm) and by["001"]["removed_points"] > 0
    assert by["000"]["removed_voxels"] == 0
    assert all(b["confirmed"] for b in res.blocks) and 0.9 < by["001"]["confidence"] <= 1.0


def test_an_unchanged_day_shows_no_change(world):
    d, T, store = world
    run = W.write_run(d / "same", d / "seq", T, ["ok"] * len(T))
    res = detect_changes(store, W.ArraySequence("map", T), read_run(run, settle_frames=0))
    assert len(res.voxels.removed) == 0 and len(res.voxels.added) == 0
    assert not any(b["confirmed"] for b in res.blocks)


def test_wrong_poses_are_gated_or_skipped(world):
    d, T, store = world
    Tb = T.copy()
    Tb[:, 0, 3] += 1.4
    Tb[:, 1, 3] += 1.4  # 2 m off
    # marked ok: the consistency gate drops every scan
    run = W.write_run(d / "bad_ok", d / "seq", Tb, ["ok"] * len(T))
    res = detect_changes(store, W.ArraySequence("run", T), read_run(run, settle_frames=0))
    assert res.scans_used == 0 and res.scans_rejected == len(T)
    assert len(res.voxels.removed) == 0 and len(res.voxels.added) == 0
    # marked as a relocalization and its aftermath: never read
    st = ["recovered"] * len(T)
    run = W.write_run(d / "bad_reloc", d / "seq", Tb, st)
    assert len(read_run(run)) == 0
