"""TUM / KITTI / NCLT trajectory files: round trips, sniffing, bad input."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from blockloc.errors import BlocklocError, DatasetError
from blockloc.trajectory_io import (kitti_times_path, read_kitti, read_kitti_file, read_trajectory,
                                               read_trajectory_file, read_tum, sniff_format, write_kitti,
                                               write_trajectory, write_tum)
from blockloc.geometry import Trajectory, xyzrpy_to_T

from eval_trajgen import random_trajectory


def test_tum_round_trip(tmp_path, rng):
    traj = random_trajectory(rng, n=250, t0=1326044400.123456)
    path = write_tum(tmp_path / "a.tum", traj)
    back = read_tum(path)
    np.testing.assert_allclose(back.stamps, traj.stamps, atol=1e-6, rtol=0)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-9, rtol=0)
    assert [p.name for p in tmp_path.iterdir()] == ["a.tum"]  # no temp file left behind
    # overwriting replaces the whole file
    write_tum(path, Trajectory(traj.stamps[:3], traj.poses[:3]))
    assert len(read_tum(path)) == 3


def test_tum_reader_accepts_comments_commas_and_repairs_order(tmp_path, caplog):
    text = ("# timestamp x y z qx qy qz qw\n\n"
            "2.0 1 2 3 0 0 0 1\n"
            "1.0, 0, 0, 0, 0, 0, 0.7071067811865476, 0.7071067811865476\n"
            "2.0 9 9 9 0 0 0 1\n"  # duplicate stamp: dropped, first kept
            "3.0 0 0 0 0 0 0 2\n")  # not unit: normalized
    path = tmp_path / "b.txt"
    path.write_text(text)
    with caplog.at_level(logging.WARNING):
        traj = read_trajectory(path)
    np.testing.assert_array_equal(traj.stamps, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(traj.poses[0, :3, :3], xyzrpy_to_T(0, 0, 0, 0, 0, np.pi / 2)[:3, :3], atol=1e-12)
    np.testing.assert_array_equal(traj.positions[1], [1, 2, 3])
    np.testing.assert_allclose(traj.poses[2, :3, :3], np.eye(3))
    assert "out of order" in caplog.text and "duplicated stamp" in caplog.text and "normalized" in caplog.text


def test_kitti_round_trip_with_times_file(tmp_path, rng):
    traj = random_trajectory(rng, n=120, t0=50.0)
    path = write_kitti(tmp_path / "poses.kitti", traj)
    assert kitti_times_path(path) == tmp_path / "poses.times.txt"
    loaded = read_kitti_file(path)
    assert loaded.timed and loaded.fmt == "kitti"
    np.testing.assert_allclose(loaded.trajectory.stamps, traj.stamps, atol=1e-9)
    np.testing.assert_allclose(loaded.trajectory.poses, traj.poses, atol=1e-8)
    rows = path.read_text().splitlines()
    assert len(rows) == 120 and all(len(r.split()) == 12 for r in rows)


def test_kitti_times_txt_and_untimed(tmp_path, rng):
    traj = random_trajectory(rng, n=20)
    path = write_kitti(tmp_path / "00.txt", traj, write_times=False)
    untimed = read_kitti_file(path)
    assert not untimed.timed
    np.testing.assert_array_equal(untimed.trajectory.stamps, np.arange(20.0))
    (tmp_path / "times.txt").write_text("".join(f"{t:e}\n" for t in traj.stamps))  # KITTI's own layout
    timed = read_kitti_file(path)
    assert timed.timed
    np.testing.assert_allclose(timed.trajectory.stamps, traj.stamps, rtol=1e-6)
    (tmp_path / "times.txt").write_text("1.0\n2.0\n")
    with pytest.raises(DatasetError, match=r"times.txt: 2 stamps, expected one per pose .* \(20\)"):
        read_kitti(path)


def test_write_trajectory_picks_format_from_extension(tmp_path, rng):
    traj = random_trajectory(rng, n=10)
    write_trajectory(tmp_path / "p.kitti", traj)
    write_trajectory(tmp_path / "p.tum", traj)
    assert sniff_format(tmp_path / "p.kitti") == "kitti" and sniff_format(tmp_path / "p.tum") == "tum"
    for name in ("p.kitti", "p.tum"):
        np.testing.assert_allclose(read_trajectory(tmp_path / name).poses, traj.poses, atol=1e-8)


def write_nclt_csv(path, rows, header=False, nan_rows=0):
    lines = ["utime,x,y,z,roll,pitch,yaw"] if header else []
    lines += ["%d,nan,nan,nan,nan,nan,nan" % (1326044400000000 + k) for k in range(nan_rows)]
    lines += [",".join(["%d" % r[0]] + ["%.9f" % v for v in r[1:]]) for r in rows]
    path.write_text("\n".join(lines) + "\n")


def test_nclt_groundtruth_csv_with_nan_rows(tmp_path, rng, caplog):
    n = 50
    utime = 1326044400500000 + np.arange(n) * 100000
    xyzrpy = np.column_stack([rng.normal(0, 10, (n, 3)), rng.uniform(-0.2, 0.2, (n, 2)), rng.uniform(-3, 3, n)])
    rows = np.column_stack([utime, xyzrpy])
    path = tmp_path / "groundtruth_2012-01-08.csv"
    write_nclt_csv(path, rows, nan_rows=3)
    assert sniff_format(path) == "nclt"
    with caplog.at_level(logging.WARNING):
        loaded = read_trajectory_file(path)
    assert loaded.fmt == "nclt" and len(loaded.trajectory) == n
    assert "NaN" in caplog.text
    np.testing.assert_allclose(loaded.trajectory.stamps, utime * 1e-6)
    np.testing.assert_allclose(loaded.trajectory.poses, xyzrpy_to_T(*xyzrpy.T), atol=1e-8)
    # a csv of only NaN rows is an error, not an empty trajectory
    write_nclt_csv(path, rows[:0], nan_rows=4)
    with pytest.raises(DatasetError, match="groundtruth_2012-01-08.csv"):
        read_trajectory(path)


@pytest.mark.parametrize("text, match", [
    ("1 2 3 4 5 6 7\n", r":1: 7 columns, expected a trajectory file"),
    ("# only a comment\n\n", r"no poses"),
    ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n", r":2: expected 8 numbers \(t x y z qx qy qz qw\), got 7"),
    ("0 0 0 0 0 0 0 1\n1 0 0 x 0 0 0 1\n", r":2: expected 8 numbers .*got '1 0 0 x"),
    ("0 0 0 0 0 0 0 1\n\n1 0 nan 0 0 0 0 1\n", r":3: non-finite value"),
    ("0 0 0 0 0 0 0 0\n", r":1: zero quaternion"),
    (" ".join(["2"] * 12) + "\n", r":1: rotation block has determinant"),
])
def test_bad_files_raise_one_line_naming_file_and_line(tmp_path, text, match):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=match) as info:
        read_trajectory(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and "\n" not in msg


def test_missing_directory_and_binary_files(tmp_path):
    with pytest.raises(DatasetError, match="no such trajectory file"):
        read_trajectory(tmp_path / "nope.tum")
    with pytest.raises(DatasetError, match="is a directory"):
        read_trajectory(tmp_path)
    (tmp_path / "bin.txt").write_bytes(bytes(range(256)))
    with pytest.raises(BlocklocError, match="bin.txt"):
        read_trajectory(tmp_path / "bin.txt")
