"""`blockloc map tile | info | plot | build` end to end through the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from blockloc.cli import app
from blockloc.maps.pcd import write_pcd
from blockloc.maps.store import open_map

runner = CliRunner()


@pytest.fixture()
def global_pcd(tmp_path):
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-10, 10, (5000, 2)), rng.uniform(0, 2, 5000)].astype(np.float32)
    write_pcd(tmp_path / "global.pcd", pts, rng.uniform(0, 100, 5000))
    return tmp_path / "global.pcd"


def test_tile_info_plot(tmp_path, global_pcd):
    res = runner.invoke(app, ["map", "tile", str(global_pcd), "--tile-size", "2", "--out",
                              str(tmp_path / "tiles")])
    assert res.exit_code == 0, res.output
    assert "tiles: 100/100 (100%)" in res.stderr  # the command's progress (piped: lines)
    store = open_map(tmp_path / "tiles")
    assert store.kind == "grid" and store.total_points == 5000 and len(store.entries) == 100
    assert (tmp_path / "tiles" / "-9.0_-9.0.pcd").exists()
    res = runner.invoke(app, ["map", "info", str(tmp_path / "tiles"), "--json"])
    assert res.exit_code == 0, res.output
    info = json.loads(res.output)
    assert info["entries"] == 100 and info["points"] == 5000 and info["overlap_ratio"] == 0.0
    # tiles hold exactly the global map's payload: same points, 16 bytes each, plus headers
    assert info["bytes"] - 16 * 5000 == sum(
        e.bytes - 16 * e.num_points for e in store.entries)
    res = runner.invoke(app, ["map", "plot", str(tmp_path / "tiles"), "--out", str(tmp_path / "t.png")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "t.png").read_bytes()[:4] == b"\x89PNG"


def test_bad_input_is_one_line(tmp_path, global_pcd):
    from blockloc.errors import MapError

    res = runner.invoke(app, ["map", "tile", str(global_pcd), "--tile-size", "0", "--out",
                              str(tmp_path / "x")])
    assert isinstance(res.exception, MapError) and "tile size" in str(res.exception)
    assert not (tmp_path / "x").exists()
    res = runner.invoke(app, ["map", "info", str(tmp_path / "nope")])
    assert isinstance(res.exception, MapError) and "no such map directory" in str(res.exception)


def test_build_from_a_session_directory(tmp_path):
    """`map build` on a sequence opened through the registry (a directory in NCLT layout)."""
    from blockloc.datasets.base import ImuData
    from blockloc.datasets.nclt import write_session

    from .synthetic import MemorySequence, route, world_points

    world = world_points(extent=(-30, 90), seed=3, density=0.2)
    traj = route([[0, 0], [60, 0]], speed=5.0)
    seq = MemorySequence(world, traj, radius=20.0)
    imu = ImuData(traj.stamps, np.zeros((len(traj), 3)), np.zeros((len(traj), 3)))
    write_session(tmp_path / "sess", date="2012-01-15", frames=seq.frames(), imu=imu,
                  ground_truth=traj)
    res = runner.invoke(app, ["map", "build", "--seq", str(tmp_path / "sess"), "--kind", "block",
                              "--block-size", "20", "--out", str(tmp_path / "bm")])
    assert res.exit_code == 0, res.output
    store = open_map(tmp_path / "bm")
    assert store.kind == "block" and len(store.entries) >= 2


def test_build_from_pcd_writes_the_place_index(tmp_path, monkeypatch):
    """`map build --from-pcd` stores a place index, as every map build does, for the gravity
    `--gravity` gives (default up: z up); it loads back byte for byte."""
    from blockloc.trajectory_io import write_tum
    from blockloc.global_init.place_index import PLACE_INDEX_NAME, load_place_index

    from .synthetic import route, world_points

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path / "cache"))  # global init's rasters: not the shared cache
    world = world_points(extent=(-15, 55), seed=3, density=0.2)
    write_pcd(tmp_path / "global.pcd", world.astype(np.float32))
    write_tum(tmp_path / "poses.tum", route([[0, 0], [40, 0]], speed=5.0))
    res = runner.invoke(app, ["map", "build", "--from-pcd", str(tmp_path / "global.pcd"), "--poses",
                              str(tmp_path / "poses.tum"), "--kind", "block", "--block-size", "20",
                              "--sensor-range", "20", "--out", str(tmp_path / "bm")])
    assert res.exit_code == 0, res.output
    assert "block map keyframes: " in res.stderr  # the command's progress (piped: lines)
    store = open_map(tmp_path / "bm")
    assert store.kind == "block" and len(store.entries) >= 2 and store.has_extra(PLACE_INDEX_NAME)
    index = load_place_index(store, np.array([0.0, 0.0, -9.81]), build_missing=False)
    assert len(index) > 0
    assert index.to_bytes() == (tmp_path / "bm" / store.extras[PLACE_INDEX_NAME].file).read_bytes()
    # built for gravity up: a sequence with the map's z axis down is refused, naming the index
    from blockloc.errors import MapError

    with pytest.raises(MapError, match="built for gravity"):
        load_place_index(store, np.array([0.0, 0.0, 9.81]), build_missing=False)


def test_gravity_goes_with_from_pcd_only(tmp_path):
    from blockloc.errors import MapError

    res = runner.invoke(app, ["map", "build", "--seq", "sim:small/map", "--gravity", "down",
                              "--out", str(tmp_path / "m")])
    assert isinstance(res.exception, MapError) and "--gravity goes with --from-pcd" in str(res.exception)
    res = runner.invoke(app, ["map", "build", "--from-pcd", str(tmp_path / "g.pcd"), "--poses",
                              str(tmp_path / "p.tum"), "--gravity", "sideways", "--out", str(tmp_path / "m")])
    assert isinstance(res.exception, MapError) and "--gravity 'sideways'" in str(res.exception)
    assert not (tmp_path / "m").exists()


def _blockloc(*args):
    """``blockloc ARGS`` as a user types it (a subprocess of the console script's module)."""
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "blockloc.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=900)


def test_the_mounting_of_an_nclt_session_whose_lidar_sits_off_nominal_is_estimated_by_default(tmp_path):
    """NCLT's ground truth is body poses and its extrinsic nominal: `map build` (by default) finds
    how the session's LiDAR really sits and keeps the estimate in the manifest; `map info` says
    so; `track` takes it (map.use_map_mounting); `--nominal-mounting` opts out, and `map info`
    says the map holds the nominal mounting."""
    from blockloc.datasets.base import ImuData
    from blockloc.datasets.nclt import NCLT_T_BODY_IMU, NCLT_T_BODY_LIDAR, write_session
    from blockloc.geometry import make_T, so3_exp, so3_log

    from .synthetic import MemorySequence, route, world_points

    X_true = np.asarray(NCLT_T_BODY_LIDAR, float) @ make_T(so3_exp(np.deg2rad([0.2, 0.3, -0.5])),
                                                          np.array([0.03, -0.02, 0.0]))
    world = world_points(extent=(-40, 110), seed=5, density=0.5)
    traj = route([[0, 0], [70, 0], [70, 70], [0, 70], [0, 0]], speed=4.0)
    seq = MemorySequence(world, traj, radius=25.0, T_body_lidar=X_true)
    # at rest on flat ground (NCLT: z down) the IMU reads the specific force -g: init levels with it
    f_imu = np.asarray(NCLT_T_BODY_IMU, float)[:3, :3].T @ np.array([0.0, 0.0, -9.81])
    imu = ImuData(traj.stamps, np.tile(f_imu, (len(traj), 1)), np.zeros((len(traj), 3)))
    write_session(tmp_path / "sess", date="2012-01-15", frames=seq.frames(), imu=imu, ground_truth=traj)
    res = _blockloc("map", "build", "--seq", tmp_path / "sess", "--kind", "block", "--block-size", "40",
                    "--out", tmp_path / "bm")
    assert res.returncode == 0, res.stderr
    params = open_map(tmp_path / "bm").params
    (m,) = params["mounting"].values()
    assert list(params["mounting_source"].values()) == [{"source": "estimated"}]
    X = np.asarray(m["T_body_lidar"])
    assert np.abs(np.rad2deg(so3_log(X[:3, :3] @ X_true[:3, :3].T))).max() < 0.1, m
    assert np.abs(X[:2, 3] - X_true[:2, 3]).max() < 0.01, m
    info = _blockloc("map", "info", tmp_path / "bm")
    assert info.returncode == 0 and "LiDAR mounting" in info.stdout, info.stderr
    assert f"estimated from {m['used']} of {m['pairs']} keyframe pairs" in " ".join(info.stdout.split())
    # tracking the same robot's session takes the map's mounting (the default)
    run = _blockloc("track", "--seq", tmp_path / "sess", "--map", tmp_path / "bm", "--init", "gt",
                    "--max-frames", "3", "--no-record", "--out", tmp_path / "run")
    assert run.returncode == 0, run.stderr
    assert "LiDAR mounting" not in run.stderr  # no warning: it tracked with the map's
    # the run's metrics break its error down, and its report shows the breakdown's plot
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["err_moving_poses"] == 3 and len(metrics["err_offset_m"]) == 3
    assert 'alt="error breakdown"' in (tmp_path / "run" / "report.html").read_text()
    run = _blockloc("track", "--seq", tmp_path / "sess", "--map", tmp_path / "bm", "--init", "gt",
                    "--max-frames", "3", "--no-record", "--out", tmp_path / "run2",
                    "--set", "map.use_map_mounting=false")
    assert run.returncode == 0, run.stderr
    assert "LiDAR mounting estimated from its drive that differs" in run.stderr
    assert "--set map.use_map_mounting=true tracks with it" in run.stderr
    # init too (the same session assembly): a warning only when told to keep the sequence's. The
    # synthetic world fits poorly (inlier ratio about 0.7) and has no static band to judge coverage
    # on: its right pose is an answer only with the fit floors lowered, the clear best's too
    floors = ["--set", "global_init.min_fitness=0.5", "--set", "global_init.unjudged_end_min_fitness=0.5",
              "--set", "global_init.unjudged_end_min_structure_fitness=0.5"]
    res = _blockloc("init", "--seq", tmp_path / "sess", "--frame", "30", "--map", tmp_path / "bm",
                    "--pose-hint", "20,0", *floors[:2])
    assert res.returncode == 2 and "global_init.unjudged_end_min_fitness" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
    for sets, warned in (([], False), (["--set", "map.use_map_mounting=false"], True)):
        res = _blockloc("init", "--seq", tmp_path / "sess", "--frame", "30", "--map", tmp_path / "bm",
                        "--pose-hint", "20,0", "--json", *floors, *sets)
        assert res.returncode == 0, res.stderr
        assert ("--set map.use_map_mounting=true tracks with it" in res.stderr) == warned, res.stderr
        assert json.loads(res.stdout)["error_m"] < 0.05  # the synthetic world's fitness: 0.69
    # opted out: the nominal mounting, and map info says so
    res = _blockloc("map", "build", "--seq", tmp_path / "sess", "--kind", "block", "--block-size", "40",
                    "--nominal-mounting", "--out", tmp_path / "nm")
    assert res.returncode == 0, res.stderr
    params = open_map(tmp_path / "nm").params
    assert "mounting" not in params
    assert list(params["mounting_source"].values()) == [{"source": "nominal", "reason": "not estimated"}]
    info = _blockloc("map", "info", tmp_path / "nm")
    assert info.returncode == 0 and "nominal, the sequence's own (not estimated)" in " ".join(info.stdout.split())
    # a global PCD has no scans to register: refused before any work, naming the option
    res = runner.invoke(app, ["map", "build", "--from-pcd", str(tmp_path / "g.pcd"), "--poses",
                              str(tmp_path / "p.tum"), "--calibrate-mounting", "--out", str(tmp_path / "m2")])
    assert "--calibrate-mounting needs --seq" in str(res.exception) and not (tmp_path / "m2").exists()


def test_map_build_keeps_the_nominal_translation_when_the_drives_poses_do_not_reproduce_it(tmp_path):
    """The same kind of session, but its ground truth (the body poses the map is built from) wanders
    6 cm around the truth, smoothly, as an offline SLAM's does: `map build` still estimates the
    mounting's rotation, keeps the nominal translation (the block jackknife along the drive finds
    it not reproducible to 5 mm), and `map info` says so (issue 41)."""
    from blockloc.datasets.base import ImuData
    from blockloc.datasets.nclt import NCLT_T_BODY_IMU, NCLT_T_BODY_LIDAR, write_session
    from blockloc.geometry import Trajectory, make_T, so3_exp, so3_log

    from .synthetic import MemorySequence, route, world_points

    X_nominal = np.asarray(NCLT_T_BODY_LIDAR, float)
    X_true = X_nominal @ make_T(so3_exp(np.deg2rad([0.2, 0.3, -0.5])), np.array([0.01, -0.01, 0.0]))
    world = world_points(extent=(-40, 110), seed=5, density=0.5)
    traj = route([[0, 0], [70, 0], [70, 70], [0, 70], [0, 0]], speed=4.0)
    seq = MemorySequence(world, traj, radius=25.0, T_body_lidar=X_true)
    t = traj.stamps - traj.stamps[0]
    wander = traj.poses.copy()
    wander[:, 0, 3] += 0.06 * np.sin(2 * np.pi * t / 23.0)
    wander[:, 1, 3] += 0.06 * np.cos(2 * np.pi * t / 17.0)
    f_imu = np.asarray(NCLT_T_BODY_IMU, float)[:3, :3].T @ np.array([0.0, 0.0, -9.81])  # at rest
    imu = ImuData(traj.stamps, np.tile(f_imu, (len(traj), 1)), np.zeros((len(traj), 3)))
    write_session(tmp_path / "sess", date="2012-01-15", frames=seq.frames(), imu=imu,
                  ground_truth=Trajectory(traj.stamps, wander))
    # the mounting step alone (the default's pose refinement would estimate x again with the poses)
    res = _blockloc("map", "build", "--seq", tmp_path / "sess", "--kind", "block", "--block-size", "40",
                    "--no-refine-poses", "--out", tmp_path / "bm")
    assert res.returncode == 0, res.stderr
    (m,) = open_map(tmp_path / "bm").params["mounting"].values()
    X = np.asarray(m["T_body_lidar"])
    assert np.abs(np.rad2deg(so3_log(X[:3, :3] @ X_true[:3, :3].T))).max() < 0.1, m
    assert m["translation_estimated"] == "" and m["translation_m"] == [0.0, 0.0, 0.0], m
    np.testing.assert_allclose(X[:3, 3], X_nominal[:3, 3], atol=1e-9)
    assert min(m["translation_uncertainty_m"][:2]) > m["translation_tolerance_m"] == 0.005, m
    import os
    import subprocess
    import sys

    # a terminal wide enough that the table does not wrap the line
    info = subprocess.run([sys.executable, "-m", "blockloc.cli", "map", "info", str(tmp_path / "bm")],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "COLUMNS": "400"})
    assert info.returncode == 0, info.stderr
    u = ", ".join(f"{1000 * v:.0f}" for v in m["translation_uncertainty_m"][:2])
    assert (f"estimated from {m['used']} of {m['pairs']} keyframe pairs, rotation {m['rotation_deg']} deg, "
            f"translation [0.0, 0.0, 0.0] m from the nominal (body frame); translation nominal on body "
            f"x, y, z (the drive determines x, y, z to {u}, - mm, not 5 mm)") in info.stdout, info.stdout


