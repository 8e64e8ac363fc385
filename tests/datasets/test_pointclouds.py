"""Point-cloud readers: PCD (ascii/binary/binary_compressed), KITTI .bin and PLY round trips,
per-point time rules, bad input, and the real opencalib fixture."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from blockloc.datasets.pointclouds import (cloud_time_range, decode_point_times, read_fields,
                                           read_point_cloud, write_point_cloud)
from blockloc.errors import DatasetError

N = 500
T0 = 1_700_000_000.25  # a UNIX epoch stamp (s)


def _cloud(seed: int = 0, n: int = N):
    rng = np.random.default_rng(seed)
    # on a 0.25 m grid and integer intensities: compressible, so binary_compressed stays
    # compressed (pypcd4 falls back to binary for data LZF cannot shrink)
    pts = (np.round(rng.uniform(-40, 40, (n, 3)) * 4) / 4).astype(np.float32)
    inten = np.round(rng.uniform(0, 255, n)).astype(np.float32)
    ring = rng.integers(0, 64, n).astype(np.uint16)
    offs = np.sort(rng.uniform(0.0, 0.1, n))  # seconds into the sweep
    return pts, inten, ring, offs


# the per-point time fields real drivers write, and the offsets (s) we expect back
TIME_FIELDS = {
    "velodyne time f32 rel s": ("time", lambda o: (o - 0.05).astype(np.float32), lambda o: o - 0.05),
    "ouster t u32 rel ns": ("t", lambda o: np.round(o * 1e9).astype(np.uint32), lambda o: o),
    "livox offset_time u32 ns": ("offset_time", lambda o: np.round(o * 1e9).astype(np.uint32),
                                 lambda o: o),
    "hesai timestamp f64 abs s": ("timestamp", lambda o: T0 + o, lambda o: o),
    "timestamp i64 abs ns": ("timestamp", lambda o: np.int64(T0 * 1e9) + np.round(o * 1e9).astype(np.int64),
                             lambda o: o),
    "time_ms suffix": ("time_ms", lambda o: (o * 1e3).astype(np.float32), lambda o: o),
}


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
@pytest.mark.parametrize("kind", [None, *TIME_FIELDS])
def test_pcd_round_trip(tmp_path, encoding, kind):
    pts, inten, ring, offs = _cloud()
    extra = {}
    if kind is not None:
        name, enc, _ = TIME_FIELDS[kind]
        extra[name] = enc(offs)
    path = write_point_cloud(tmp_path / "scan.pcd", pts, intensity=inten, ring=ring, extra=extra,
                             encoding=encoding)
    assert f"DATA {encoding}".encode() in path.read_bytes()[:400]
    c = read_point_cloud(path)
    assert len(c) == N and c.num_dropped == 0
    np.testing.assert_allclose(c.points, pts, atol=1e-6)
    np.testing.assert_allclose(c.intensity, inten, atol=1e-4)
    np.testing.assert_array_equal(c.ring, ring)
    if kind is None:
        assert c.time_offsets is None and c.stamp is None and c.time_field is None
        return
    name, _, expected = TIME_FIELDS[kind]
    assert c.time_field == name
    absolute = "abs" in kind
    if absolute:  # no stamp given: relative to the earliest point, which becomes the stamp
        assert c.stamp == pytest.approx(T0 + offs.min(), abs=1e-6)
        np.testing.assert_allclose(c.time_offsets, offs - offs.min(), atol=2e-6)
    else:
        assert c.stamp is None
        np.testing.assert_allclose(c.time_offsets, expected(offs), atol=2e-6)


def test_absolute_times_relative_to_given_stamp(tmp_path):
    pts, _, _, offs = _cloud()
    path = write_point_cloud(tmp_path / "a.pcd", pts, extra={"timestamp": T0 + offs},
                             encoding="binary_compressed")
    c = read_point_cloud(path, stamp=T0 + 0.1)  # stamped at the sweep end
    assert c.stamp == T0 + 0.1
    np.testing.assert_allclose(c.time_offsets, offs - 0.1, atol=2e-6)
    assert cloud_time_range(path) == pytest.approx((T0 + offs.min(), T0 + offs.max()), abs=1e-6)
    rel = write_point_cloud(tmp_path / "r.pcd", pts, extra={"time": offs.astype(np.float32)})
    assert cloud_time_range(rel) is None  # relative offsets carry no stamp


def test_pcd_written_by_hand_ascii_with_count_and_padding(tmp_path):
    """A hand-written ascii PCD (independent of the writer): a COUNT 3 field, an unused '_' field,
    upper-case names, NaN padding rows."""
    rows = ["1.5 2.5 -3.0 7 0 0 0 9 4 0.01", "nan nan nan 0 0 0 0 0 0 0",
            "-4 5 6 1 2 3 0 10 5 0.02"]
    header = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z normal _ Intensity ring time\n"
              "SIZE 4 4 4 4 4 4 2 4\nTYPE F F F F F F U F\nCOUNT 1 1 1 3 1 1 1 1\n"
              "WIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n")
    path = tmp_path / "hand.pcd"
    path.write_text(header + "\n".join(rows) + "\n")
    c = read_point_cloud(path)
    assert c.num_dropped == 1
    np.testing.assert_allclose(c.points, [[1.5, 2.5, -3.0], [-4, 5, 6]])
    np.testing.assert_allclose(c.intensity, [9, 10])
    np.testing.assert_array_equal(c.ring, [4, 5])
    np.testing.assert_allclose(c.time_offsets, [0.01, 0.02], atol=1e-7)
    assert "normal__0002" in read_fields(path).dtype.names


def test_store_encoder_output_reads(tmp_path):
    from blockloc.maps.pcd import encode_pcd

    pts, inten, _, _ = _cloud(1)
    (tmp_path / "m.pcd").write_bytes(encode_pcd(pts, inten))
    c = read_point_cloud(tmp_path / "m.pcd")
    np.testing.assert_array_equal(c.points, pts)
    np.testing.assert_array_equal(c.intensity, inten)
    assert c.ring is None and c.time_offsets is None


def test_float64_coordinates_kept(tmp_path):
    pts = np.array([[500_000.123456, 4_000_000.654321, 12.5]] * 3)  # UTM-like
    c = read_point_cloud(write_point_cloud(tmp_path / "utm.pcd", pts))
    assert c.points.dtype == np.float64
    np.testing.assert_array_equal(c.points, pts)


def test_kitti_bin_round_trip(tmp_path):
    pts, inten, _, _ = _cloud(2)
    raw = np.column_stack([pts, inten]).astype("<f4")
    raw.tofile(tmp_path / "000000.bin")  # as KITTI ships them
    c = read_point_cloud(tmp_path / "000000.bin")
    np.testing.assert_array_equal(c.points, pts)
    np.testing.assert_array_equal(c.intensity, inten)
    assert c.ring is None and c.time_offsets is None
    back = read_point_cloud(write_point_cloud(tmp_path / "w.bin", pts, intensity=inten))
    np.testing.assert_array_equal(back.points, pts)
    with pytest.raises(DatasetError, match="x y z intensity only"):
        write_point_cloud(tmp_path / "x.bin", pts, ring=np.zeros(N, np.uint16))


@pytest.mark.parametrize("text", [True, False])
def test_ply_cloudcompare_style(tmp_path, text):
    """A PLY written by plyfile directly, with CloudCompare's scalar_ names and a double time."""
    from plyfile import PlyData, PlyElement

    pts, inten, ring, offs = _cloud(3)
    rec = np.empty(N, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("scalar_Intensity", "f4"),
                       ("scalar_Ring", "u2"), ("scalar_Timestamp", "f8")])
    rec["x"], rec["y"], rec["z"] = pts.T
    rec["scalar_Intensity"], rec["scalar_Ring"], rec["scalar_Timestamp"] = inten, ring, T0 + offs
    PlyData([PlyElement.describe(rec, "vertex")], text=text).write(str(tmp_path / "cc.ply"))
    c = read_point_cloud(tmp_path / "cc.ply", stamp=T0)
    np.testing.assert_allclose(c.points, pts, atol=1e-5)
    np.testing.assert_allclose(c.intensity, inten, atol=1e-3)
    np.testing.assert_array_equal(c.ring, ring)
    np.testing.assert_allclose(c.time_offsets, offs, atol=2e-6)


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_ply_round_trip(tmp_path, encoding):
    pts, inten, ring, offs = _cloud(4)
    path = write_point_cloud(tmp_path / "s.ply", pts, intensity=inten, ring=ring,
                             extra={"t": np.round(offs * 1e9).astype(np.uint32)}, encoding=encoding)
    c = read_point_cloud(path)
    np.testing.assert_allclose(c.points, pts, atol=1e-5)
    np.testing.assert_array_equal(c.ring, ring)
    np.testing.assert_allclose(c.time_offsets, offs, atol=2e-6)


