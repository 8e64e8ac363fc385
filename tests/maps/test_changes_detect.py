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


def _crown_scans(stop_share: float, seed: int = 0):
    """A see-through 'crown' (a 1.2 m ball of map points 10 m ahead) and a wall behind it at
    x = 16; scans from 12 places along y, each ray towards the wall stopping inside the ball with
    ``stop_share`` (0: the crown is gone). Returns the evidence and the map's voxel keys."""
    from blockloc.maps.changes.detect import voxel_keys

    rng = np.random.default_rng(seed)
    ball = rng.normal(size=(1500, 3))
    ball = np.array([10.0, 0, 2.0]) + 1.2 * ball / np.linalg.norm(ball, axis=1)[:, None] * rng.uniform(0, 1, (1500, 1)) ** (1 / 3)
    gy, gz = np.meshgrid(np.arange(-6, 6, 0.25), np.arange(0, 4, 0.25))
    wall = np.c_[np.full(gy.size, 16.0), gy.ravel(), gz.ravel()]
    map_pts = np.concatenate([ball, wall])
    fine_m = 0.2
    map_keys = np.unique(voxel_keys(map_pts, 0.5))
    ev = Evidence(0.5, 1.0, fine=(map_keys, fine_m, np.unique(voxel_keys(map_pts, fine_m))))
    for y in np.linspace(-3, 3, 12):
        origin = np.array([0.0, y, 2.0])
        d = wall - origin
        d /= np.linalg.norm(d, axis=1)[:, None]
        # where each ray meets the ball (if it does), it stops there with stop_share
        oc = origin - np.array([10.0, 0, 2.0])
        b = (d @ oc)
        disc = b ** 2 - (oc @ oc - 1.2 ** 2)
        t_in = -b - np.sqrt(np.maximum(disc, 0))
        t_out = -b + np.sqrt(np.maximum(disc, 0))
        stop = (disc > 0) & (rng.uniform(size=len(d)) < stop_share)
        t_hit = np.where(stop, rng.uniform(t_in, t_out), np.linalg.norm(wall - origin, axis=1))
        ev.add_scan(origin, origin + d * t_hit[:, None])
    return ev, map_keys


def test_a_see_through_crown_is_not_removed_but_a_gone_one_is():
    from blockloc.maps.changes.detect import Thresholds, classify

    def removed_in_ball(stop_share):
        ev, map_keys = _crown_scans(stop_share)
        vc = classify(ev, map_keys, None, Thresholds(min_cluster_voxels=1))
        c = _centres(vc.removed, 0.5)
        return int((np.linalg.norm(c - [10.0, 0, 2.0], axis=1) < 1.5).sum())

    # a crown rays stop in by chance (a third of them): hit in every scan, never removed
    assert removed_in_ball(0.3) == 0
    # the crown gone (every ray passes): its voxels are removed
    assert removed_in_ball(0.0) >= 10


def test_a_block_is_confirmed_by_one_coherent_change_not_by_scattered_voxels():
    from blockloc.maps.changes.detect import Thresholds, VoxelChanges, block_report

    th = Thresholds(min_block_m3=2.0)
    # block A: 40 isolated voxels (noise spread over the block); block B: a 4 x 4 x 2 object (4 m^3)
    scattered = np.sort(pack_keys(np.array([[4 * i, 4 * (i % 5), 0] for i in range(40)])))
    obj = np.sort(pack_keys(np.array([[300 + i, j, k] for i in range(4) for j in range(4) for k in range(2)])))
    removed = np.sort(np.concatenate([scattered, obj]))
    vc = VoxelChanges(0.5, removed, np.zeros(0, np.int64), np.zeros(0, np.int64),
                      {"removed": np.full(len(removed), -3.0), "added": np.zeros(0), "dynamic": np.zeros(0)},
                      np.zeros(0, np.int64), np.full(len(removed), 9))
    rows = {r["block"]: r for r in block_report(vc, {"A": scattered, "B": obj}, {}, {}, th)}
    assert rows["A"]["removed_voxels"] == 40 and not rows["A"]["confirmed"]
    assert rows["A"]["largest_change_m3"] == pytest.approx(0.125)
    assert rows["B"]["confirmed"] and rows["B"]["largest_change_m3"] == pytest.approx(4.0)