def test_a_drive_too_short_to_estimate_its_mounting_builds_nominal_unless_the_estimate_is_insisted_on(tmp_path):
    """`map build` (default) on a 3 m drive: a warning, the nominal mounting, and `map info` says
    why; `--calibrate-mounting` on it: one line naming the drive and the option, no map."""
    from blockloc.datasets.base import ImuData
    from blockloc.datasets.nclt import NCLT_T_BODY_LIDAR, write_session

    from .synthetic import MemorySequence, route, world_points

    world = world_points(extent=(-20, 40), seed=2, density=0.3)
    traj = route([[0, 0], [3, 0]], speed=1.0)
    seq = MemorySequence(world, traj, radius=20.0, T_body_lidar=np.asarray(NCLT_T_BODY_LIDAR, float))
    imu = ImuData(traj.stamps, np.zeros((len(traj), 3)), np.zeros((len(traj), 3)))
    write_session(tmp_path / "sess", date="2012-01-15", frames=seq.frames(), imu=imu, ground_truth=traj)
    res = _blockloc("map", "build", "--seq", tmp_path / "sess", "--kind", "block", "--out", tmp_path / "m")
    assert res.returncode == 0, res.stderr
    assert "LiDAR mounting kept as the sequence gives it (nominal: the estimate failed" in res.stderr
    info = " ".join(_blockloc("map", "info", tmp_path / "m").stdout.split())
    assert "nominal, the sequence's own (the estimate failed:" in info
    res = _blockloc("map", "build", "--seq", tmp_path / "sess", "--kind", "block", "--calibrate-mounting",
                    "--out", tmp_path / "m2")
    assert res.returncode != 0 and not (tmp_path / "m2").exists()
    (line,) = [ln for ln in res.stderr.splitlines() if ln.startswith("error: ")]
    assert "--calibrate-mounting needs keyframes" in line and "Traceback" not in res.stderr


