"""Presets ship inside the package, and ``--config`` tells a preset from a path without guessing
from the current directory: a path has a slash or an extension; a bare word is a preset, which
wins (with one warning line) over a file or directory of that name in the current directory."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

from blockloc.config import PRESET_DIR, config_file, load_config, looks_like_path, preset_names
from blockloc.errors import ConfigError
from blockloc.maps.store import open_map
from tests.faults import tiny

REPO = Path(__file__).resolve().parent.parent


def _blockloc(*args, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    """``blockloc ARGS`` as a user types it (the console script), this checkout on the path."""
    exe = shutil.which("blockloc")
    if exe is None:
        (pytest.fail if os.environ.get("CI", "").lower() == "true" else pytest.skip)("the blockloc console script is not installed (pip install -e .)")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
               BLOCKLOC_CACHE=str(cwd / ".cache"), COLUMNS="200")
    return subprocess.run([exe, *map(str, args)], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def test_names_and_paths_are_told_apart_by_their_text(tmp_path, monkeypatch):
    assert {"default", "sim", "nclt", "m2dgr", "handheld"} <= set(preset_names())
    assert not looks_like_path("handheld") and looks_like_path("./handheld") and looks_like_path("my.yaml")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine").write_text("map:\n  block_size_m: 7\n")
    with pytest.raises(ConfigError, match=r"mine: no such preset .*give it as ./mine"):
        load_config("mine")
    assert load_config("./mine").map.block_size_m == 7.0
    (tmp_path / "dir.yaml").mkdir()
    with pytest.raises(ConfigError, match="dir.yaml: a directory, expected a YAML config file"):
        load_config("dir.yaml")
    with pytest.raises(ConfigError, match="nothere.yaml: no such config file"):
        load_config("nothere.yaml")
    assert config_file("sim") == PRESET_DIR / "sim.yaml"
    # the preset a sequence implies is never a file of the current directory, and says nothing
    (tmp_path / "sim").mkdir()
    assert load_config(preset="sim").map.block_size_m == load_config(PRESET_DIR / "sim.yaml").map.block_size_m


@pytest.fixture(scope="module")
def tiny_session(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("presets")
    return tiny.write_tiny_session(root / "sess", n_frames=12)


def test_a_sim_folder_in_the_cwd_does_not_break_a_map_build_of_a_sim_session(tiny_session, tmp_path):
    """Issue 40: ``map build`` of a session written by ``blockloc sim`` (sim.json beside it: the
    sim preset) failed with IsADirectoryError when the cwd held a folder ``sim/``."""
    data = tmp_path / "data"
    shutil.copytree(tiny_session, data / "loc")
    (data / "sim.json").write_text(json.dumps({"preset": "tiny"}))
    (tmp_path / "sim").mkdir()
    r = _blockloc("map", "build", "--seq", "data/loc", "--kind", "block", "--out", "m", "--max-frames", "6",
                  cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    # the only warning: 6 frames are too short to estimate the LiDAR mounting (issue 41's default)
    warnings = [ln for ln in r.stderr.splitlines() if "WARNING" in ln and "LiDAR mounting kept" not in ln]
    assert "IsADirectoryError" not in r.stderr and not warnings, r.stderr[-2000:]
    assert open_map(tmp_path / "m").params["block_size_m"] == load_config(preset="sim").map.block_size_m


def test_a_preset_name_wins_over_a_file_of_that_name_with_one_warning(tiny_session, tmp_path):
    """Issue 40: a file ``./handheld`` silently replaced the preset ``handheld``."""
    (tmp_path / "handheld").write_text("bogus_section:\n  x: 1\n")  # read, it would fail at load
    args = ("map", "build", "--seq", tiny_session, "--kind", "block", "--max-frames", "6")
    r = _blockloc(*args, "--out", "m1", "--config", "handheld", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    # (6 frames are too short to estimate the LiDAR mounting: that warning is issue 41's default)
    warnings = [line for line in r.stderr.splitlines() if "WARNING" in line and "LiDAR mounting kept" not in line]
    assert len(warnings) == 1 and "preset handheld.yaml is used, not ./handheld" in warnings[0], r.stderr
    assert open_map(tmp_path / "m1").params["voxel_size_m"] == load_config(preset="handheld").map.voxel_size_m == 0.1
    # the file, given as a path, is read (and its unknown section named)
    r = _blockloc(*args, "--out", "m2", "--config", "./handheld", cwd=tmp_path)
    assert r.returncode == 2 and "unknown section 'bogus_section'" in r.stderr and "handheld" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_every_preset_loads_by_name_from_an_installed_wheel(tmp_path):
    """A wheel holds the presets: built here, installed into a venv outside the repo (the
    dependencies from this interpreter's site-packages), each preset loaded by name from a cwd
    outside the repo."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    shutil.copytree(REPO / "blockloc", src / "blockloc", ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                            "-w", str(wheels), str(src)], capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stderr[-3000:]
    wheel = next(wheels.glob("blockloc-*.whl"))
    env_dir = tmp_path / "venv"
    venv.create(env_dir, system_site_packages=True, with_pip=False)
    py = env_dir / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "-q",
                              str(wheel)], capture_output=True, text=True, timeout=600, env=env)
    assert install.returncode == 0, install.stderr[-3000:]
    work = tmp_path / "elsewhere"
    work.mkdir()
    code = ("import json, blockloc\nfrom blockloc.config import load_config, preset_names\n"
            "names = preset_names()\n"
            "print(json.dumps({'file': blockloc.__file__, 'names': names,"
            " 'blocks': [load_config(n).map.block_size_m for n in names]}))")
    r = subprocess.run([str(py), "-c", code], cwd=work, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["file"].startswith(str(env_dir)), out["file"]  # the wheel's copy, not this checkout
    assert set(out["names"]) == set(preset_names())
    assert out["blocks"] == [load_config(n).map.block_size_m for n in out["names"]]
