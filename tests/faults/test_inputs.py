"""Finding 6: the smaller faults. Binary files where CSVs belong, config values out of range,
a ground-truth warning that names a file nobody should create, ``map plot``'s blocks, and
progress when the output is piped."""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
import time

import numpy as np
import pytest

from .cases import Case, case, table
from .conftest import cli_in_process

BINARY = bytes(range(128, 256)) * 16  # no line of valid UTF-8 text


@case(6, "a binary ms25.csv in an NCLT session", "exit 2, one line naming ms25.csv and its line "
      "(was UnicodeDecodeError naming no file)")
def test_binary_ms25_csv(tiny_world, tmp_path):
    sess = shutil.copytree(tiny_world["session"], tmp_path / "sess")
    (sess / "ms25.csv").write_bytes(BINARY)
    r = cli_in_process("track", "--seq", sess, "--map", tiny_world["map"], "--init", "gt", "--config",
                       tiny_world["config"], "--out", tmp_path / "res")
    assert r.code == 2 and len(r.err_lines) == 1, r.err
    assert r.err_lines[0].startswith(f"error: {sess / 'ms25.csv'}:1: binary bytes")
    assert not (tmp_path / "res").exists()


@case(6, "a binary groundtruth_<date>.csv in an NCLT session", "one DatasetError naming the file "
      "and its line")
def test_binary_ground_truth_csv(tiny_world, tmp_path):
    from blockloc.datasets.nclt import NcltSequence
    from blockloc.errors import DatasetError

    sess = shutil.copytree(tiny_world["session"], tmp_path / "sess")
    gt = next(sess.glob("groundtruth_*.csv"))
    gt.write_bytes(b"1000000,0,0,0,0,0,0\n" + BINARY)
    with pytest.raises(DatasetError, match=rf"^{gt}:2: binary bytes"):
        NcltSequence(sess).ground_truth()


CONFIG_RANGES = table("test_config_value_out_of_range", [
    Case("voxel-size-negative", 6, "map.voxel_size_m: -1", "ConfigError naming the key, >= 0",
         needle="map.voxel_size_m: expected a value >= 0, got -1.0"),
    Case("rate-nan", 6, "imu.rate_hz: .nan", "ConfigError: expected a finite number",
         needle="imu.rate_hz: expected a finite number, got nan"),
    Case("rate-inf", 6, "lidar.rate_hz: .inf", "ConfigError: expected a finite number",
         needle="lidar.rate_hz: expected a finite number"),
    Case("rate-zero", 6, "imu.rate_hz: 0", "ConfigError: > 0",
         needle="imu.rate_hz: expected a value > 0, got 0.0"),
    Case("block-size-negative", 6, "map.block_size_m: -40", "ConfigError: > 0",
         needle="map.block_size_m: expected a value > 0"),
    Case("count-zero", 6, "tracking.window_size: 0", "ConfigError: >= 1",
         needle="tracking.window_size: expected a value >= 1, got 0"),
    Case("probability-one", 6, "global_init.min_fitness: 1.0", "ConfigError: in (0, 1)",
         needle="global_init.min_fitness: expected a value in (0, 1)"),
    Case("fraction-negative", 6, "tracking.min_fitness: -0.1", "ConfigError: in [0, 1]",
         needle="tracking.min_fitness: expected a value in [0, 1]"),
    Case("yaw-window-too-wide", 6, "global_init.yaw_window_deg: 720", "ConfigError: in (0, 360]",
         needle="global_init.yaw_window_deg: expected a value in (0, 360]"),
    Case("rpe-delta-negative", 6, "evaluation.rpe_deltas_m: [1, -10]", "ConfigError naming the key",
         needle="evaluation.rpe_deltas_m: expected a value > 0"),
    Case("band-nan", 6, "global_init.height_band_m: [0.3, .nan]", "ConfigError naming the element",
         needle="global_init.height_band_m[1]: expected a finite"),
    Case("fraction-in-scientific-notation", 6, "tracking.min_fitness: 5e0",
         "ConfigError: in [0, 1], the value read as 5.0 (was 'expected a number')",
         needle="tracking.min_fitness: expected a value in [0, 1], got 5.0"),
    Case("rate-overflowing-notation", 6, "imu.rate_hz: 1e999", "ConfigError: expected a finite number",
         needle="imu.rate_hz: expected a finite number, got '1e999'"),
    Case("count-a-fraction-in-notation", 6, "registration.max_iterations: 2.5e0",
         "ConfigError: an integer field refuses a fraction in any notation",
         needle="registration.max_iterations: expected an integer, got '2.5e0'"),
])