def test_a_sweep_is_deskewed_with_the_neighbouring_poses_only():
    from blockloc.maps.changes.pipeline import sweep_poses
    from blockloc.maps.changes.runs import RunPoses

    stamps = np.array([0.0, 0.1, 0.2, 5.0, 5.1])
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, 0, 3] = stamps * 2.0
    run = RunPoses(None, np.arange(5), stamps, T, {}, None)
    assert list(sweep_poses(run, 1).stamps) == [0.0, 0.1, 0.2]
    # across the gap after 0.2 s the pose is held, not interpolated towards 5.0 s
    tr = sweep_poses(run, 2)
    assert list(tr.stamps) == [0.1, 0.2]
    assert tr.interpolate(np.array([0.25]))[0, 0, 3] == pytest.approx(0.4)


def _evidence(voxel_m, fine_pts, seen_free, ground=None, hits=()):
    """An Evidence whose map holds the points ``fine_pts`` (N, 3), with every map voxel seen
    through in ``seen_free`` scans and never hit (but the voxels of the points ``hits``)."""
    from blockloc.maps.changes.detect import voxel_keys

    fine_m = voxel_m / 2.5
    map_keys = np.unique(voxel_keys(fine_pts, voxel_m))
    fine_keys = np.unique(voxel_keys(fine_pts, fine_m))
    ev = Evidence(voxel_m, fine=(map_keys, fine_m, fine_keys), ground=ground)
    ev.keys = map_keys
    ev.n_free = np.full(len(map_keys), seen_free, np.int32)
    ev.n_hit = np.isin(map_keys, voxel_keys(np.asarray(hits, float).reshape(-1, 3), voxel_m)).astype(np.int32) * seen_free
    return ev, map_keys


def test_a_removed_voxel_needs_map_structure_not_a_stray_point():
    from blockloc.maps.changes.detect import Thresholds, classify

    g = np.arange(0.05, 2.0, 0.1)
    wall = np.array([[5.05, y, z] for y in g for z in g])  # a 2 x 2 m wall: 4 x 4 dense voxels
    strays = np.array([[10.0 + 1.5 * i, 8.1, 2.2] for i in range(12)]) + 0.05  # one point a voxel
    halo = np.array([[5.3, 2.1, 1.0]])  # one point next to the wall: an edge of it
    ev, _ = _evidence(0.5, np.concatenate([wall, strays, halo]), seen_free=10)
    th = Thresholds(min_cluster_voxels=1)
    rm = _centres(classify(ev, ev.fine[0], None, th).removed, 0.5)
    assert (rm[:, 0] < 6).sum() == 17  # the wall's 16 voxels and its edge's
    assert not (rm[:, 0] > 9).any()  # a row of stray points (mixed pixels) never counts
    # without the rule the strays (1 map cell each) are removed like the wall
    rm1 = _centres(classify(ev, ev.fine[0], None, Thresholds(min_cluster_voxels=1, min_map_cells=1)).removed, 0.5)
    assert (rm1[:, 0] > 9).sum() == 12


def test_the_ground_is_not_removed_and_spares_no_neighbour():
    from blockloc.maps.changes.detect import Thresholds, classify, ground_band, voxel_keys

    g = np.arange(0.05, 3.0, 0.1)
    ground = np.array([[x, y, 0.03] for x in g for y in g])  # map frame z down: the ground at z ~ 0
    car = np.array([[x, y, -z] for x in np.arange(1.05, 2.0, 0.1) for y in np.arange(1.05, 2.0, 0.1)
                    for z in (0.35, 0.75, 1.25, 1.45)])  # a car's body from 0.35 to 1.5 m above the ground
    pts = np.concatenate([ground, car])
    up = np.array([0, 0, -1.0])
    band = ground_band(np.unique(voxel_keys(pts, 0.2)), up, 1)
    ev, _ = _evidence(0.5, pts, seen_free=10, ground=band, hits=ground)  # ground hit, the car gone
    rm = _centres(classify(ev, ev.fine[0], None, Thresholds(min_cluster_voxels=1)).removed, 0.5)
    assert len(rm) and (rm[:, 2] < 0).all()  # the car's voxels only: the ground's stay
    # its lowest voxel (0-0.5 m up), next to the hit ground voxel, is not spared as a crown's edge is
    assert (rm[:, 2] == -0.25).sum() == 4
    # the ground's voxels themselves are never removed, even when rays cross them
    ev2, _ = _evidence(0.5, ground, seen_free=10, ground=ground_band(np.unique(voxel_keys(ground, 0.2)), up, 1))
    assert len(classify(ev2, ev2.fine[0], None, Thresholds(min_cluster_voxels=1)).removed) == 0


