"""NCLT layout: constants, byte layouts, round trips through write_session, and bad input."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from blockloc.datasets.base import ImuData, LidarFrame, Sequence
from blockloc.datasets.nclt import (NCLT_GRAVITY_MAP, NCLT_POINT_DTYPE, NCLT_T_BODY_LIDAR, NCLT_T_BODY_SYNC,
                                    HITS_PACKET_US,
                                    NcltSequence, read_groundtruth_csv, read_ms25_csv,
                                    write_groundtruth_csv, write_session)
from blockloc.errors import DatasetError
from blockloc.geometry import T_to_xyzrpy, inv_T

QUANT_M = 0.0025 + 1e-5  # half of NCLT's 5 mm grid, plus float32 rounding (ulp 7.6e-6 at 100 m)


def _write(tmp_path, d, **kw):
    return write_session(tmp_path / "2012-01-22", date="2012-01-22", frames=iter(d["frames"]),
                         imu=d["imu"], ground_truth=d["gt"], **kw)


def test_t_body_lidar_matches_devkit_ssc():
    # devkit x_body_vel: lidar 0.957 m above the body origin (z down), yawed -90.703 deg
    xyzrpy = T_to_xyzrpy(NCLT_T_BODY_LIDAR)
    np.testing.assert_allclose(xyzrpy[:3], [0.002, -0.004, -0.957])
    np.testing.assert_allclose(np.rad2deg(xyzrpy[3:]), [0.807, 0.166, -90.703], atol=1e-9)
    R = NCLT_T_BODY_LIDAR[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # lidar x axis points to body -y (yaw -90 deg): the devkit's Rz Ry Rx convention
    assert R[1, 0] < -0.99
    assert NCLT_GRAVITY_MAP[2] > 9.8


def test_session_round_trip(tmp_path, session_data):
    out = _write(tmp_path, session_data, slam_poses=session_data["slam"])
    assert out == tmp_path / "2012-01-22"
    assert not list(tmp_path.glob("*.tmp-*"))
    seq = NcltSequence(out, min_range_m=0.5, max_range_m=200.0)
    assert isinstance(seq, Sequence)
    frames = session_data["frames"]
    assert len(seq) == len(frames)
    np.testing.assert_allclose(seq.frame_stamps(), [f.stamp for f in frames], atol=1e-6)
    for ref, got in zip(frames, seq.frames()):
        # the writer stores points in time order; the synthetic frames already are
        assert len(got) == len(ref)
        assert got.points.shape == (len(ref), 3)
        assert np.abs(got.points - ref.points).max() <= QUANT_M
        np.testing.assert_array_equal(got.intensity, np.rint(ref.intensity))
        np.testing.assert_array_equal(got.ring, ref.ring)
        err = np.abs(got.time_offsets - ref.time_offsets)
        assert err.max() <= HITS_PACKET_US * 0.5e-6 + 2e-6
        assert got.stamp == pytest.approx(ref.stamp, abs=1e-6)
    imu = seq.imu()
    np.testing.assert_allclose(imu.t, session_data["imu"].t, atol=1e-6)
    np.testing.assert_allclose(imu.acc, session_data["imu"].acc, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(imu.gyro, session_data["imu"].gyro, rtol=1e-7, atol=1e-8)
    gt = seq.ground_truth()
    np.testing.assert_allclose(gt.stamps, session_data["gt"].stamps, atol=1e-6)
    np.testing.assert_allclose(gt.poses, session_data["gt"].poses, atol=1e-8)
    np.testing.assert_allclose(seq.mapping_poses().poses, session_data["slam"].poses, atol=1e-8)
    assert seq.info.imu_rate_hz == pytest.approx(100.0)
    np.testing.assert_allclose(seq.info.T_body_lidar, NCLT_T_BODY_LIDAR)


def test_mapping_poses_fall_back_to_ground_truth(tmp_path, session_data):
    seq = NcltSequence(_write(tmp_path, session_data))
    np.testing.assert_allclose(seq.mapping_poses().poses, session_data["gt"].poses, atol=1e-8)


def test_byte_layout_is_nclt(tmp_path, session_data):
    out = _write(tmp_path, session_data)
    ref = session_data["frames"][0]
    utime = int(round(ref.stamp * 1e6))
    raw = np.fromfile(out / "velodyne_sync" / f"{utime}.bin", dtype=NCLT_POINT_DTYPE)
    # the devkit's decoding: raw * 0.005 - 100
    xyz = np.stack([raw["x"], raw["y"], raw["z"]], 1) * 0.005 - 100.0
    assert np.abs(xyz - ref.points).max() <= QUANT_M
    np.testing.assert_array_equal(raw["laser_id"], ref.ring)
    hits = (out / "velodyne_hits.bin").read_bytes()
    head = np.frombuffer(hits[:24], dtype=[("m", "<u2", 4), ("n", "<u4"), ("t", "<u8"), ("p", "<u4")])[0]
    assert list(head["m"]) == [44444] * 4
    assert 0 < head["n"] < 4000
    assert abs(int(head["t"]) - (utime - 100_000)) < 1000  # first points fire 0.1 s before the stamp
    # all frames' points are in the hits file, each packet 24 + 8 n bytes
    n_points = sum(len(f) for f in session_data["frames"])
    assert (len(hits) - 8 * n_points) % 24 == 0


def test_sessions_are_byte_identical(tmp_path, session_data):
    a = _write(tmp_path / "a", session_data)
    b = _write(tmp_path / "b", session_data)
    for f in sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file()):
        assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_azimuth_fallback_without_hits(tmp_path, session_data, caplog):
    out = _write(tmp_path, session_data, write_hits=False)
    with caplog.at_level(logging.INFO, logger="blockloc.datasets.nclt"):
        seq = NcltSequence(out, max_range_m=200)
    assert "azimuth" in caplog.text
    f = seq.frame(1)
    ref = session_data["frames"][1]
    # sweep starts at the first point; points are ordered by azimuth (z-down convention: increasing)
    assert f.time_offsets[0] == 0.0
    est = f.time_offsets + ref.time_offsets[0]
    assert np.abs(est - ref.time_offsets).max() < 2e-3
    # hits present but disabled behaves the same
    out2 = _write(tmp_path / "h", session_data)
    np.testing.assert_array_equal(NcltSequence(out2, use_hits_times=False, max_range_m=200).frame(1).time_offsets,
                                  f.time_offsets)


def test_hits_matching_when_sync_is_not_a_contiguous_run(tmp_path, session_data):
    out = _write(tmp_path, session_data)
    ref = session_data["frames"][2]
    utime = int(round(ref.stamp * 1e6))
    path = out / "velodyne_sync" / f"{utime}.bin"
    raw = np.fromfile(path, dtype=NCLT_POINT_DTYPE)
    perm = np.random.default_rng(5).permutation(len(raw))[: len(raw) - 100]  # shuffled, subsampled
    raw[perm].tofile(path)
    f = NcltSequence(out, max_range_m=200).frame(2)
    assert len(f) == len(perm)
    err = np.abs(f.time_offsets - ref.time_offsets[perm])
    assert err.max() <= HITS_PACKET_US * 0.5e-6 + 2e-6


def test_range_filter_and_nan_points(tmp_path, session_data, caplog):
    fr = session_data["frames"][0]
    pts = fr.points.copy()
    pts[:3] = [np.nan, 0, 0]
    pts[3] = [np.inf, 1, 1]
    pts[4] = [0.3, 0.0, 0.0]  # inside min range
    session_data["frames"][0] = LidarFrame(0, fr.stamp, pts, fr.intensity, fr.time_offsets, fr.ring)
    with caplog.at_level(logging.WARNING):
        out = _write(tmp_path, session_data)
    assert "dropped 4 non-finite" in caplog.text
    seq = NcltSequence(out, min_range_m=1.0, max_range_m=200)
    f = seq.frame(0)
    assert len(f) == len(pts) - 5
    r = np.linalg.norm(f.points, axis=1)
    assert np.isfinite(f.points).all() and r.min() >= 1.0
    assert len(NcltSequence(out, min_range_m=1.0, max_range_m=30).frame(1).points) < len(session_data["frames"][1])
    assert np.linalg.norm(NcltSequence(out, max_range_m=30).frame(1).points, axis=1).max() <= 30


def test_empty_scan_gives_empty_frame(tmp_path, session_data, caplog):
    fr = session_data["frames"][1]
    session_data["frames"][1] = LidarFrame(1, fr.stamp, np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0, np.uint16))
    out = _write(tmp_path, session_data)
    seq = NcltSequence(out)
    with caplog.at_level(logging.WARNING):
        f = seq.frame(1)
    assert len(f) == 0 and f.points.shape == (0, 3) and "empty scan" in caplog.text
    assert len(seq.frame(2)) > 0


def test_truncated_sync_bin(tmp_path, session_data):
    out = _write(tmp_path, session_data)
    path = sorted((out / "velodyne_sync").iterdir())[1]
    data = path.read_bytes()
    path.write_bytes(data[:-3])
    seq = NcltSequence(out)
    with pytest.raises(DatasetError, match=rf"{path.name}.*{len(data) - 3} bytes.*multiple of 8"):
        seq.frame(1)


def test_truncated_hits_bin(tmp_path, session_data):
    out = _write(tmp_path, session_data)
    hits = out / "velodyne_hits.bin"
    hits.write_bytes(hits.read_bytes()[:-16])
    with pytest.raises(DatasetError, match=r"velodyne_hits.bin: truncated packet at byte \d+: expected \d+ bytes"):
        NcltSequence(out).frame(0)
    hits.write_bytes(hits.read_bytes()[:-3])
    with pytest.raises(DatasetError, match=r"velodyne_hits.bin: \d+ bytes, expected a multiple of 8"):
        NcltSequence(out).frame(0)


def test_bad_hits_magic(tmp_path, session_data):
    out = _write(tmp_path, session_data)
    hits = out / "velodyne_hits.bin"
    b = bytearray(hits.read_bytes())
    b[0] = 0
    hits.write_bytes(bytes(b))
    with pytest.raises(DatasetError, match="bad packet magic at byte 0"):
        NcltSequence(out).frame(0)


def test_missing_files(tmp_path, session_data):
    with pytest.raises(DatasetError, match=r"velodyne_sync: not found; put the NCLT"):
        NcltSequence(tmp_path / "nothing")
    out = _write(tmp_path, session_data)
    (out / "ms25.csv").unlink()


def test_missing_imu_file_means_lidar_only_with_the_remedy_for_its_kind(tmp_path, session_data, caplog):
    """No ms25.csv: an empty IMU (the session tracks LiDAR-only) and one warning naming the file
    and how to get it: a download for NCLT, `blockloc sim` again for a simulated session."""
    import json
    import logging

    out = _write(tmp_path, session_data)
    (out / "ms25.csv").unlink()
    (out / "blockloc_session.json").unlink()  # as NCLT's own downloads: no sidecar
    with caplog.at_level(logging.WARNING, logger="blockloc.datasets.nclt"):
        seq = NcltSequence(out, date="2012-01-22")
        assert len(seq.imu()) == 0 and len(seq.imu()) == 0  # warned once
    warned = [r.getMessage() for r in caplog.records if "ms25.csv" in r.getMessage()]
    assert len(warned) == 1 and "ms25.csv: not found; no IMU, tracking LiDAR-only" in warned[0]
    assert "download 2012-01-22_sen.tar.gz" in warned[0]
    (tmp_path / "sim.json").write_text(json.dumps({"preset": "small", "seed": 3, "sessions": {}}))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="blockloc.datasets.nclt"):
        NcltSequence(out).imu()
    warned = [r.getMessage() for r in caplog.records if "ms25.csv" in r.getMessage()]
    assert len(warned) == 1 and f"re-run `blockloc sim --preset small --seed 3 --out {tmp_path}`" in warned[0]
    assert "download" not in warned[0]
    caplog.clear()  # a run that ignores the IMU (--no-imu): no warning
    with caplog.at_level(logging.INFO, logger="blockloc.datasets.nclt"):
        assert len(NcltSequence(out, want_imu=False).imu()) == 0
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and "ms25.csv" in r.getMessage()]
    assert any("LiDAR-only, as asked" in r.getMessage() for r in caplog.records)


def test_ground_truth_found_beside_session(tmp_path, session_data, caplog):
    out = _write(tmp_path, session_data)
    (out / "groundtruth_2012-01-22.csv").rename(tmp_path / "groundtruth_2012-01-22.csv")
    seq = NcltSequence(out, date="2012-01-22")
    assert len(seq.ground_truth()) == len(session_data["gt"])
    (tmp_path / "groundtruth_2012-01-22.csv").unlink()
    with caplog.at_level(logging.WARNING):
        assert NcltSequence(out, date="2012-01-22").ground_truth() is None
    assert "no groundtruth_2012-01-22.csv" in caplog.text


def test_groundtruth_csv_nan_rows_and_errors(tmp_path, session_data, caplog):
    p = tmp_path / "gt.csv"
    write_groundtruth_csv(p, session_data["gt"])
    lines = p.read_text().splitlines()
    lines.insert(0, "1326030000000000,nan,nan,nan,nan,nan,nan")  # NCLT's first rows look like this
    lines[5] = lines[5].split(",")[0] + ",1,2,NaN,0,0,0"
    p.write_text("\n".join(lines) + "\n")
    with caplog.at_level(logging.WARNING):
        traj = read_groundtruth_csv(p)
    assert "dropped 2 of" in caplog.text
    assert len(traj) == len(session_data["gt"]) - 1  # one real row became NaN
    assert np.isfinite(traj.poses).all()
    lines[7] = "1326030000070000,1,2,3"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"gt.csv:8: 4 columns, expected 7"):
        read_groundtruth_csv(p)
    with pytest.raises(DatasetError, match="not found"):
        read_groundtruth_csv(tmp_path / "missing.csv")


def test_groundtruth_csv_round_trip_is_exact(tmp_path, session_data):
    p = tmp_path / "gt.csv"
    write_groundtruth_csv(p, session_data["gt"])
    traj = read_groundtruth_csv(p)
    np.testing.assert_allclose(traj.stamps, session_data["gt"].stamps, atol=5e-7)
    err = inv_T(traj.poses) @ session_data["gt"].poses
    np.testing.assert_allclose(err, np.broadcast_to(np.eye(4), err.shape), atol=1e-8)


def test_ms25_unsorted_duplicate_nan_and_short_rows(tmp_path, caplog):
    p = tmp_path / "ms25.csv"
    rows = [f"{1000000 + 10000 * i},0,0,0,{i},0,-9.8,0,0,{i * 0.1}" for i in range(10)]
    rows[3], rows[4] = rows[4], rows[3]          # out of order
    rows.append(rows[6])                          # duplicate stamp
    rows.append("1200000,0,0,0,nan,0,-9.8,0,0,0")  # NaN
    p.write_text("\n".join(rows) + "\n")
    with caplog.at_level(logging.WARNING):
        imu = read_ms25_csv(p)
    assert "1 IMU rows holding NaN" in caplog.text
    assert "out of time order; sorted" in caplog.text
    assert "1 IMU rows with a duplicate stamp" in caplog.text
    assert len(imu) == 10 and np.all(np.diff(imu.t) > 0)
    np.testing.assert_allclose(imu.acc[:, 0], np.arange(10))
    np.testing.assert_allclose(imu.gyro[:, 2], np.arange(10) * 0.1)
    rows[2] = "1020000,0,0,0,1,2"
    p.write_text("\n".join(rows[:10]) + "\n")
    with pytest.raises(DatasetError, match=r"ms25.csv:3: 6 columns, expected 10"):
        read_ms25_csv(p)


def test_write_session_is_atomic_on_failure(tmp_path, session_data):
    def frames():
        yield session_data["frames"][0]
        raise RuntimeError("simulator crashed")

    with pytest.raises(RuntimeError):
        write_session(tmp_path / "s", date="d", frames=frames(), imu=session_data["imu"],
                      ground_truth=session_data["gt"])
    assert list(tmp_path.iterdir()) == []


def test_write_session_replaces_and_rejects_unordered_frames(tmp_path, session_data):
    out = _write(tmp_path, session_data)
    (out / "stale.txt").write_text("x")  # a file blockloc did not write: the session is not replaced
    from blockloc.errors import BlocklocError

    with pytest.raises(BlocklocError, match=r"holds files blockloc did not write \(stale.txt\)"):
        _write(tmp_path, session_data)
    assert (out / "stale.txt").read_text() == "x"
    (out / "stale.txt").unlink()
    _write(tmp_path, session_data)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["2012-01-22"]
    fr = session_data["frames"]
    with pytest.raises(DatasetError, match="is not after"):
        write_session(tmp_path / "x", date="d", frames=[fr[1], fr[0]], imu=session_data["imu"],
                      ground_truth=session_data["gt"])


def test_sidecar_extrinsics(tmp_path, session_data):
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, -1.0]
    out = _write(tmp_path, session_data, T_body_lidar=T, gravity_map=(0, 0, -9.81))
    seq = NcltSequence(out)
    np.testing.assert_allclose(seq.info.T_body_lidar, T)
    np.testing.assert_allclose(seq.info.gravity_map, [0, 0, -9.81])
    np.testing.assert_allclose(seq.info.T_body_imu, np.eye(4))
    (out / "blockloc_session.json").write_text("{bad json")
    with pytest.raises(DatasetError, match="blockloc_session.json: malformed"):
        NcltSequence(out)


def test_frame_index_errors_and_imu_type(tmp_path, session_data):
    seq = NcltSequence(_write(tmp_path, session_data))
    with pytest.raises(IndexError):
        seq.frame(len(seq))
    assert seq.frame(-1).index == len(seq) - 1
    assert isinstance(seq.imu(), ImuData)
    assert [f.index for f in seq.frames(1, 3)] == [1, 2]


def test_empty_hits_file_falls_back_to_azimuth(tmp_path, session_data):
    out = _write(tmp_path, session_data)
    (out / "velodyne_hits.bin").write_bytes(b"")
    f = NcltSequence(out, max_range_m=200).frame(0)
    assert len(f) == len(session_data["frames"][0]) and f.time_offsets[0] == 0.0


def test_real_hdl32e_scan_round_trip(tmp_path, shared_data, session_data):
    """A real HDL-32E sweep through the NCLT byte layout keeps every point within 5 mm quantization."""
    from pypcd4 import PointCloud

    arr = PointCloud.from_path(shared_data / "hdl32e_pair" / "target.pcd").numpy(("x", "y", "z", "intensity"))
    arr = arr[np.isfinite(arr).all(axis=1)]
    n = len(arr)
    assert n > 60000
    frame = LidarFrame(0, 1326030000.1, arr[:, :3], np.clip(arr[:, 3], 0, 255), None, None)
    out = write_session(tmp_path / "real", date="real", frames=[frame], imu=session_data["imu"],
                        ground_truth=session_data["gt"])
    got = NcltSequence(out, min_range_m=0.0, max_range_m=300.0).frame(0)
    assert len(got) == n
    assert np.abs(got.points - arr[:, :3]).max() <= QUANT_M
    np.testing.assert_array_equal(got.intensity, np.rint(np.clip(arr[:, 3], 0, 255)))
    np.testing.assert_array_equal(got.time_offsets, np.zeros(n, np.float32))


def test_official_velodyne_sync_is_body_frame(tmp_path, session_data):
    # Official velodyne_sync scans are in the body frame (devkit project_vel_to_cam.py projects
    # them with T_c_body alone): a session without blockloc_session.json (the official layout)
    # must not apply x_body_vel's -90.7 deg yaw / 0.957 m lift to them.
    out = _write(tmp_path, session_data)
    (out / "blockloc_session.json").unlink()
    seq = NcltSequence(out)
    np.testing.assert_allclose(seq.info.T_body_lidar, NCLT_T_BODY_SYNC)
    np.testing.assert_allclose(seq.info.T_body_lidar, np.eye(4))
    np.testing.assert_allclose(seq.info.gravity_map, NCLT_GRAVITY_MAP)


def test_written_sessions_record_velodyne_frame(tmp_path, session_data):
    # write_session stores velodyne-frame points, so it always records NCLT_T_BODY_LIDAR
    out = _write(tmp_path, session_data)
    assert (out / "blockloc_session.json").is_file()
    np.testing.assert_allclose(NcltSequence(out).info.T_body_lidar, NCLT_T_BODY_LIDAR)


def test_official_session_ignores_hits_and_reports_its_scan_rate(tmp_path, session_data, caplog):
    # official hits are velodyne-frame, sync scans body-frame: the hits file is not indexed
    out = _write(tmp_path, session_data)
    (out / "blockloc_session.json").unlink()
    with caplog.at_level("INFO"):
        seq = NcltSequence(out)
        frame = seq.frame(0)
    assert seq._hits_path is None and seq._hits is None
    assert "per-point times come from the azimuth" in caplog.text
    assert frame.time_offsets.min() >= 0 and frame.time_offsets.max() < 0.1
    stamps = seq.frame_stamps()
    assert seq.info.lidar_rate_hz == pytest.approx(1.0 / np.median(np.diff(stamps)), rel=1e-6)


def _rss_file_kb() -> int:
    """This process's file-backed resident memory (Linux, the platform blockloc runs on)."""
    lines = [line for line in open("/proc/self/status") if line.startswith("RssFile:")]
    assert lines, "/proc/self/status has no RssFile line"
    return int(lines[0].split()[1])


