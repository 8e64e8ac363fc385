"""PCD reading/writing: round trips, interoperability with open3d, and clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.errors import MapError
from blockloc.maps.pcd import decode_pcd, encode_pcd, read_pcd, write_pcd


def _cloud(n=500, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(n, 3)) * 50).astype(np.float32), rng.uniform(0, 255, n).astype(np.float32)


def test_roundtrip_binary(tmp_path):
    pts, inten = _cloud()
    nbytes = write_pcd(tmp_path / "a.pcd", pts, inten)
    assert nbytes == (tmp_path / "a.pcd").stat().st_size
    p2, i2 = read_pcd(tmp_path / "a.pcd")
    assert p2.dtype == np.float32 and p2.shape == pts.shape
    np.testing.assert_array_equal(p2, pts)
    np.testing.assert_array_equal(i2, inten)
    assert not list(tmp_path.glob("*.tmp"))  # temp file renamed away


def test_empty_cloud_roundtrip(tmp_path):
    write_pcd(tmp_path / "e.pcd", np.zeros((0, 3)))
    p, i = read_pcd(tmp_path / "e.pcd")
    assert p.shape == (0, 3) and i.shape == (0,)


def test_open3d_reads_ours_and_we_read_open3d_variants(tmp_path):
    from blockloc.open3d_loader import open3d

    o3d = open3d()
    pts, inten = _cloud(300, seed=1)
    write_pcd(tmp_path / "ours.pcd", pts, inten)
    pc = o3d.t.io.read_point_cloud(str(tmp_path / "ours.pcd"))
    np.testing.assert_array_equal(pc.point.positions.numpy(), pts)
    np.testing.assert_array_equal(pc.point.intensity.numpy().ravel(), inten)
    # open3d's compressed and ASCII writers -> our reader
    o3d.t.io.write_point_cloud(str(tmp_path / "c.pcd"), pc, write_ascii=False, compressed=True)
    p2, i2 = read_pcd(tmp_path / "c.pcd")
    np.testing.assert_array_equal(p2, pts)
    np.testing.assert_array_equal(i2, inten)
    o3d.t.io.write_point_cloud(str(tmp_path / "t.pcd"), pc, write_ascii=True)
    p3, i3 = read_pcd(tmp_path / "t.pcd")
    np.testing.assert_allclose(p3, pts, atol=1e-4)
    np.testing.assert_allclose(i3, inten, atol=1e-4)


def test_real_hdl32e_scan(shared_data):
    pts, inten = read_pcd(shared_data / "hdl32e_pair" / "target.pcd")
    assert pts.shape == (69088, 3)
    assert inten is not None and inten.max() > 1.0
    assert np.isfinite(pts).all()


def test_xyz_only_and_extra_fields():
    header = (b"VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\n"
              b"WIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA binary\n")
    body = np.zeros(2, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    body["x"] = [1, 2]
    body["z"] = [3, 4]
    p, i = decode_pcd(header + body.tobytes(), "x.pcd")
    assert i is None
    np.testing.assert_array_equal(p, [[1, 0, 3], [2, 0, 4]])


def test_truncated_payload_names_file(tmp_path):
    pts, inten = _cloud(100)
    data = encode_pcd(pts, inten)
    (tmp_path / "t.pcd").write_bytes(data[:-10])
    with pytest.raises(MapError, match=r"t\.pcd: truncated"):
        read_pcd(tmp_path / "t.pcd")


@pytest.mark.parametrize("blob,msg", [
    (b"hello world\n", "not a PCD"),
    (b"VERSION 0.7\nFIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\nHEIGHT 1\n"
     b"POINTS 0\nDATA binary\n", "no 'x' field"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nPOINTS 1\n"
     b"DATA weird\n", "unsupported PCD DATA"),
    (b"\x00\x01\x02\xff\xfe\n", "not a PCD"),
])
def test_bad_headers(tmp_path, blob, msg):
    (tmp_path / "bad.pcd").write_bytes(blob)
    with pytest.raises(MapError, match=msg) as err:
        read_pcd(tmp_path / "bad.pcd")
    assert "bad.pcd" in str(err.value) and "\n" not in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(MapError, match="no such PCD file"):
        read_pcd(tmp_path / "nope.pcd")