def test_non_finite_points_dropped_and_counted(tmp_path, caplog):
    pts, inten, ring, offs = _cloud(5)
    pts[[3, 10, 11]] = np.nan
    pts[20, 1] = np.inf
    path = write_point_cloud(tmp_path / "nan.pcd", pts, intensity=inten, ring=ring,
                             extra={"time": offs.astype(np.float32)})
    with caplog.at_level(logging.INFO, logger="blockloc.datasets.pointclouds"):
        c = read_point_cloud(path)
    assert c.num_dropped == 4 and len(c) == N - 4
    assert "dropped 4 of 500 points" in caplog.text
    keep = np.setdiff1d(np.arange(N), [3, 10, 11, 20])
    np.testing.assert_array_equal(c.ring, ring[keep])
    np.testing.assert_allclose(c.time_offsets, offs[keep], atol=1e-7)


def test_range_filter(tmp_path):
    pts = np.array([[0.0, 0, 0], [0.5, 0, 0], [3, 4, 0], [100, 0, 0]], np.float32)
    c = read_point_cloud(write_point_cloud(tmp_path / "r.pcd", pts, intensity=np.arange(4.0)),
                         min_range_m=1.0, max_range_m=50.0)
    np.testing.assert_array_equal(c.points, [[3, 4, 0]])
    np.testing.assert_array_equal(c.intensity, [2.0])
    assert c.num_dropped == 0