def test_a_sheet_of_mixed_pixels_over_the_ground_is_not_removed_but_a_car_is():
    from blockloc.maps.changes.detect import Thresholds, classify, ground_band, voxel_keys

    g = np.arange(0.05, 6.0, 0.1)
    ground = np.array([[x, y, 0.03] for x in g for y in g])  # map frame z down: the ground at z ~ 0
    # the mapping day's mixed pixels between the ground and a crown behind: a layer 0.3-0.5 m over
    # 3 x 3 m of ground, dense (a drive's passes pile it up), one voxel thick
    sheet = np.array([[x, y, -z] for x in np.arange(0.05, 3.0, 0.1) for y in np.arange(0.05, 3.0, 0.1)
                      for z in (0.35, 0.45)])
    car = np.array([[x, y, -z] for x in np.arange(4.05, 5.5, 0.1) for y in np.arange(4.05, 5.5, 0.1)
                    for z in (0.35, 0.75, 1.25, 1.45)])  # a car from 0.35 to 1.5 m above the ground
    pts = np.concatenate([ground, sheet, car])
    up = np.array([0, 0, -1.0])
    ev, _ = _evidence(0.5, pts, seen_free=10, ground=ground_band(np.unique(voxel_keys(pts, 0.2)), up, 1),
                      hits=ground)  # today: the ground hit, rays through the sheet and the car's place
    ev.up = up
    th = Thresholds(min_cluster_voxels=1)
    rm = _centres(classify(ev, ev.fine[0], None, th).removed, 0.5)
    assert not (rm[:, 0] < 3.5).any()  # the sheet stays
    assert (rm[:, 0] > 3.5).sum() >= 27  # the car's 3 x 3 columns, three voxels high
    # without the rule the sheet is read as removed structure
    off = _centres(classify(ev, ev.fine[0], None, Thresholds(min_cluster_voxels=1, sheet_voxels_per_column=0)).removed, 0.5)
    assert (off[:, 0] < 3.5).sum() >= 36
    # a layer as thin but high above the ground (a canopy, 2.3-2.5 m up) is no ground sheet
    high = sheet - np.array([0, 0, 2.0])
    pts2 = np.concatenate([ground, high])
    ev2, _ = _evidence(0.5, pts2, seen_free=10, ground=ground_band(np.unique(voxel_keys(pts2, 0.2)), up, 1),
                       hits=ground)
    ev2.up = up
    assert len(classify(ev2, ev2.fine[0], None, th).removed) >= 36


def test_ground_band_keeps_the_lowest_cells_of_each_column():
    from blockloc.maps.changes.detect import ground_band

    k = np.sort(pack_keys(np.array([[0, 0, 1], [0, 0, 2], [0, 0, 3], [0, 0, 4], [1, 0, 7]])))
    got = sorted(map(tuple, unpack_keys(ground_band(k, np.array([0, 0, 1.0]), 2))))
    assert got == [(0, 0, 1), (0, 0, 2), (0, 0, 3), (1, 0, 7)]
    got = sorted(map(tuple, unpack_keys(ground_band(k, np.array([0, 0, -1.0]), 1))))  # z down
    assert got == [(0, 0, 3), (0, 0, 4), (1, 0, 7)]


