"""`blockloc init` end to end on a small NCLT-layout session and a tiled map store (subprocess)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from blockloc.datasets.base import ImuData, LidarFrame
from blockloc.datasets.nclt import write_session
from blockloc.geometry import Trajectory, T_to_xyzrpy, inv_T, xyzrpy_to_T
from blockloc.global_init.relocalize import pose_error
from blockloc.maps.store import MapWriter

from .synthetic import GRAVITY_Z_DOWN, Z_DOWN, gravity_body, scan_from, world_up

TRUE_XYZRPY = (8.0, -6.0, -(1.9 + 0.02 * 8.0), 0.02, -0.01, 1.1)


def _write_store(path, points, tile=40.0):
    with MapWriter(path, "grid", params={"tile_size_m": tile}) as w:
        keys = np.floor(points[:, :2] / tile).astype(int)
        for k in np.unique(keys, axis=0):
            sel = np.all(keys == k, axis=1)
            w.add(f"{(k[0] + 0.5) * tile:.1f}_{(k[1] + 0.5) * tile:.1f}", points[sel].astype(np.float32))
        w.commit()


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("init_cli")
    world = world_up(seed=11) @ Z_DOWN.T
    _write_store(root / "map", world)
    _write_store(root / "other_map", world_up(seed=12) @ Z_DOWN.T)
    T = xyzrpy_to_T(*TRUE_XYZRPY)
    scan = scan_from(world, T, radius=40.0).astype(np.float32)
    stamps = 100.0 + np.arange(3) * 0.1
    frames = [LidarFrame(i, s, scan, np.full(len(scan), 50, np.float32), np.zeros(len(scan), np.float32),
                         np.zeros(len(scan), np.uint16)) for i, s in enumerate(stamps)]
    t = np.arange(99.5, 101.0, 0.01)
    acc = np.tile(-gravity_body(T), (len(t), 1)) + np.random.default_rng(0).normal(0, 0.02, (len(t), 3))
    imu = ImuData(t, acc, np.zeros((len(t), 3)))
    gt = Trajectory(stamps, np.repeat(T[None], len(stamps), axis=0))
    write_session(root / "session", date="2012-01-01", frames=frames, imu=imu, ground_truth=gt,
                  write_hits=False, T_body_lidar=np.eye(4), T_body_imu=np.eye(4), gravity_map=GRAVITY_Z_DOWN)
    env = dict(os.environ, BLOCKLOC_CACHE=str(root / "cache"))
    return root, T, env


def _run(env, *args):
    return subprocess.run([sys.executable, "-m", "blockloc.cli", "init", *args], capture_output=True,
                          text=True, env=env, timeout=300)


def test_init_with_a_hint_prints_the_body_pose_as_json(setup):
    root, T, env = setup
    p = _run(env, "--seq", str(root / "session"), "--frame", "1", "--map", str(root / "map"),
             "--pose-hint", "20,-15", "--json")
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    T_est = xyzrpy_to_T(*(out[k] for k in ("x", "y", "z", "roll", "pitch", "yaw")))
    dt, dr = pose_error(T_est, T)
    assert dt < 0.1 and dr < 0.5, (dt, dr)
    assert out["verified"] and out["fitness"] >= 0.5 and out["time_s"] > 0
    # through the place index in the hint's window (the store has none: built and cached once)
    assert out["stats"]["hint_search"] == "places" and out["stats"]["places_in_window"] > 0
    # the cold start, apart: opening the map, loading (here building) the index, the first search
    cold = out["cold"]
    assert cold["map_open_s"] > 0 and cold["index_load_s"] > 0 and cold["search_s"] > 0
    assert cold["total_s"] == pytest.approx(cold["map_open_s"] + cold["index_load_s"] + cold["search_s"], abs=0.003)
    assert cold["total_s"] >= out["time_s"]
    # the per-tile pyramids were cached under BLOCKLOC_CACHE
    assert list((root / "cache" / "global_init").rglob("*.npz"))


def test_init_without_a_hint_relocalizes_over_the_whole_map(setup):
    root, T, env = setup
    p = _run(env, "--seq", str(root / "session"), "--frame", "0", "--map", str(root / "map"), "--json")
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert np.hypot(out["x"] - T[0, 3], out["y"] - T[1, 3]) < 0.1
    assert out["stats"]["regions_searched"] >= 1


def test_init_text_output(setup):
    root, _, env = setup
    p = _run(env, "--seq", str(root / "session"), "--frame", "2", "--map", str(root / "map"),
             "--pose-hint", "8,-6,1.1", "--yaw-window", "30")
    assert p.returncode == 0, p.stderr
    assert "T_map_body" in p.stdout and "fitness" in p.stdout


@pytest.mark.parametrize("args, message", [
    (["--pose-hint", "900,0"], "outside the map"),
    (["--pose-hint", "0,0", "--window", "0"], "--window 0"),
    (["--pose-hint", "abc"], "--pose-hint"),
    (["--frame", "99"], "--frame 99"),
])
def test_init_bad_input_is_one_line_and_non_zero(setup, args, message):
    root, _, env = setup
    base = {"--seq": str(root / "session"), "--frame": "0", "--map": str(root / "map")}
    for i in range(0, len(args), 2):
        base[args[i]] = args[i + 1]
    p = _run(env, *[x for kv in base.items() for x in kv])
    assert p.returncode != 0
    assert message in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_init_no_match_says_so_with_the_best_score(setup):
    root, _, env = setup
    p = _run(env, "--seq", str(root / "session"), "--frame", "0", "--map", str(root / "other_map"),
             "--pose-hint", "8,-6")
    assert p.returncode != 0
    assert "no verified match (best score" in p.stderr


def _blockloc(env, *args):
    return subprocess.run([sys.executable, "-m", "blockloc.cli", *args], capture_output=True, text=True, env=env,
                          timeout=300)


def test_map_index_then_init_without_a_hint_uses_the_place_index(setup, tmp_path):
    import shutil

    root, T, env = setup
    shutil.copytree(root / "map", tmp_path / "map")
    p = _blockloc(env, "map", "index", str(tmp_path / "map"), "--gravity", "down")
    assert p.returncode == 0, p.stderr
    manifest = json.loads((tmp_path / "map" / "manifest.json").read_text())
    extra = manifest["extras"]["place_index.npz"]
    assert (tmp_path / "map" / extra["file"]).stat().st_size == extra["bytes"]
    p = _run(env, "--seq", str(root / "session"), "--frame", "0", "--map", str(tmp_path / "map"), "--json")
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert set(out) >= {"pose", "verified", "ambiguous", "time_s", "compile_s", "candidates"}
    assert out["verified"] and not out["ambiguous"] and out["time_s"] > 0 and out["candidates"]
    T_est = xyzrpy_to_T(*(out["pose"][k] for k in ("x", "y", "z", "roll", "pitch", "yaw")))
    dt, dr = pose_error(T_est, T)
    assert dt < 0.1 and dr < 0.5, (dt, dr)
    assert out["stats"]["place_stage"] >= 1 and out["stats"]["places"] > 0  # found through the index
    assert "error_m" in out and out["error_m"] < 0.1  # the session has ground truth


def test_map_index_precompute_fills_the_caches_that_later_searches_read(setup, tmp_path, monkeypatch):
    import shutil

    root, T, env = setup
    shutil.copytree(root / "map", tmp_path / "map")
    env = dict(env, BLOCKLOC_CACHE=str(tmp_path / "cache"))
    p = _blockloc(env, "map", "index", str(tmp_path / "map"), "--gravity", "down", "--precompute")
    assert p.returncode == 0, p.stderr
    entries = json.loads((tmp_path / "map" / "manifest.json").read_text())["entries"]
    out = " ".join(p.stdout.split())
    assert f"global-init caches of {tmp_path / 'map'}: {len(entries)} entries" in out
    assert f"refinement statistics of {len(entries)} on disk" in out
    cache = tmp_path / "cache" / "global_init"
    (targets,) = cache.glob("targets-*")  # one entry's refinement statistics a file, named by its content
    assert sorted(f.stem for f in targets.glob("*.npz")) == sorted(e["sha256"] for e in entries)
    assert len(list(cache.glob("points-*/*.points.npy"))) == len(entries)
    pyramids = [d for d in cache.iterdir() if d.name.startswith("v")]
    assert pyramids and all(len(list(d.glob("*.npz"))) == len(entries) for d in pyramids)
    stamp = {f: f.stat().st_mtime_ns for f in targets.glob("*.npz")}
    # a search afterwards finds the pose as before and rewrites none of it
    p = _run(env, "--seq", str(root / "session"), "--frame", "0", "--map", str(tmp_path / "map"), "--json")
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["verified"] and out["error_m"] < 0.1
    # a process that searches again (a session, the node) with the same settings reads every entry
    # its targets need from those files and builds none
    from blockloc.app.assemble import make_localizer
    from blockloc.app.catalog import open_sequence
    from blockloc.commands.common import config_for
    from blockloc.global_init.scan_prep import prepare_for_init
    from blockloc.maps.store import open_map

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path / "cache"))
    seq = open_sequence(str(root / "session"))
    scan = prepare_for_init(seq.frame(0), seq.imu(), seq.info)
    loc = make_localizer(open_map(tmp_path / "map"), GRAVITY_Z_DOWN, config_for(None, None))
    for _ in range(2):
        res = loc.localize(scan.points_body, scan.gravity_body)
    loc.target_cache.flush()
    assert res.verified and 0 < loc.target_cache.misses == loc.target_cache.loaded
    assert {f: f.stat().st_mtime_ns for f in targets.glob("*.npz")} == stamp


@pytest.mark.parametrize("args, message", [
    (["--gravity", "sideways"], "--gravity 'sideways'"),
    (["--gravity", "0,0,0"], "--gravity '0,0,0'"),
    ([], "give --gravity"),  # the test map's manifest names no mapping sequence
])
def test_map_index_bad_input_is_one_line_and_non_zero(setup, args, message):
    root, _, env = setup
    p = _blockloc(env, "map", "index", str(root / "map"), *args)
    assert p.returncode != 0
    assert message in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "extras" not in json.loads((root / "map" / "manifest.json").read_text())


def test_search_time_never_goes_negative_when_the_compile_falls_outside_the_localizers_clock():
    from blockloc.app.runs import search_seconds

    # CI: the localizer timed 0.4 s of a 1.5 s call whose first 0.9 s compiled kernels
    assert search_seconds(0.4, 1.5, 0.9) == pytest.approx(0.4)
    # the compile inside the localizer's own clock comes off it
    assert search_seconds(1.3, 1.5, 0.9) == pytest.approx(0.6)
    assert search_seconds(0.4, 0.5, 0.9) == 0.0