@pytest.mark.parametrize("c", CONFIG_RANGES, ids=lambda c: c.id)
def test_config_value_out_of_range(c: Case, tmp_path):
    from blockloc.config import load_config
    from blockloc.errors import ConfigError

    dotted, value = c.what.split(": ", 1)  # "section.key: value"
    section, key = dotted.split(".")
    path = tmp_path / "c.yaml"
    path.write_text(f"{section}:\n  {key}: {value}\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: ") and c.needle in msg and "\n" not in msg


@case(6, "numbers in scientific notation, which YAML 1.1 (PyYAML) reads as strings: `--set "
      "tracking.min_fitness=5e-1`, `--set registration.max_iterations=3E1`, a config file with "
      "`voxel_size_m: 4e-1` and `max_points: 6e3`",
      "exit 0; the run's config.yaml holds the floats 0.5 and 0.4 and the integers 30 and 6000 (was "
      "'expected a number, got '5e-1''); an integer field takes an integral value in any notation")
def test_scientific_notation_in_set_and_config_file(tiny_world, tmp_path):
    import yaml

    from . import tiny

    config = tmp_path / "sci.yaml"  # tiny.CONFIG, with numbers as a user may write them
    config.write_text(f"lidar:\n  rate_hz: {tiny.RATE_HZ}\n  max_points: 6e3\n  voxel_size_m: 4e-1\n"
                      f"map:\n  block_size_m: {tiny.BLOCK_SIZE_M}\n  prefetch: false\n"
                      "evaluation:\n  plots: false\n")
    out = tmp_path / "res"
    r = cli_in_process("track", "--seq", tiny_world["session"], "--map", tiny_world["map"], "--init", "gt",
                       "--config", config, "--out", out, "--max-frames", "2", "--no-record",
                       "--set", "tracking.min_fitness=5e-1", "--set", "registration.max_iterations=3E1")
    assert r.code == 0, r.err
    used = yaml.safe_load((out / "config.yaml").read_text())
    assert used["tracking"]["min_fitness"] == 0.5 and used["lidar"]["voxel_size_m"] == 0.4
    assert used["lidar"]["max_points"] == 6000 and type(used["lidar"]["max_points"]) is int
    assert used["registration"]["max_iterations"] == 30 and type(used["registration"]["max_iterations"]) is int


@case(6, "`map build` of a scan folder without stamps (scans named 000000.pcd ..., KITTI poses without "
      "times): the loader warns that it assumes 10 Hz", "the warning once, before the build's progress, as "
      "track and init give it (was twice: the command opened the drive again after the build, for its "
      "gravity)")
def test_map_build_gives_a_drives_warning_once(tiny_world, tmp_path):
    from blockloc.trajectory_io import read_tum, write_kitti

    from .conftest import cli_process

    folder = tmp_path / "walk"
    (folder / "scans").mkdir(parents=True)
    for i, scan in enumerate(sorted((tiny_world["folder"] / "scans").glob("*.pcd"), key=lambda p: float(p.stem))):
        shutil.copy(scan, folder / "scans" / f"{i:06d}.pcd")
    write_kitti(folder / "poses_kitti.txt", read_tum(tiny_world["folder"] / "poses.tum"), write_times=False)
    r = cli_process("map", "build", "--seq", folder / "scans", "--poses", folder / "poses_kitti.txt", "--block-size",
                    "8", "--nominal-mounting", "--no-refine-poses", "--out", tmp_path / "map")
    assert r.code == 0, r.err
    warnings = [ln for ln in r.err.splitlines() if "no scan stamps" in ln]
    assert len(warnings) == 1 and warnings[0].startswith("WARNING "), r.err
    assert r.err.index("no scan stamps") < r.err.index("map build tasks")


@case(6, "the defaults and every preset against the declared ranges", "all within them (a bound "
      "that rejects a shipped value would be wrong)")
def test_defaults_and_presets_lie_in_their_ranges():
    from blockloc.config import PRESET_DIR, Config, load_config

    checked = 0
    for cfg in [Config()] + [load_config(p) for p in sorted(PRESET_DIR.glob("*.yaml"))]:
        for section in dataclasses.fields(cfg):
            sub = getattr(cfg, section.name)
            for f in dataclasses.fields(sub):
                value = getattr(sub, f.name)
                values = value if isinstance(value, tuple) else (value,)
                assert all(not isinstance(v, float) or math.isfinite(v) for v in values), (section.name, f.name)
                bounds = f.metadata.get("bounds")
                if bounds is not None:
                    assert all(bounds.contains(v) for v in values), (section.name, f.name, value, str(bounds))
                    checked += 1
    assert checked > 200  # 5 configs x ~60 bounded fields


@case(6, "an NCLT-layout session in a directory called 'loc' without ground truth; then one "
      "groundtruth_<date>.csv where ground truth is searched",
      "the warning names groundtruth_<date>.csv and the directories searched (not groundtruth_loc.csv); "
      "the one file is found")
