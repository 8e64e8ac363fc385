"""Worlds, sessions and written datasets: determinism, change between days, NCLT round trip."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from blockloc.datasets.base import Sequence
from blockloc.errors import SimError
from blockloc.sim import generate_dataset
from blockloc.sim.presets import get_preset
from blockloc.sim.stream import open_sim_sequence
from blockloc.sim.world import build_world, session_movables


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim")
    a = generate_dataset("tiny", 5, root / "a", max_frames=12, azimuth_steps=120)
    b = generate_dataset("tiny", 5, root / "b", max_frames=12, azimuth_steps=120)
    c = generate_dataset("tiny", 6, root / "c", max_frames=12, azimuth_steps=120)
    return a, b, c


def test_same_seed_same_bytes_other_seed_other_world(written):
    a, b, c = written
    da, db, dc = _digest(a), _digest(b), _digest(c)
    assert len(da) > 20 and da == db
    assert set(da) == set(dc)
    assert da["map/ms25.csv"] != dc["map/ms25.csv"]
    wa, wc = build_world(get_preset("tiny"), 5), build_world(get_preset("tiny"), 6)
    assert not np.allclose(wa.roads.xs, wc.roads.xs)
    assert wa.meshes["terrain"][0].shape == wc.meshes["terrain"][0].shape
    assert not np.allclose(wa.meshes["terrain"][0][:, 2], wc.meshes["terrain"][0][:, 2])


def test_written_sessions_read_back_with_the_nclt_loader(written):
    from blockloc.datasets.nclt import NcltSequence
    from blockloc.app.catalog import open_sequence

    a = written[0]
    assert sorted(p.name for p in a.iterdir()) == [".blockloc-output.json", "loc", "map", "sim.json"]
    for session in ("map", "loc"):
        disk = open_sequence(str(a / session))
        assert isinstance(disk, NcltSequence)
        sim = open_sim_sequence("tiny", session, 5, azimuth_steps=120)
        assert len(disk) == 12
        assert np.allclose(disk.frame_stamps(), sim.frame_stamps()[:12])
        for i in (0, 7):
            fd, fs = disk.frame(i), sim.frame(i)
            # the loader drops returns nearer than 1 m (the robot's own mast among them)
            r = np.linalg.norm(fs.points, axis=1)  # (the 5 mm quantisation may move a point over 1 m)
            assert (r >= 1.01).sum() <= len(fd) <= (r >= 0.99).sum() and (r < 1.0).sum() < 0.05 * len(fs)
            from scipy.spatial import cKDTree

            dist, j = cKDTree(fs.points).query(fd.points)
            assert dist.max() < 0.005  # 5 mm quantisation
            assert np.allclose(fd.time_offsets, fs.time_offsets[j], atol=3e-4)
        gt_d, gt_s = disk.ground_truth(), sim.ground_truth()
        n = len(gt_d)
        assert n > 100 and np.allclose(gt_d.poses, gt_s.poses[:n], atol=1e-6)
        imu_d, imu_s = disk.imu(), sim.imu()
        assert np.allclose(imu_d.acc, imu_s.acc[:len(imu_d)], atol=1e-6)
        assert np.allclose(disk.info.T_body_lidar, sim.info.T_body_lidar)
    # the mapping session carries offline-SLAM poses a few cm off ground truth
    m = open_sequence(str(a / "map"))
    err = np.linalg.norm(m.mapping_poses().positions - m.ground_truth().positions, axis=1)
    assert 0.003 < np.median(err) < 0.1


def test_stream_is_random_access_and_deterministic():
    s1 = open_sim_sequence("tiny", "loc", 2, azimuth_steps=90)
    s2 = open_sim_sequence("tiny", "loc", 2, azimuth_steps=90)
    assert isinstance(s1, Sequence)
    f_late = s1.frame(40)
    f_seq = list(s2.frames(38, 41))[-1]
    assert np.array_equal(f_late.points, f_seq.points)
    assert np.array_equal(f_late.intensity, f_seq.intensity)
    assert f_late.stamp == pytest.approx(s1.frame_stamps()[40])
    assert not np.array_equal(s1.frame(41).points[:50], f_late.points[:50])
    gt = s1.ground_truth()
    assert np.median(np.diff(gt.stamps)) == pytest.approx(0.01)
    assert s1.info.name == "sim:tiny/loc@2" and s1.info.gravity_map[2] > 9
    with pytest.raises(SimError, match="session 'loc9'"):
        open_sim_sequence("tiny", "loc9", 2)
    with pytest.raises(SimError, match="preset 'huge'"):
        open_sim_sequence("huge", "map", 2)


def test_days_differ_in_movable_objects_and_moving_actors():
    world = build_world(get_preset("small"), 1)
    base = session_movables(world, "map", base=True)
    day = session_movables(world, "loc", base=False)
    assert len(base) >= 40
    same_uid = np.intersect1d(base.uid, day.uid)
    removed = len(base) - len(same_uid)
    added = len(np.setdiff1d(day.uid, base.uid))
    ib = np.searchsorted(base.uid, same_uid)
    iday = np.array([np.flatnonzero(day.uid == u)[0] for u in same_uid])
    moved = int((np.linalg.norm(base.xy[ib] - day.xy[iday], axis=1) > 0.5).sum())
    assert (removed + moved + added) / len(base) >= 0.10
    assert removed > 0 and moved > 0 and added > 0
    from blockloc.sim.scene import make_actors

    actors = make_actors(world, "loc")
    kinds = set(actors.kind.tolist())
    assert kinds == {"pedestrian", "vehicle"}
    assert len(make_actors(world, "map").kind) == 0  # the mapping day is quiet
    p0, _ = actors.poses(0.0)
    p1, _ = actors.poses(2.0)
    step = np.linalg.norm(p1 - p0, axis=1)
    assert np.all(step > 1.0) and np.all(step < 15.0)  # walking and driving speeds


@pytest.mark.parametrize("preset", ["small", "campus"])
def test_movable_meshes_in_one_pass_equal_the_per_object_meshes(preset):
    """The scene builds every car and bin in one vectorised pass: bit for bit the meshes that
    movable_mesh per object gives (the scans, and every cached sim result, stay the same)."""
    from blockloc.sim.stream import cached_world
    from blockloc.sim.world import MeshBuilder, movable_mesh, movable_meshes

    world = cached_world(get_preset(preset), 1)
    for session, base in (("map", True), ("loc", False)):
        mv = session_movables(world, session, base)
        ref = {k: MeshBuilder() for k in ("car", "bin")}
        for kind, (x, y), yaw in zip(mv.kind, mv.xy, mv.yaw):
            for V, F in movable_mesh(str(kind), x, y, yaw, world.terrain):
                ref[str(kind)].add(V, F)
        ref = {k: b.build() for k, b in ref.items() if b.verts}
        got = movable_meshes(mv, world.terrain)
        assert list(got) == list(ref) and len(ref["car"][1]) > 1000
        for k in ref:
            assert got[k][0].tobytes() == ref[k][0].tobytes()
            assert got[k][1].dtype == ref[k][1].dtype and np.array_equal(got[k][1], ref[k][1])


def test_ground_material_near_paths_only_equals_every_point_against_every_path():
    """Footpath codes are computed only for grass near each path's box: the same codes as every
    point measured against every path."""
    from blockloc.sim.stream import cached_world
    from blockloc.sim.world import polyline_distance

    world = cached_world(get_preset("campus"), 1)
    rng = np.random.default_rng(0)
    x0, x1, y0, y1 = world.extent
    x, y = rng.uniform(x0, x1, 60_000), rng.uniform(y0, y1, 60_000)
    d = world.roads.distance(x, y)
    hw = world.roads.width_m / 2
    ref = np.where(d < hw, 0, np.where(d < hw + 2.5, 1, 2))
    for P in world.roads.paths.values():
        ref = np.where((ref == 2) & (polyline_distance(P, x, y) < 1.25), 3, ref)
    got = world._ground_material_exact(x, y)
    assert (ref == 3).sum() > 100 and np.array_equal(got, ref)


def test_small_routes_cover_blocks_and_stay_in_the_map():
    mp = open_sim_sequence("small", "map", 1).ground_truth().positions
    lc = open_sim_sequence("small", "loc", 1).ground_truth().positions
    from scipy.spatial import cKDTree

    d, _ = cKDTree(mp[:, :2]).query(lc[:, :2])
    assert d.max() < 15.0  # localization stays within the mapped area
    # it is another route: mostly in the other direction or another place at the same time
    assert 150 < np.linalg.norm(np.diff(mp, axis=0), axis=1).sum() < 260
    # with 40 m blocks (blockloc/presets/sim.yaml) the map route spans several blocks
    ext = mp.max(axis=0) - mp.min(axis=0)
    assert ext[0] > 35 and ext[1] > 35
    assert np.ptp(mp[:, 2]) > 0.3  # terrain: z matters


def test_cli_sim_writes_a_dataset(tmp_path):
    from typer.testing import CliRunner

    from blockloc.cli import app

    res = CliRunner().invoke(app, ["sim", "--preset", "tiny", "--seed", "3", "--out", str(tmp_path / "o"),
                                   "--azimuth-steps", "16"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o" / "map" / "velodyne_hits.bin").stat().st_size > 0
    assert len(list((tmp_path / "o" / "loc" / "velodyne_sync").iterdir())) > 300
    bad = CliRunner().invoke(app, ["sim", "--preset", "tiny", "--out", str(tmp_path / "x"), "--format", "las"])
    assert bad.exit_code != 0 and not (tmp_path / "x").exists()


@pytest.mark.parametrize("fmt", ["rosbag1", "rosbag2"])
def test_rosbag_formats_read_back(tmp_path, fmt):
    from blockloc.datasets.rosbag import RosbagSequence

    out = generate_dataset("tiny", 5, tmp_path / fmt, fmt, max_frames=4, azimuth_steps=60)
    bag = out / ("map.bag" if fmt == "rosbag1" else "map")
    seq = RosbagSequence(bag, lidar_topic="/velodyne_points", imu_topic="/imu",
                         ground_truth_path=out / "map_groundtruth.csv")
    sim = open_sim_sequence("tiny", "map", 5, azimuth_steps=60)
    assert len(seq) == 4
    f, s = seq.frame(3), sim.frame(3)
    assert f.stamp == pytest.approx(s.stamp) and len(f) == len(s)
    assert np.allclose(np.sort(f.points[:, 2]), np.sort(s.points[:, 2]), atol=1e-5)
    assert np.allclose(seq.ground_truth().poses, sim.ground_truth().poses[:len(seq.ground_truth())], atol=1e-6)


def test_campus_routes_are_long_and_inside_the_map():
    from scipy.spatial import cKDTree

    from blockloc.sim.presets import get_preset
    from blockloc.sim.stream import session_trajectory

    p = get_preset("campus")
    assert p.size_m[0] >= 800 and p.size_m[1] >= 500 and "loc2" in p.sessions
    mp = session_trajectory(p, 1, "map").samples[::10, 1:3]
    tree = cKDTree(mp)
    loc = session_trajectory(p, 1, "loc")
    assert loc.path_length() >= 6000
    t = np.arange(0, loc.duration, 0.1)
    v = np.hypot(loc._sx(t, 1), loc._sy(t, 1))
    w = np.abs(loc._sp(t, 1))
    assert v.max() <= 1.5 and 1.0 <= loc.path_length() / loc.duration <= 1.5
    assert ((v < 0.02) & (w > 0.2)).sum() > 50  # turns in place
    for s in ("loc", "loc2"):
        d, _ = tree.query(session_trajectory(p, 1, s).samples[::10, 1:3])
        assert d.max() < 15.0


def test_ground_material_keeps_a_bounded_number_of_raster_tiles(monkeypatch):
    """A world keeps the MATERIAL_TILES raster tiles used last (it kept every tile it touched: a
    process rendering drives across a city grew with the area they covered); a tile built again
    after its eviction gives the same codes."""
    from blockloc.sim import world as world_mod

    monkeypatch.setattr(world_mod, "MATERIAL_TILES", 3)
    world = world_mod.build_world(get_preset("tiny"), 1)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-60, 60, 4000), rng.uniform(-60, 60, 4000)  # the 4 tiles around the origin
    first = world.ground_material(x, y)
    assert len(world._material) == 3
    assert all(t.nbytes == 512 * 128 for t in world._material.values())  # 512 x 512 codes, 2 bits each
    for tx, ty in [(300.0, 300.0), (-300.0, 300.0), (300.0, -300.0), (-300.0, -300.0)]:
        world.ground_material(np.array([tx]), np.array([ty]))
        assert len(world._material) <= 3
    assert np.array_equal(world.ground_material(x, y), first)
    assert set(np.unique(first)) >= {0, 2}  # roads and grass both sampled


def test_ground_raster_tiles_are_shared_between_processes_on_disk(tmp_path, monkeypatch):
    """A tile one process rasterized is read by the next (a Dask worker, a later run) instead of
    computed again, and reads the same codes; a damaged tile file is computed again."""
    import blockloc.sim.stream as stream
    import blockloc.sim.world as W

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path))
    stream.cached_world.cache_clear()
    try:
        world = stream.cached_world(get_preset("tiny"), 3)
        x, y = np.array([1.0, 40.0, -30.0]), np.array([2.0, -20.0, 10.0])
        first = world.ground_material(x, y)
        files = sorted(world.material_tiles.dir.glob("*.npy"))
        assert len(files) >= 2 and all(f.stat().st_size > 512 * 128 for f in files)
        calls = []

        def forget():  # as in another process: no tile nor stack of tiles in memory
            world._material.clear()
            world._material_stacks.clear()

        monkeypatch.setattr(W.World, "_ground_material_exact",
                            lambda self, *a, **k: calls.append(1) or np.full(len(a[0]), 2))
        forget()
        assert np.array_equal(world.ground_material(x, y), first) and not calls
        files[0].write_bytes(b"not a tile")
        forget()
        world.ground_material(x, y)
        assert len(calls) == 1  # the damaged tile only, computed again
        files[1].write_bytes(b"")  # cut short by a crash: np.load raises EOFError
        forget()
        world.ground_material(x, y)
        assert len(calls) == 2
        good = np.load(files[-1])
        np.save(files[-1], good.astype(np.int16))  # right shape, wrong type: not a tile of ours
        forget()
        world.ground_material(x, y)
        assert len(calls) == 3
    finally:
        stream.cached_world.cache_clear()
