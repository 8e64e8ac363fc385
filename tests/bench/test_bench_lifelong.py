"""bench/lifelong.py's scoring: one-voxel-tolerant precision / recall, and the update's hash and
size check on two small stores (the bench itself runs minutes: python -m bench.lifelong)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import lifelong as B
from blockloc.maps.changes.detect import pack_keys


def test_precision_recall_with_one_voxel_tolerance():
    truth = pack_keys(np.array([[0, 0, 0], [1, 0, 0], [10, 10, 10]]))
    det = pack_keys(np.array([[0, 0, 1], [5, 5, 5]]))  # one next to the truth, one far off
    r = B._prf(det, truth)
    assert r["precision"] == 0.5 and r["recall"] == pytest.approx(2 / 3)
    assert r["f1"] == pytest.approx(2 * 0.5 * (2 / 3) / (0.5 + 2 / 3))
    empty = B._prf(np.zeros(0, np.int64), truth)
    assert np.isnan(empty["precision"]) and empty["recall"] == 0.0


def _store(root, files: dict, lifelong=None):
    root.mkdir()
    entries = []
    for bid, data in files.items():
        name = f"{bid}.pcd" if lifelong is None or bid not in lifelong["changed_blocks"] else f"{bid}.v2.pcd"
        (root / name).write_bytes(data)
        entries.append({"id": bid, "file": name, "bytes": len(data)})
    man = {"entries": entries}
    if lifelong is not None:
        man["lifelong"] = lifelong
    (root / "manifest.json").write_text(json.dumps(man))
    return root


def test_update_cost_hashes_the_unchanged_blocks(tmp_path):
    old = _store(tmp_path / "old", {"000": b"a" * 100, "001": b"b" * 100, "002": b"c" * 100})
    new = _store(tmp_path / "new", {"000": b"a" * 100, "001": b"B" * 90, "002": b"x" * 100},
                 {"changed_blocks": ["001"], "held_back": [{"block": "002"}]})
    fresh = _store(tmp_path / "fresh", {"000": b"a" * 95, "001": b"b" * 95, "002": b"c" * 100})
    c = B.update_cost(old, new, fresh, 10.0, 4.0)
    # 000 kept its bytes; 002 was not rebuilt yet its bytes differ: reported, not hidden
    assert c["unchanged_identical"] == 1 and c["unchanged_differ"] == ["002"]
    assert c["bytes_updated"] == 290 and c["bytes_fresh"] == 290 and c["bytes_stale"] == 300
    assert c["wall_per_block_s"] == 10.0 and c["cpu_per_block_s"] == 4.0 and c["held_back"] == 1
