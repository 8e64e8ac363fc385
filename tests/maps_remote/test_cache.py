"""TileCache: content addressed, validated on read, LRU-bounded in bytes, atomic."""

from __future__ import annotations

import hashlib
import os
import threading
import time

import pytest

from blockloc.errors import MapError
from blockloc.maps.remote import TileCache


def _blob(i: int, size: int = 1000) -> tuple[str, bytes]:
    data = bytes([i % 256]) * size + str(i).encode()
    return hashlib.sha256(data).hexdigest(), data


def test_put_get_roundtrip_and_layout(tmp_path):
    c = TileCache(tmp_path / "c", max_bytes=10_000)
    sha, data = _blob(1)
    assert c.get(sha) is None
    assert c.put(sha, data)
    assert c.get(sha) == data
    assert (tmp_path / "c" / sha[:2] / sha).read_bytes() == data
    assert sha in c and len(c) == 1 and c.bytes_used == len(data)
    # no temporary files left behind
    assert [p.name for p in (tmp_path / "c" / sha[:2]).iterdir()] == [sha]


def test_corrupt_entry_is_dropped(tmp_path):
    c = TileCache(tmp_path, max_bytes=10_000)
    sha, data = _blob(2)
    c.put(sha, data)
    path = tmp_path / sha[:2] / sha
    path.write_bytes(data[:-1] + b"X")
    assert c.get(sha) is None
    assert not path.exists() and sha not in c and c.bytes_used == 0 and c.corrupt_dropped == 1


def test_lru_eviction_by_bytes(tmp_path):
    c = TileCache(tmp_path, max_bytes=3500)  # room for three 1 kB blobs
    blobs = [_blob(i) for i in range(4)]
    for sha, data in blobs[:3]:
        c.put(sha, data)
    assert c.get(blobs[0][0]) == blobs[0][1]  # 0 becomes the most recent; 1 is the oldest
    c.put(*blobs[3])
    assert blobs[1][0] not in c and not (tmp_path / blobs[1][0][:2] / blobs[1][0]).exists()
    for i in (0, 2, 3):
        assert c.get(blobs[i][0]) == blobs[i][1]
    assert c.bytes_used <= 3500


def test_recency_survives_a_restart(tmp_path):
    c = TileCache(tmp_path, max_bytes=10_000)
    blobs = [_blob(i) for i in range(3)]
    for k, (sha, data) in enumerate(blobs):
        c.put(sha, data)
        os.utime(tmp_path / sha[:2] / sha, ns=(10**18 + k * 10**9, 10**18 + k * 10**9))
    c.get(blobs[0][0])  # touch: now the newest on disk too
    again = TileCache(tmp_path, max_bytes=2100)  # scanning evicts the least recent one
    assert len(again) == 2 and blobs[1][0] not in again
    assert again.get(blobs[0][0]) == blobs[0][1]


def test_too_big_entry_is_not_cached_and_bad_keys_rejected(tmp_path):
    c = TileCache(tmp_path, max_bytes=100)
    sha, data = _blob(5)
    assert not c.put(sha, data) and c.get(sha) is None
    with pytest.raises(ValueError):
        c.get("../../etc/passwd")
    with pytest.raises(MapError, match="expected >= 0"):
        TileCache(tmp_path, max_bytes=-1)


def test_shared_directory_between_instances(tmp_path):
    a = TileCache(tmp_path, max_bytes=10_000)
    b = TileCache(tmp_path, max_bytes=10_000)
    sha, data = _blob(7)
    a.put(sha, data)
    assert b.get(sha) == data and sha in b  # written by "another process"
    a.clear()
    assert b.get(sha) is None and sha not in b


def test_concurrent_puts_and_gets(tmp_path):
    c = TileCache(tmp_path, max_bytes=20_000)
    blobs = [_blob(i) for i in range(40)]
    errors = []

    def worker(seed):
        try:
            for k in range(200):
                sha, data = blobs[(seed * 7 + k) % len(blobs)]
                got = c.get(sha)
                if got is None:
                    c.put(sha, data)
                elif got != data:
                    errors.append(sha)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(s,)) for s in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors
    assert c.bytes_used <= 20_000
    on_disk = sum(p.stat().st_size for p in tmp_path.rglob("*") if p.is_file())
    assert on_disk == c.bytes_used
    assert not list(tmp_path.rglob("*.tmp"))