def test_hits_index_does_not_keep_the_file_mapped(tmp_path):
    """Indexing walks every packet header, reading every page of the file; those pages must not
    stay in the process's RSS (a long NCLT session's hits file is tens of GB)."""
    import os

    from blockloc.datasets.nclt import HitsIndex, _hits_packets

    rng = np.random.default_rng(3)
    n = 8_000_000  # 64 MB of hits
    t_us = np.sort(rng.integers(0, 60_000_000, n))
    words = rng.integers(0, 2**63, n, dtype=np.int64).astype("<u8")
    path = tmp_path / "velodyne_hits.bin"
    path.write_bytes(_hits_packets(words, t_us))
    size_kb = os.path.getsize(path) // 1024
    before = _rss_file_kb()
    index = HitsIndex(path)
    assert _rss_file_kb() - before < size_kb // 8
    got, got_t = index.window(10_000_000, 40_000_000)  # half the file, read and copied
    keep = (t_us >= 10_000_000 - HITS_PACKET_US) & (t_us <= 40_000_000 + HITS_PACKET_US)
    known = np.sort(words)
    at = np.minimum(np.searchsorted(known, got[:1000]), n - 1)
    assert len(got) >= keep.sum() * 0.99 and np.array_equal(known[at], got[:1000])  # words of the file
    assert np.all(np.diff(got_t) >= 0)
    index.window(50_000_000, 50_200_000)  # the next window: the one before is handed back
    assert _rss_file_kb() - before < size_kb // 8

    # while walking: each chunk's pages are handed back before the next chunk is read
    from blockloc.datasets._nclt_kernels import index_hits_words

    seen = []

    def kernel(words):
        seen.append(_rss_file_kb() - before)
        return index_hits_words(words)

    index._walk(kernel, chunk_words=n // 16)
    assert len(seen) >= 16 and max(seen) < size_kb // 8


@pytest.mark.parametrize("cut", [None, "truncated", "magic"])
def test_hits_index_walks_in_chunks_as_in_one_piece(tmp_path, cut):
    from blockloc.datasets._nclt_kernels import index_hits_words
    from blockloc.datasets.nclt import HitsIndex, _hits_packets

    rng = np.random.default_rng(4)
    n = 20_000
    t_us = np.sort(rng.integers(0, 2_000_000, n))
    data = bytearray(_hits_packets(rng.integers(0, 2**63, n, dtype=np.int64).astype("<u8"), t_us))
    if cut == "truncated":
        data = data[:-16]
    elif cut == "magic":
        whole = np.frombuffer(bytes(data), "<u8")
        offs = index_hits_words(whole)[0]
        data[int(offs[len(offs) * 2 // 3]) * 8] = 0
    path = tmp_path / "velodyne_hits.bin"
    path.write_bytes(bytes(data))
    whole = index_hits_words(np.frombuffer(bytes(data), "<u8"))
    try:
        index = HitsIndex(path)
    except DatasetError:
        assert cut is not None
        index = HitsIndex.__new__(HitsIndex)  # the walk alone, on the same map
        import mmap as _mmap

        with open(path, "rb") as fh:
            index._map = _mmap.mmap(fh.fileno(), 0, access=_mmap.ACCESS_READ)
        index.words = np.frombuffer(index._map, "<u8")
    else:
        assert cut is None
    for chunk in (7, 300, 1001, 1 << 20):  # 7: shorter than a packet, the chunk widens
        got = index._walk(index_hits_words, chunk)
        for a, b in zip(got[:3], whole[:3]):
            np.testing.assert_array_equal(a, b)
        assert got[3:] == tuple(int(v) for v in whole[3:]), chunk
