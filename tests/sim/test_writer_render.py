"""``sim/writer.py`` (what ``generate_dataset`` records, its errors, its atomic replace) and
``sim/render.py`` (the top-down PNG of a world and its routes), directly."""

from __future__ import annotations

import json

import numpy as np
import pytest

from blockloc.datasets.nclt import NCLT_GRAVITY_MAP, NCLT_T_BODY_LIDAR, NcltSequence
from blockloc.errors import SimError
from blockloc.sim.presets import get_preset
from blockloc.sim.stream import open_sim_sequence
from blockloc.sim.writer import generate_dataset

SEED, STEPS = 5, 40


def test_sim_json_records_sessions_and_nclt_frames(tmp_path):
    calls = []
    out = generate_dataset("tiny", SEED, tmp_path / "d", max_frames=3, azimuth_steps=STEPS,
                           sessions=("loc",), progress=lambda s, k, n: calls.append((s, k, n)))
    meta = json.loads((out / "sim.json").read_text())
    assert meta["preset"] == "tiny" and meta["seed"] == SEED and meta["format"] == "nclt"
    assert meta["azimuth_steps"] == STEPS and list(meta["sessions"]) == ["loc"]
    np.testing.assert_allclose(meta["frames"]["T_body_lidar"], NCLT_T_BODY_LIDAR)
    assert meta["frames"]["gravity_map"] == list(NCLT_GRAVITY_MAP)
    sim = open_sim_sequence("tiny", "loc", SEED, azimuth_steps=STEPS)
    rec = meta["sessions"]["loc"]
    assert rec["frames"] == 3 and rec["date"] == sim.date
    assert rec["path_length_m"] == pytest.approx(sim.trajectory.path_length(), abs=0.01)
    total = len(sim)
    assert calls == [("loc", 1, total), ("loc", 2, total), ("loc", 3, total)]
    assert sorted(p.name for p in out.iterdir()) == [".blockloc-output.json", "loc", "sim.json"]
    seq = NcltSequence(out / "loc")
    assert len(seq) == 3
    np.testing.assert_allclose(seq.info.T_body_lidar, NCLT_T_BODY_LIDAR)
    # ground truth and IMU are cut to the frames' span (+0.2 s), not the whole drive
    t_end = sim.frame_stamps()[2] + 0.2
    assert seq.ground_truth().stamps[-1] <= t_end + 1e-6
    assert seq.imu().t[-1] <= t_end + 1e-6 and seq.imu().t[-1] > sim.frame_stamps()[2]
    # the mapping session (the preset's first) also gets offline-SLAM poses; loc does not
    assert not list((out / "loc").glob("slam_poses_*.csv"))


def test_bad_format_and_session(tmp_path):
    with pytest.raises(SimError, match="sim format 'las'"):
        generate_dataset("tiny", SEED, tmp_path / "a", "las")
    with pytest.raises(SimError, match="sim session 'loc9'"):
        generate_dataset("tiny", SEED, tmp_path / "b", sessions=("loc9",), max_frames=1)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_failed_run_keeps_the_old_dataset_and_leaves_no_temp(tmp_path):
    out = tmp_path / "d"
    generate_dataset("tiny", SEED, out, max_frames=2, azimuth_steps=STEPS, sessions=("map",))
    before = (out / "sim.json").read_text()

    def interrupt(session, k, n):
        if k == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate_dataset("tiny", SEED + 1, out, max_frames=3, azimuth_steps=STEPS, sessions=("map",),
                         progress=interrupt)
    assert (out / "sim.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]
    assert list((out / "map").glob("slam_poses_*.csv"))  # the mapping session has them


def test_render_world_draws_the_routes(tmp_path):
    from matplotlib.image import imread

    from blockloc.sim.render import _ROUTE_COLORS, render_world

    out = render_world("tiny", SEED, tmp_path / "pics" / "world.png", dpi=40)
    assert out == tmp_path / "pics" / "world.png"
    assert sorted(p.name for p in out.parent.iterdir()) == ["world.png"]  # no temp file left
    img = imread(out)[..., :3]
    sx, sy = get_preset("tiny").size_m
    assert img.shape[1] == 12 * 40 and abs(img.shape[0] - (12 * sy / sx * 0.92 + 0.8) * 40) <= 1

    def share(hex_color, tol=0.08):
        rgb = np.array([int(hex_color[i:i + 2], 16) for i in (1, 3, 5)]) / 255.0
        return float(np.mean(np.all(np.abs(img - rgb) < tol, axis=-1)))

    # both sessions' routes are drawn in their colours; a third colour is not used
    assert share(_ROUTE_COLORS[0]) > 1e-5 and share(_ROUTE_COLORS[1]) > 1e-5
    assert share(_ROUTE_COLORS[3]) == 0.0
    only_map = render_world("tiny", SEED, tmp_path / "map.png", sessions=("map",), dpi=40)
    img = imread(only_map)[..., :3]
    assert share(_ROUTE_COLORS[0]) > 1e-5 and share(_ROUTE_COLORS[1]) == 0.0
