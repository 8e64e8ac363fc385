"""``blockloc track --detect-changes`` as a user types it, and the changes drawn where a run is
looked at: the ``/changes/*`` layer of ``run.mcap`` and the changes section of ``report.html``
(also for ``blockloc map changes --run``).

The world is the fault suite's tiny NCLT-layout session (40 scans along a circle, IMU, ground
truth) tracked in its own block map, into which a phantom wall was put 6 m beside the path:
the run's rays pass through it, so it must come out as removed, in the block that holds it.
"""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

from blockloc.maps.store import MapWriter, open_map
from tests.faults import tiny

#: The phantom wall (map frame, m): 3 m along the path's tangent at angle 0.7 rad, 6 m outside
#: the 20 m circle, standing 3 m tall on the sloped ground. (Closer, the beams cross only its
#: lowest 1.5 m, which the detector leaves alone next to the ground the scans hit.)
PHANTOM_ANGLE, PHANTOM_RADIUS = 0.7, 26.0


def phantom_points() -> np.ndarray:
    c = PHANTOM_RADIUS * np.array([np.cos(PHANTOM_ANGLE), np.sin(PHANTOM_ANGLE)])
    tangent = np.array([-np.sin(PHANTOM_ANGLE), np.cos(PHANTOM_ANGLE)])
    s, h = np.meshgrid(np.arange(-1.5, 1.5, 0.2), np.arange(0.0, 3.0, 0.2))
    xy = c + s.reshape(-1, 1) * tangent
    ground = 0.02 * xy[:, 0] + 0.3 * np.sin(xy[:, 1] / 15.0)
    return np.c_[xy, ground + h.reshape(-1)]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The tiny session, its map with the phantom wall (in the block nearest to it), the config."""
    root = tmp_path_factory.mktemp("track_changes")
    session = tiny.write_tiny_session(root / "sess")
    clean = open_map(tiny.build_tiny_map(session, root / "clean"))
    wall = phantom_points()
    centre = wall.mean(axis=0)
    owner = min(clean.ids, key=lambda b: np.linalg.norm(clean.entry(b).centroid[:2] - centre[:2]))
    with MapWriter(root / "map", "block", params=dict(clean.params)) as w:
        for b in clean.ids:
            pts, inten = clean.load(b)
            if b == owner:
                pts = np.vstack([pts[:, :3], wall])
                inten = np.concatenate([np.asarray(inten, np.float32).reshape(-1), np.full(len(wall), 50, np.float32)])
            w.add(b, pts[:, :3], inten, keyframes=clean.entry(b).keyframes)
        w.commit()
    return {"root": root, "session": session, "map": root / "map", "owner": owner,
            "config": tiny.write_config(root / "cfg.yaml")}


def _cli(*args):
    return subprocess.run(["blockloc", *map(str, args)], capture_output=True, text=True)


def _mcap_changes(path):
    """topic -> points (clouds) or markers of the /changes/ topics; every topic's message count."""
    from mcap_ros2.decoder import DecoderFactory
    from mcap.reader import make_reader

    clouds, counts = {}, {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic.startswith("/changes/"):
                clouds[channel.topic] = (msg.width if hasattr(msg, "width") else
                                         [(m.ns, m.id, len(m.points)) for m in msg.markers])
    return clouds, counts


def _per_block(doc, key):
    return sum(b[key] for b in doc["blocks"])


@pytest.fixture(scope="module")
def tracked(world):
    """``track --detect-changes`` on the first 30 frames (one run shared by the tests: read-only)."""
    out = world["root"] / "run"
    r = _cli("track", "--seq", world["session"], "--map", world["map"], "--init", "gt", "--config", world["config"],
             "--out", out, "--max-frames", "30", "--detect-changes", "--changes-stride", "2")
    assert r.returncode == 0, r.stderr
    return out, r


def test_track_detect_changes_finds_the_phantom_and_draws_it(world, tracked):
    out, r = tracked
    doc = json.loads((out / "changes.json").read_text())
    assert doc["during"] == "track --detect-changes" and doc["frames_trusted"] >= 15
    assert doc["scans_used"] == (doc["frames_trusted"] + 1) // 2 and doc["scans_rejected"] == 0
    cost = doc["cost"]
    assert cost["cpu_s"] > 0 and cost["wall_s"] > 0 and cost["frames_tracked"] == 30
    blocks = {b["block"]: b for b in doc["blocks"]}
    assert blocks[world["owner"]]["removed_voxels"] >= 5 and blocks[world["owner"]]["removed_points"] >= 30
    clouds, counts = _mcap_changes(out / "run.mcap")
    assert clouds["/changes/removed"] == _per_block(doc, "removed_voxels") > 0
    assert clouds["/changes/added"] == _per_block(doc, "added_voxels")
    assert clouds["/changes/dynamic"] == _per_block(doc, "dynamic_voxels")
    cubes = {(ns, n) for ns, _, n in clouds["/changes/blocks"] if ns != "changes/label"}
    assert ("changes/removed", blocks[world["owner"]]["removed_voxels"]) in cubes
    # the tracking topics are all still there
    assert counts["/tf"] >= 20 and counts["/points/aligned"] >= 1 and counts["/diagnostics"] == 30
    page = (out / "report.html").read_text()
    section = page.split('<section id="changes">')[1].split("</section>")[0]
    assert page.count('<section id="changes">') == 1 and 'src="data:image/png;base64,' in section
    assert f"<td>{world['owner']}</td>" in section
    assert "change detection while tracking:" in r.stdout and "per scan used" in r.stdout
    # detected frame by frame: a used frame waits for the pose after it; the cost per frame
    assert doc["params"]["live"] is True and doc["params"]["lag_frames"] == 1 and "interrupted" not in doc["params"]
    assert 0 < cost["per_frame_cpu_ms"]["p50"] <= cost["per_frame_cpu_ms"]["p99"] <= cost["per_frame_cpu_ms"]["max"]
    assert cost["per_scan_cpu_ms"]["p50"] >= cost["per_frame_cpu_ms"]["p50"]
    assert 0 < cost["blocks_loaded"] <= cost["blocks_in_map"]


def test_track_detect_changes_equals_map_changes_on_its_run(world, tracked, tmp_path):
    """What was detected while tracking is what ``map changes`` finds after the fact in the same
    run folder with the same stride (the same trusted frames, poses and detector)."""
    out = shutil.copytree(tracked[0], tmp_path / "run")
    live = json.loads((out / "changes.json").read_text())
    r = _cli("map", "changes", "--map", world["map"], "--run", out, "--seq", world["session"],
             "--out", tmp_path / "after.json", "--stride", "2")
    assert r.returncode == 0, r.stderr
    after = json.loads((tmp_path / "after.json").read_text())
    for k in ("frames_trusted", "scans_used", "scans_rejected", "totals", "blocks"):
        assert live[k] == after[k], k
    assert live["totals"]["removed_voxels"] > 0


def test_map_changes_run_redraws_the_layer_and_section(world, tracked, tmp_path):
    """``map changes --run`` on a run already drawn into: the layer and the section replaced, not doubled."""
    out = shutil.copytree(tracked[0], tmp_path / "run")
    doc = json.loads((out / "changes.json").read_text())
    clouds, counts = _mcap_changes(out / "run.mcap")
    again = tmp_path / "again.json"
    # the run's metrics.json names the session nclt:sess, not its path: --seq gives it
    r = _cli("map", "changes", "--map", world["map"], "--run", out, "--seq", world["session"], "--out", again,
             "--stride", "3")
    assert r.returncode == 0, r.stderr
    doc2 = json.loads(again.read_text())
    assert doc2["scans_used"] == (doc["frames_trusted"] + 2) // 3 and doc2["scans_used"] != doc["scans_used"]
    clouds2, counts2 = _mcap_changes(out / "run.mcap")
    assert clouds2["/changes/removed"] == _per_block(doc2, "removed_voxels")
    assert clouds2["/changes/added"] == _per_block(doc2, "added_voxels")
    assert {t: n for t, n in counts2.items()} == counts  # one message per /changes/ topic, all others kept
    assert (out / "report.html").read_text().count('<section id="changes">') == 1
    assert "drew the changes into run.mcap" in r.stdout


def test_map_changes_leaves_a_folder_blockloc_did_not_make_alone(world, tracked, tmp_path, capsys):
    """A run folder without blockloc's marker: changes.json is written (asked for), its run.mcap
    and report.html are not rewritten."""
    theirs = shutil.copytree(tracked[0], tmp_path / "theirs")
    (theirs / ".blockloc-output.json").unlink()
    (theirs / "metrics.json").write_text(json.dumps({"sequence": str(world["session"])}))  # no blockloc fields
    (theirs / "changes.json").unlink()
    before = {n: (theirs / n).read_bytes() for n in ("run.mcap", "report.html")}
    from blockloc.commands.lifelong import changes_command  # in this process: the CLI is tested above

    changes_command(str(world["map"]), theirs, None, None, None, 4)
    assert (theirs / "changes.json").is_file() and "drew the changes" not in capsys.readouterr().out
    assert {n: (theirs / n).read_bytes() for n in before} == before


def test_detect_changes_needs_a_block_map(world, tmp_path):
    from blockloc.maps.grid_tiles import tile_global_map

    clean = open_map(world["root"] / "clean")
    pts = np.vstack([clean.load(b)[0][:, :3] for b in clean.ids])
    tile_global_map(pts, None, 20.0, tmp_path / "grid")
    r = _cli("track", "--seq", world["session"], "--map", tmp_path / "grid", "--map-backend", "grid", "--init", "gt",
             "--config", world["config"], "--out", tmp_path / "run", "--detect-changes")
    assert r.returncode == 2 and r.stderr.startswith("error: --map") and "block map" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "run" / "poses.tum").exists()