# ----------------------------------------------------------------------------- time rules


def test_time_rules():
    o = np.linspace(0.0, 0.1, 11)
    cases = [
        (o.astype(np.float32), (0.0, False)),                       # Velodyne: rel s
        ((o - 0.1).astype(np.float32), (0.0, False)),               # stamp at sweep end
        (np.round(o * 1e9).astype(np.uint32), (0.0, False)),        # Ouster/Livox: rel ns
        (np.round(o * 1e6).astype(np.int32), (0.0, False)),         # rel us
        (T0 + o, (T0, True)),                                        # abs s float64
        (np.int64(T0 * 1e3) + np.round(o * 1e3).astype(np.int64), (T0, True)),  # abs ms
        (np.int64(T0 * 1e6) + np.round(o * 1e6).astype(np.int64), (T0, True)),  # abs us
        (np.int64(T0 * 1e9) + np.round(o * 1e9).astype(np.int64), (T0, True)),  # abs ns
    ]
    for values, (base, absolute) in cases:
        got_base, rel, got_abs = decode_point_times(values)
        assert got_abs is absolute, values.dtype
        assert got_base == pytest.approx(base, abs=1e-6)
        start = o - 0.1 if values.dtype == np.float32 and values.min() < 0 else o
        np.testing.assert_allclose(rel, start, atol=1e-6)
    # the unit suffix overrides the inference: 0..100 ms would otherwise be read as ms anyway;
    # 0..0.1 labelled _ms is 0.1 ms
    np.testing.assert_allclose(decode_point_times(o, unit_s=1e-3)[1], o * 1e-3)
    # all points at one absolute instant (keyframes exported without per-point times)
    assert decode_point_times(np.full(5, T0))[2] is True


def test_float32_absolute_times_ignored(tmp_path, caplog):
    pts, _, _, offs = _cloud(6)
    path = write_point_cloud(tmp_path / "f32.pcd", pts,
                             extra={"timestamp": (T0 + offs).astype(np.float32)})
    with caplog.at_level(logging.WARNING):
        c = read_point_cloud(path)
    assert c.time_offsets is None and "float32" in caplog.text


# ----------------------------------------------------------------------------- bad input


def _truncate(path, keep_fraction=0.6):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep_fraction)])
    return path