def test_added_needs_a_place_the_mapping_day_had_in_sight():
    from blockloc.maps.changes.detect import seen_by_keyframes, voxel_keys

    fine_m = 0.2
    wall = np.array([[5.05, y, z] for y in np.arange(-2, 2, 0.1) for z in np.arange(-1, 2, 0.1)])
    fine_keys = np.unique(voxel_keys(wall, fine_m))
    cells = np.unique(voxel_keys(np.array([[8.0, 0.0, 0.5], [8.0, 6.0, 0.5], [3.0, 0.0, 0.5]]), fine_m))
    seen = _centres(seen_by_keyframes(cells, fine_m, np.zeros((1, 3)), fine_keys, 0.4, 40.0, k=1), fine_m)
    # behind the wall: hidden; beside it and before it: in sight
    assert sorted(np.round(seen[:, :2], 1).tolist()) == [[3.1, 0.1], [8.1, 6.1]]
    # a second keyframe that looks past the wall sees behind it
    kf = np.array([[0.0, 0.0, 0.0], [8.0, 3.0, 0.0]])
    assert len(seen_by_keyframes(cells, fine_m, kf, fine_keys, 0.4, 40.0, k=2)) == 3
    # out of range of every keyframe: not seen
    assert len(seen_by_keyframes(cells, fine_m, kf, fine_keys, 0.4, 1.0, k=2)) == 0


def test_a_place_hidden_from_the_nearest_road_counts_as_seen_from_another_direction():
    from blockloc.maps.changes.detect import Thresholds, seen_by_keyframes, voxel_keys

    fine_m = 0.2
    # a road along y = 12 (keyframes every metre), a wall at y = 9 between it and a fence at y = 0;
    # a cross road along x = -20 sees the fence past the wall's end
    wall = np.array([[x, 9.05, z] for x in np.arange(-15, 15, 0.1) for z in np.arange(-1, 3, 0.1)])
    fine_keys = np.unique(voxel_keys(wall, fine_m))
    road = np.array([[x, 12.0, 1.0] for x in np.arange(-14.0, 15.0, 1.0)])
    cross = np.array([[-20.0, y, 1.0] for y in np.arange(-10.0, 20.0, 1.0)])
    kf = np.concatenate([road, cross])
    cells = np.unique(voxel_keys(np.array([[x, 0.0, 1.0] for x in np.arange(-5.0, 5.0, 1.0)]), fine_m))
    k = Thresholds().seen_keyframes
    # the k nearest keyframes are the road's, all behind the wall: hidden
    assert len(seen_by_keyframes(cells, fine_m, kf, fine_keys, 0.4, 40.0, k=k)) == 0
    # the nearest keyframe to the west (the cross road) sees them
    got = seen_by_keyframes(cells, fine_m, kf, fine_keys, 0.4, 40.0, k=k, sectors=8, up=np.array([0, 0, 1.0]))
    assert len(got) == len(cells)
    assert np.array_equal(seen_by_keyframes(cells, fine_m, kf, fine_keys, 0.4, 40.0, k=k, sectors=8,
                                            up=np.array([0, 0, 1.0]), chunk=3), got)  # a few cells at a time
    # z down (the NCLT map frame): the same
    flip = np.c_[kf[:, :2], -kf[:, 2]]
    wall_d = np.unique(voxel_keys(np.c_[wall[:, :2], -wall[:, 2]], fine_m))
    cells_d = np.unique(voxel_keys(np.array([[x, 0.0, -1.0] for x in np.arange(-5.0, 5.0, 1.0)]), fine_m))
    assert len(seen_by_keyframes(cells_d, fine_m, flip, wall_d, 0.4, 40.0, k=k, sectors=8,
                                 up=np.array([0, 0, -1.0]))) == len(cells_d)
    # out of the range of the cross road (and of the pool of nearest keyframes): hidden still
    assert len(seen_by_keyframes(cells, fine_m, kf, fine_keys, 0.4, 14.0, k=k, sectors=8)) == 0
    assert len(seen_by_keyframes(cells, fine_m, kf, fine_keys, 0.4, 40.0, k=k, sectors=8, pool=10)) == 0
    # a place the wall hides from every keyframe stays hidden
    closed = np.concatenate([wall, [[x, y, z] for x in (-15.05, 15.05) for y in np.arange(-12, 9.1, 0.1)
                                    for z in np.arange(-1, 3, 0.1)]])
    closed_keys = np.unique(voxel_keys(closed, fine_m))
    assert len(seen_by_keyframes(cells, fine_m, road, closed_keys, 0.4, 40.0, k=k, sectors=8)) == 0