def test_ground_truth_warning_names_the_real_pattern(tiny_world, tmp_path, caplog):
    from blockloc.datasets.nclt import NcltSequence

    loc = shutil.copytree(tiny_world["session"], tmp_path / "data" / "loc")
    gt = next(loc.glob("groundtruth_*.csv"))
    gt.unlink()
    with caplog.at_level(logging.WARNING, logger="blockloc.datasets.nclt"):
        assert NcltSequence(loc).ground_truth() is None
    msg = caplog.text
    assert "groundtruth_<date>.csv" in msg and "groundtruth_loc.csv" not in msg
    assert str(tmp_path / "data" / "ground_truth") in msg
    (tmp_path / "data" / "ground_truth").mkdir()
    shutil.copy(tiny_world["session"] / gt.name, tmp_path / "data" / "ground_truth" / gt.name)
    seq = NcltSequence(loc)
    assert seq.date == gt.stem.removeprefix("groundtruth_") and seq.ground_truth() is not None


@case(6, "`map plot` of a block map of 8 m blocks (stored bounds ~55 m: sensor range)",
      "each block drawn as its footprint (keyframe hull + 5 m): holds its keyframes, < 1/4 of its "
      "bounds' area; coloured patches with a legend naming every block and the trajectory")
def test_map_plot_draws_footprints_with_a_legend(tiny_world, tmp_path):
    from matplotlib.path import Path as MplPath

    from blockloc.datasets.nclt import NcltSequence
    from blockloc.maps.plot import map_figure, plot_map, polygon_area
    from blockloc.maps.store import open_map

    store = open_map(tiny_world["map"])
    traj = NcltSequence(tiny_world["long"]).ground_truth()
    fig, footprints = map_figure(store, traj)
    assert set(footprints) == set(store.ids) and len(store.ids) >= 5
    for e in store.entries:
        poly = footprints[e.id]
        box = np.prod((e.bounds_max - e.bounds_min)[:2])
        assert polygon_area(poly) < box / 4, (e.id, polygon_area(poly), box)
        assert MplPath(poly).contains_points(e.keyframes[:, :2]).all()
    legend = fig.axes[0].get_legend()
    labels = [t.get_text() for t in legend.get_texts()]
    assert all(any(lb.startswith(f"block {i} ") for lb in labels) for i in store.ids)
    assert "trajectory" in labels
    colours = {tuple(np.round(p.get_edgecolor(), 3)) for p in fig.axes[0].patches}
    assert len(colours) == len(store.ids)  # one colour per block
    import matplotlib.pyplot as plt

    plt.close(fig)
    png = plot_map(store, tmp_path / "m.png", traj)
    assert png.read_bytes()[:4] == b"\x89PNG"


@case(6, "progress while the output is piped, during a step that reports nothing for a while "
      "(the demo's global initialization)", "a line to stderr at least every heartbeat (30 s; 0.3 s here)")
def test_progress_heartbeat_when_piped(capfd):
    from blockloc.commands.common import progress

    with progress("tracking", 100, heartbeat_s=0.3) as cb:
        time.sleep(1.0)  # a global init: no frame done yet
        cb(100)
    lines = capfd.readouterr().err.splitlines()
    beats = [ln for ln in lines if ln.startswith("tracking: 0/100 (0%), working for")]
    assert len(beats) >= 2 and lines[-1] == "tracking: 100/100 (100%)"


@case(6, "`blockloc demo`'s global initialization (86 s on a fresh clone here) with its output piped",
      "run_tracking, which the demo and track run, prints 'tracking: 0/N (0%), working for S s' while "
      "the initialization reports nothing (every 30 s; 0.3 s here), then the frames in 10% steps")
def test_demo_initialization_prints_progress_when_piped(tiny_world, monkeypatch, capfd):
    from blockloc.commands import common
    from blockloc.app.runs import open_session
    from blockloc.commands.track import run_tracking
    from blockloc.config import load_config
    from blockloc.app.session import Session

    monkeypatch.setattr(common, "HEARTBEAT_S", 0.3)
    initialize = Session.initialize

    def slow_initialize(self, *args, **kw):  # a global init: a long step that reports nothing
        time.sleep(1.2)
        return initialize(self, *args, **kw)

    monkeypatch.setattr(Session, "initialize", slow_initialize)
    session = open_session(str(tiny_world["session"]), cfg=load_config(tiny_world["config"]),
                           map_path=str(tiny_world["map"]))
    run_tracking(session, mode="gt", hint=None, out_dir=None, max_frames=5)
    err = capfd.readouterr().err.splitlines()
    assert len([ln for ln in err if ln.startswith("tracking: 0/5 (0%), working for")]) >= 2
    assert err[-1] == "tracking: 5/5 (100%)"