@pytest.mark.parametrize("suffix,encoding,match", [
    (".pcd", "binary", "truncated binary PCD.*expected 8000 for 500 points"),
    (".pcd", "binary_compressed", "truncated binary_compressed PCD"),
    (".pcd", "ascii", "(truncated|corrupt) ascii PCD.*500 points"),
    (".ply", "binary", "PLY"),
    (".ply", "ascii", "PLY"),
    (".bin", "binary", "multiple of 16"),
])
def test_truncated_files_name_path_and_expectation(tmp_path, suffix, encoding, match):
    pts, inten, _, _ = _cloud(7)
    path = write_point_cloud(tmp_path / f"cut{suffix}", pts, intensity=inten, encoding=encoding)
    if suffix == ".bin":
        path.write_bytes(path.read_bytes()[:-3])
    else:
        _truncate(path)
    with pytest.raises(DatasetError, match=match) as err:
        read_point_cloud(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_unreadable_files(tmp_path):
    (tmp_path / "junk.pcd").write_bytes(b"\x00\xff" * 100)
    with pytest.raises(DatasetError, match="junk.pcd: not a PCD file"):
        read_point_cloud(tmp_path / "junk.pcd")
    (tmp_path / "nodata.pcd").write_text("VERSION 0.7\nFIELDS x y z\n")
    with pytest.raises(DatasetError, match="no DATA line"):
        read_point_cloud(tmp_path / "nodata.pcd")
    (tmp_path / "noxyz.pcd").write_text("VERSION 0.7\nFIELDS a b\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\n"
                                        "WIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n")
    with pytest.raises(DatasetError, match="no field.*x, y, z"):
        read_point_cloud(tmp_path / "noxyz.pcd")
    with pytest.raises(DatasetError, match="no such point-cloud file"):
        read_point_cloud(tmp_path / "missing.pcd")
    (tmp_path / "a.las").write_bytes(b"LASF")
    with pytest.raises(DatasetError, match="unknown point-cloud suffix"):
        read_point_cloud(tmp_path / "a.las")
    (tmp_path / "bad.ply").write_text("not a ply\n")
    with pytest.raises(DatasetError, match="bad.ply: unreadable or truncated PLY"):
        read_point_cloud(tmp_path / "bad.ply")


# ----------------------------------------------------------------------------- real data


def _header_points(path) -> int:
    for line in path.read_bytes()[:1000].split(b"\n"):
        if line.startswith(b"POINTS"):
            return int(line.split()[1])
    raise AssertionError(f"{path}: no POINTS line")


def test_opencalib_fixture(shared_data):
    files = sorted((shared_data / "opencalib_car5" / "top_center_lidar").glob("*.pcd"))
    assert len(files) == 5
    for f in files:
        assert b"DATA binary_compressed" in f.read_bytes()[:600]
        c = read_point_cloud(f)
        assert len(c) == _header_points(f) > 70_000 and c.num_dropped == 0
        rings = np.unique(c.ring)
        assert rings[0] == 0 and 30 < rings[-1] < 64
        np.testing.assert_array_equal(rings, np.arange(rings[-1] + 1))  # rings 0..N, none missing
        assert c.time_field == "timestamp" and c.stamp > 1.6e9  # absolute UNIX seconds
        span = float(c.time_offsets.max() - c.time_offsets.min())
        assert span == pytest.approx(0.1, abs=0.005)  # 10 Hz sweeps
        r = np.linalg.norm(c.points, axis=1)
        assert 3.0 < np.median(r) < 80.0  # metres, not mm


def test_walk_scan_reads(shared_data):
    f = shared_data / "balm_hilti_walk" / "scans" / "000000.pcd"
    c = read_point_cloud(f)
    assert len(c) == _header_points(f)
    assert c.intensity is not None and c.ring is None and c.time_offsets is None


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_header_that_undercounts_its_payload_is_an_error(tmp_path, encoding):
    """A PCD whose POINTS (and WIDTH) says fewer points than its payload holds was read silently
    as a shorter cloud; now it is an error naming the file and both counts."""
    path = tmp_path / "under.pcd"
    pts = np.arange(30, dtype=np.float32).reshape(10, 3)
    write_point_cloud(path, pts, encoding=encoding)
    data = path.read_bytes().replace(b"WIDTH 10\n", b"WIDTH 6\n").replace(b"POINTS 10\n", b"POINTS 6\n")
    path.write_bytes(data)
    with pytest.raises(DatasetError, match=r"under.pcd: PCD header does not match its payload: (10 rows|120 payload bytes hold 10 points), the header says 6 points"):
        read_point_cloud(path)
    path.write_bytes(data.replace(b"WIDTH 6\n", b"WIDTH 10\n"))  # WIDTH 10, POINTS 6
    with pytest.raises(DatasetError, match=r"under.pcd: PCD header does not match itself: WIDTH 10 x HEIGHT 1"):
        read_point_cloud(path)