def test_a_cloud_of_the_mapping_days_noise_is_not_removed_even_where_a_few_voxels_are_dense():
    from blockloc.maps.changes.detect import Thresholds, classify, map_cells_per_voxel, voxel_keys

    g = np.arange(0.05, 2.0, 0.1)
    wall = np.array([[5.05, y, z] for y in g for z in g])  # a 2 x 2 m wall: 4 x 4 dense voxels
    # behind a crown's edge: a 4 x 4 x 3 cloud of voxels holding one mixed pixel each, 6 of them
    # (where the pixels piled up) dense enough to pass min_map_cells and carry their neighbours
    cloud = np.array([[10.25 + 0.5 * i, 4.25 + 0.5 * j, 2.25 + 0.5 * k] for i in range(4) for j in range(4)
                      for k in range(3)])
    pile = np.array([c + [dx, dy, dz] for c in cloud[::8] for dx in (-0.1, 0.1) for dy in (-0.1, 0.1)
                     for dz in (-0.1, 0.1)])
    pts = np.concatenate([wall, cloud, pile])
    ev, _ = _evidence(0.5, pts, seen_free=10)
    dense = map_cells_per_voxel(np.unique(voxel_keys(pile, 0.5)), 0.5, ev.fine[1], ev.fine[2])
    assert len(dense) == 6 and (dense >= 4).all()
    rm = _centres(classify(ev, ev.fine[0], None, Thresholds()).removed, 0.5)
    assert (rm[:, 0] < 6).sum() == 16  # the wall: a dense surface, removed
    assert not (rm[:, 0] > 9).any()  # the cloud: mostly single points, kept
    # without the rule the dense voxels and their neighbours form a removed cluster
    rm0 = _centres(classify(ev, ev.fine[0], None, Thresholds(min_solid_share=0.0)).removed, 0.5)
    assert (rm0[:, 0] > 9).sum() >= 20 and (rm0[:, 0] < 6).sum() == 16


def test_the_compiled_key_kernels_give_the_numpy_answers():
    """near_sorted, dilate_keys, voxel_keys, the column rules (without_lowest, ground_band) and the
    evidence merge (Evidence.flush) against the same sums written out in numpy."""
    from blockloc.maps.changes import detect as d

    rng = np.random.default_rng(0)
    for _ in range(3):
        table = d.unique_keys(d.pack_keys(rng.integers(-20, 20, (600, 3))))
        q = d.pack_keys(rng.integers(-22, 22, (2000, 3)))
        ref = np.zeros(len(q), bool)
        for off in d._NEIGHBOURS:
            ref |= d.in_sorted(d.pack_keys(d.unpack_keys(q) + off), table)
        np.testing.assert_array_equal(d.near_sorted(q, table), ref)
        dil = d.pack_keys((d.unpack_keys(table)[:, None, :] + d._NEIGHBOURS[None]).reshape(-1, 3))
        np.testing.assert_array_equal(d.dilate_keys(table), np.unique(dil))
        p = rng.normal(0.0, 30.0, (3000, 4))
        np.testing.assert_array_equal(d.voxel_keys(p, 0.2), d.pack_keys(np.floor(p[:, :3] / 0.2).astype(np.int64)))
        keys = d.unique_keys(d.pack_keys(rng.integers(-15, 15, (4000, 3))))
        for up in ([0, 0, 1.0], [0, 0, -1.0]):
            up = np.array(up)
            h = d.unpack_keys(keys)[:, 2] * np.sign(up[2])
            col = keys >> 21  # the (i, j) column
            low = {c: h[col == c].min() for c in np.unique(col)}
            lowest = np.array([h[n] == low[c] for n, c in enumerate(col)])
            np.testing.assert_array_equal(d.without_lowest(keys, up), keys[~lowest])
            band = np.array([h[n] - low[c] <= 1 for n, c in enumerate(col)])
            np.testing.assert_array_equal(d.ground_band(keys, up, 1), keys[band])
        ev = d.Evidence(0.5)
        hits = [d.unique_keys(d.pack_keys(rng.integers(-9, 9, (300, 3)))) for _ in range(40)]
        free = [d.unique_keys(d.pack_keys(rng.integers(-9, 9, (500, 3)))) for _ in range(40)]
        for h_, f_ in zip(hits, free):
            ev._pending_hit.append(h_)
            ev._pending_free.append(f_)
            if len(ev._pending_hit) == 25:
                ev.flush()
        ev.flush()
        allk = np.unique(np.concatenate(hits + free))
        np.testing.assert_array_equal(ev.keys, allk)
        np.testing.assert_array_equal(ev.n_hit, np.bincount(np.searchsorted(allk, np.concatenate(hits)),
                                                            minlength=len(allk)))
        np.testing.assert_array_equal(ev.n_free, np.bincount(np.searchsorted(allk, np.concatenate(free)),
                                                             minlength=len(allk)))