def test_map_build_remove_dynamic_from_the_command_line(tmp_path):
    """`map build --remove-dynamic` on a day with pedestrians and traffic (the tiny world's
    12-month mapping drive): moving points are left out (counted in the manifest and in `map
    info`), the block map holds fewer points than the build that keeps them; a grid build takes
    the option too; a global PCD is refused naming it."""
    import json
    import subprocess

    from blockloc.maps.store import open_map

    from blockloc.sim.writer import generate_dataset

    # 100 frames of the 12-month day at 128 columns a sweep: pedestrians and cars in sight, seconds to write
    day = generate_dataset("tiny", 1, tmp_path / "d", sessions=("map",), max_frames=100, months=(12,),
                           workers=0, azimuth_steps=128) / "map_m12"

    def build(*extra, out):
        res = subprocess.run(["blockloc", "map", "build", "--seq", str(day),
                              "--nominal-mounting", *extra, "--out", str(tmp_path / out)],
                             capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
        return open_map(tmp_path / out), res.stdout

    kept, _ = build("--kind", "block", "--keep-dynamic", out="kept")
    left, text = build("--kind", "block", "--remove-dynamic", out="left")
    rd = left.params["remove_dynamic"]
    assert rd["moving_points"] > 0 and rd["raw_points"] > 10 * rd["moving_points"], rd
    assert "remove_dynamic" not in kept.params
    assert sum(e.num_points for e in left.entries) < sum(e.num_points for e in kept.entries)
    assert f"left out: {rd['moving_points']:,} of" in " ".join(text.split())
    grid, _ = build("--kind", "grid", "--remove-dynamic", out="grid")
    assert grid.params["remove_dynamic"]["moving_points"] > 0
    manifest = json.loads((tmp_path / "left" / "manifest.json").read_text())
    assert manifest["parameters"]["remove_dynamic"]["context_keyframes"] == 8
    res = subprocess.run(["blockloc", "map", "build", "--from-pcd", str(tmp_path / "g.pcd"), "--poses",
                          str(tmp_path / "p.tum"), "--remove-dynamic", "--out", str(tmp_path / "g")],
                         capture_output=True, text=True)
    assert res.returncode != 0 and "--remove-dynamic needs --seq" in res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "g").exists()


