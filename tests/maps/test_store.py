"""Store format: manifest, checksums, atomic builds, the released block-map layout."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from blockloc.errors import MapError
from blockloc.maps.pcd import read_pcd, write_pcd
from blockloc.maps.store import MapWriter, open_map


def _write_store(out, kind="block", n_entries=3, seed=0):
    rng = np.random.default_rng(seed)
    clouds = {}
    params = {"tile_size_m": 10.0} if kind == "grid" else {"block_size_m": 50.0}
    with MapWriter(out, kind, params=params) as w:
        for k in range(n_entries):
            eid = f"{k:03d}" if kind == "block" else f"{10 * k + 5:.1f}_-5.0"
            pts = (rng.uniform(0, 10, (200, 3)) + [10 * k, -10, 0]).astype(np.float32)
            inten = rng.uniform(0, 100, 200).astype(np.float32)
            w.add(eid, pts, inten)
            clouds[eid] = (pts, inten)
        store = w.commit()
    return store, clouds


def test_manifest_roundtrip(tmp_path):
    store, clouds = _write_store(tmp_path / "m")
    again = open_map(tmp_path / "m")
    assert again.kind == "block" and again.frame == "map" and again.params == {"block_size_m": 50.0}
    assert again.ids == ["000", "001", "002"]
    for eid, (pts, inten) in clouds.items():
        p, i = again.load(eid)
        np.testing.assert_array_equal(p, pts)
        np.testing.assert_array_equal(i, inten)
        e = again.entry(eid)
        np.testing.assert_allclose(e.bounds_min, pts.min(0))
        np.testing.assert_allclose(e.centroid, pts.astype(float).mean(0), atol=1e-9)
        assert e.num_points == 200 and e.bytes == (tmp_path / "m" / e.file).stat().st_size
    assert len(again.load_points(["000", "002"])) == 400
    lo, hi = again.bounds()
    assert lo[0] >= 0 and hi[0] <= 30 and hi[0] > 25
    doc = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert doc["version"] == 1 and doc["kind"] == "block" and len(doc["entries"]) == 3


def test_entries_in_box(tmp_path):
    store, _ = _write_store(tmp_path / "m", n_entries=4)
    ids = [e.id for e in store.entries_in_box([12, -5], [18, -4])]
    assert ids == ["001"]
    ids = [e.id for e in store.entries_in_box([9, -5], [21, -4])]
    assert set(ids) >= {"001"} and "003" not in ids
    assert store.entries_in_box([100, 100], [200, 200]) == []


def test_block_store_writes_released_layout_and_it_opens_without_manifest(tmp_path):
    store, clouds = _write_store(tmp_path / "m")
    cents, _ = read_pcd(tmp_path / "m" / "CentroidCloud.pcd")
    np.testing.assert_allclose(cents, store.centroids(), atol=1e-4)
    (tmp_path / "m" / "manifest.json").unlink()
    legacy = open_map(tmp_path / "m")
    assert legacy.kind == "block" and legacy.legacy and legacy.ids == ["000", "001", "002"]
    p, _ = legacy.load("001")
    np.testing.assert_array_equal(p, clouds["001"][0])
    np.testing.assert_allclose(legacy.entry("001").bounds_max, clouds["001"][0].max(0))


def test_grid_store_writes_autoware_metadata(tmp_path):
    import yaml

    _write_store(tmp_path / "g", kind="grid", n_entries=2)
    meta = yaml.safe_load((tmp_path / "g" / "pointcloud_map_metadata.yaml").read_text())
    assert meta["x_resolution"] == 10.0 and meta["y_resolution"] == 10.0
    assert meta["5.0_-5.0.pcd"] == [0.0, -10.0]
    assert meta["15.0_-5.0.pcd"] == [10.0, -10.0]


def test_checksum_mismatch_and_truncation(tmp_path):
    _write_store(tmp_path / "m")
    f = tmp_path / "m" / "001.pcd"
    data = bytearray(f.read_bytes())
    data[-5] ^= 0xFF
    f.write_bytes(bytes(data))
    store = open_map(tmp_path / "m")
    with pytest.raises(MapError, match=r"001\.pcd: checksum mismatch"):
        store.load("001")
    f.write_bytes(bytes(data[:-40]))
    with pytest.raises(MapError, match=r"001\.pcd"):
        store.load("001")
    f.unlink()
    with pytest.raises(MapError, match=r"001\.pcd: missing map file"):
        store.load("001")
    store.load("000")  # the others still load


def test_bad_manifests(tmp_path):
    _write_store(tmp_path / "m")
    man = tmp_path / "m" / "manifest.json"
    doc = json.loads(man.read_text())
    man.write_text(json.dumps({**doc, "version": 99}))
    with pytest.raises(MapError, match="newer"):
        open_map(tmp_path / "m")
    man.write_text(json.dumps({**doc, "kind": "blob"}))
    with pytest.raises(MapError, match="kind"):
        open_map(tmp_path / "m")
    man.write_text("{not json")
    with pytest.raises(MapError, match="not valid JSON"):
        open_map(tmp_path / "m")
    with pytest.raises(MapError, match="no such map directory"):
        open_map(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(MapError, match="not a map store"):
        open_map(tmp_path / "empty")


def test_exception_mid_build_leaves_nothing(tmp_path):
    out = tmp_path / "m"
    with pytest.raises(RuntimeError):
        with MapWriter(out, "block") as w:
            w.add("000", np.zeros((5, 3)))
            raise RuntimeError("boom")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_refuses_existing_output_unless_overwrite(tmp_path):
    _write_store(tmp_path / "m")
    with pytest.raises(MapError, match="already exists"):
        MapWriter(tmp_path / "m", "block")
    with MapWriter(tmp_path / "m", "block", overwrite=True) as w:
        w.add("000", np.ones((3, 3)))
        store = w.commit()
    assert store.ids == ["000"] and len(list((tmp_path).iterdir())) == 1


def test_killed_build_does_not_load(tmp_path):
    """A build process killed half way leaves only a hidden temp dir that open_map refuses."""
    out = tmp_path / "m"
    script = textwrap.dedent(f"""
        import os, signal, numpy as np
        from blockloc.maps.store import MapWriter
        w = MapWriter({str(out)!r}, "block")
        for k in range(3):
            w.add(f"{{k:03d}}", np.random.default_rng(k).normal(size=(100, 3)))
        print(w.tmp, flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -9
    assert not out.exists()
    leftovers = [p for p in tmp_path.iterdir()]
    assert len(leftovers) == 1 and leftovers[0].name.startswith(".m.building-")
    with pytest.raises(MapError, match="incomplete"):
        open_map(leftovers[0])
    # even with the marker gone and the released layout's files present, no CentroidCloud -> no map
    (leftovers[0] / ".incomplete").unlink()
    with pytest.raises(MapError, match="not a map store"):
        open_map(leftovers[0])


def test_point_count_mismatch_names_the_file(tmp_path):
    """A valid file whose point count disagrees with the manifest (checksum matching, or absent)."""
    _write_store(tmp_path / "m")
    man = tmp_path / "m" / "manifest.json"
    doc = json.loads(man.read_text())
    good = json.loads(man.read_text())
    doc["entries"][1]["num_points"] = 201  # the file (checksum intact) holds 200
    man.write_text(json.dumps(doc))
    store = open_map(tmp_path / "m")
    with pytest.raises(MapError, match=r"001\.pcd: holds 200 points, manifest says 201"):
        store.load("001")
    assert len(store.load("000")[0]) == 200
    # a replaced file without a checksum in the manifest: the count still catches it
    pts, inten = read_pcd(tmp_path / "m" / "002.pcd")
    write_pcd(tmp_path / "m" / "002.pcd", pts[:150], inten[:150])
    good["entries"][2]["sha256"] = None
    man.write_text(json.dumps(good))
    with pytest.raises(MapError, match=r"002\.pcd: holds 150 points, manifest says 200"):
        open_map(tmp_path / "m").load("002")