def test_a_neighbour_hit_once_spares_nothing_with_solid_min_hits():
    """The neighbour rule (a crown's edge next to its hit core) asks the neighbour to be hit in
    solid_min_hits scans (2 by default): a voxel hit once in five (a stray return) no longer keeps
    a removed wall's side."""
    from blockloc.maps.changes.detect import Thresholds, classify, voxel_keys

    g = np.arange(0.05, 2.0, 0.1)
    wall = np.array([[5.05, y, z] for y in g for z in g])
    stray = np.array([[5.55, 1.0, 1.0]])  # a map voxel next to the wall
    ev, _ = _evidence(0.5, np.concatenate([wall, stray]), seen_free=10)
    j = np.searchsorted(ev.keys, voxel_keys(stray, 0.5))
    ev.n_hit[j] = 1  # seen by 5 scans, hit by one
    ev.n_free[j] = 4
    th = Thresholds(min_cluster_voxels=1, min_map_cells=1, solid_min_hits=1, solid_min_cells=0)
    spared = 16 - np.isin(np.unique(voxel_keys(wall, 0.5)), classify(ev, ev.fine[0], None, th).removed).sum()
    assert spared >= 3  # the wall's voxels next to the stray are kept
    rm = classify(ev, ev.fine[0], None, Thresholds(min_cluster_voxels=1, min_map_cells=1)).removed
    assert np.isin(np.unique(voxel_keys(wall, 0.5)), rm).all()


def test_a_neighbour_the_map_barely_holds_spares_nothing_but_a_dense_one_does():
    """The neighbour rule asks the hit neighbour to hold solid_min_cells of the map's fine cells
    (2 by default): the ground a removed car hid on the mapping day (one map cell, the car's
    lowest edge) is hit today and no longer keeps the car's side; a crown's core, dense in the
    map and hit today, still spares its edge."""
    from blockloc.maps.changes.detect import Thresholds, classify, voxel_keys

    g = np.arange(0.05, 2.0, 0.1)
    side = np.array([[5.05, y, z] for y in g for z in g])  # a car's side, 2 x 2 m: 4 x 4 dense voxels
    hidden = np.array([[5.55, 1.05, 1.05]])  # one map point next to it: the ground it hid, hit today
    ev, _ = _evidence(0.5, np.concatenate([side, hidden]), seen_free=10, hits=hidden)
    side_keys = np.unique(voxel_keys(side, 0.5))
    th = Thresholds(min_cluster_voxels=1, min_map_cells=1)
    assert np.isin(side_keys, classify(ev, ev.fine[0], None, th).removed).all()
    # without the rule the hit voxel spares its 9 neighbours of the side as a crown's edge
    old = classify(ev, ev.fine[0], None, Thresholds(min_cluster_voxels=1, min_map_cells=1, solid_min_cells=0))
    assert (~np.isin(side_keys, old.removed)).sum() == 9
    # a dense neighbour hit today (a crown's core: 5 x 5 map points in its voxel) still spares them
    core = np.array([[5.55 + 0.1 * a, 1.05, 0.85 + 0.1 * b] for a in range(5) for b in range(5)])
    ev2, _ = _evidence(0.5, np.concatenate([side, core]), seen_free=10, hits=core[:1])
    kept = ~np.isin(side_keys, classify(ev2, ev2.fine[0], None, th).removed)
    assert kept.sum() >= 3
