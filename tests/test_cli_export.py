"""`blockloc export dynamicmap` from the command line, as a user types it."""

import subprocess

import numpy as np
import pytest

from blockloc.datasets.dynamicmap import read_gt_cloud, read_scan, scan_paths

SEQ = "sim:tiny/map_m12@3"


def run(*args):
    return subprocess.run(["blockloc", *args], capture_output=True, text=True)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("dm") / "m12"
    r = run("export", "dynamicmap", "--seq", SEQ, "--out", str(out), "--start", "5", "--frames", "2")
    assert r.returncode == 0, r.stderr
    return out, r.stdout


def test_scans_in_world_frame_with_viewpoint_and_labels(exported):
    from blockloc.app.catalog import open_sequence
    from blockloc.maps.mapping import scan_to_map
    from blockloc.sim.changes import LABEL_MOVING

    out, stdout = exported
    paths = scan_paths(out)
    assert [p.name for p in paths] == ["000000.pcd", "000001.pcd"]
    seq = open_sequence(SEQ)
    gt = seq.ground_truth()
    T_bl = np.asarray(seq.info.T_body_lidar)
    total = dynamic = 0
    for k, path in zip((5, 6), paths):
        pts, T_world_lidar, inten = read_scan(path)
        frame, lab = seq.frame_labels(k)
        T_expected = gt.interpolate(np.array([frame.stamp]))[0] @ T_bl
        assert np.allclose(T_world_lidar, T_expected, atol=1e-5)  # VIEWPOINT = the sensor pose
        r = np.linalg.norm(frame.points, axis=1)
        keep = (r >= 2.5) & (r <= 50.0)  # the command's default ranges
        want = scan_to_map(frame.points[keep], frame.time_offsets[keep], frame.stamp, gt, T_bl)
        assert len(pts) == keep.sum() and np.allclose(pts, want, atol=1e-3)  # deskewed, world frame
        assert np.array_equal(inten > 0.5, lab[keep] == LABEL_MOVING)
        total += len(pts)
        dynamic += int((lab[keep] == LABEL_MOVING).sum())
    g, d = read_gt_cloud(out)
    assert len(g) == total and int(d.sum()) == dynamic
    assert f"gt_cloud.pcd: {total} points, {dynamic} dynamic" in stdout


def test_mapping_day_has_no_labels(tmp_path):
    r = run("export", "dynamicmap", "--seq", "sim:tiny/map@3", "--out", str(tmp_path / "m"), "--frames", "1")
    assert r.returncode == 0, r.stderr
    assert "no labels" in r.stdout and not (tmp_path / "m" / "gt_cloud.pcd").exists()
    assert len(scan_paths(tmp_path / "m")) == 1


def test_errors_are_one_line_and_touch_nothing(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    r = run("export", "dynamicmap", "--seq", SEQ, "--out", str(mine), "--frames", "1")
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr
    assert (mine / "notes.txt").read_text() == "keep me"
    r = run("export", "dynamicmap", "--seq", SEQ, "--out", str(tmp_path / "x"), "--min-range", "60")
    assert r.returncode == 2 and "error: --min-range" in r.stderr and not (tmp_path / "x").exists()
    r = run("export", "dynamicmap", "--seq", SEQ, "--out", str(tmp_path / "x"), "--start", "100000")
    assert r.returncode == 2 and "error: --start 100000" in r.stderr and not (tmp_path / "x").exists()


def test_labels_of_a_written_session(tmp_path):
    """A session `blockloc sim --months` wrote: labels from its point_labels/, one per point of the scan file."""
    from blockloc.app.dynamicmap import export_dynamicmap
    from blockloc.datasets.nclt import NCLT_POINT_DTYPE, decode_points
    from blockloc.sim.changes import LABEL_MOVING, read_point_labels
    from blockloc.sim.writer import generate_dataset

    d = generate_dataset("tiny", 3, tmp_path / "d", sessions=("map",), max_frames=2, months=(12,),
                         workers=0, azimuth_steps=64)
    s = export_dynamicmap(str(d / "map_m12"), tmp_path / "out", min_range_m=2.5, max_range_m=50.0)
    assert s.labelled and s.scans == 2
    want = total = 0
    for path in sorted((d / "map_m12" / "velodyne_sync").glob("*.bin")):
        xyz, _, _ = decode_points(np.fromfile(path, dtype=NCLT_POINT_DTYPE))
        r = np.linalg.norm(xyz, axis=1)
        keep = (r >= 2.5) & (r <= 50.0)
        lab = read_point_labels(d / "map_m12", int(path.stem))
        want += int((lab[keep] == LABEL_MOVING).sum())
        total += int(keep.sum())
        assert len(lab) == len(xyz)
    g, dyn = read_gt_cloud(tmp_path / "out")
    assert int(dyn.sum()) == want == s.dynamic_points and len(g) == s.points == total