def test_mapping_sequence_reads_every_form_the_manifest_records():
    from blockloc.app.runs import mapping_sequence

    assert mapping_sequence({"sequence": "sim:small/map@1"}) == "sim:small/map@1"
    assert mapping_sequence({"sequence": "sim:small/map@1[0:900]"}) == "sim:small/map@1"
    assert mapping_sequence({"sequence": "/d/a[5:] + /d/b", "drives": [{"sequence": "/d/a[5:]"},
                                                                     {"sequence": "/d/b"}]}) == "/d/a"
    assert mapping_sequence({"sequence": "/d/a + /d/b"}) == "/d/a"
    assert mapping_sequence({}) is None and mapping_sequence({"sequence": ""}) is None


def test_map_index_of_a_map_built_from_part_of_a_drive_finds_the_drives_gravity(tmp_path):
    """A map built from `DRIVE[START:STOP]` records that slice as its sequence: `map index` (and the
    node) must open the drive itself for gravity (they refused it: "expected sim:<preset>/...")."""
    import json

    from blockloc.datasets.base import ImuData
    from blockloc.datasets.nclt import write_session

    from .synthetic import MemorySequence, route, world_points

    world = world_points(extent=(-30, 90), seed=3, density=0.2)
    traj = route([[0, 0], [60, 0]], speed=5.0)
    seq = MemorySequence(world, traj, radius=20.0)
    imu = ImuData(traj.stamps, np.zeros((len(traj), 3)), np.zeros((len(traj), 3)))
    write_session(tmp_path / "sess", date="2012-01-15", frames=seq.frames(), imu=imu, ground_truth=traj)
    res = _blockloc("map", "build", "--seq", f"{tmp_path / 'sess'}[0:80]", "--kind", "block", "--block-size", "20",
                    "--nominal-mounting", "--out", tmp_path / "bm")
    assert res.returncode == 0, res.stderr
    assert json.loads((tmp_path / "bm" / "manifest.json").read_text())["parameters"]["sequence"].endswith("[0:80]")
    (tmp_path / "bm" / "place_index.npz").unlink()  # the index `map build` wrote, rebuilt below
    res = _blockloc("map", "index", tmp_path / "bm")
    assert res.returncode == 0, res.stderr
    assert "place index of" in res.stdout
    from blockloc.app.catalog import open_sequence
    from blockloc.global_init.place_index import PLACE_INDEX_NAME, PlaceIndex

    store = open_map(tmp_path / "bm")
    got = PlaceIndex.from_bytes(store.load_extra(PLACE_INDEX_NAME)).gravity_map
    np.testing.assert_allclose(got, open_sequence(str(tmp_path / "sess")).info.gravity_map)
