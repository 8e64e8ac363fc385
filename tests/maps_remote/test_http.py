"""The store read through `blockloc map serve` over HTTP: identical entries, cache, faults."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from blockloc.errors import MapError
from blockloc.maps.files import MapFiles, open_map_files
from blockloc.maps.remote import RemoteMapFiles, RetryPolicy
from blockloc.maps.server import MapServer
from blockloc.maps.store import _open_manifest, open_map

from .conftest import FAST_RETRY, AppThread, write_grid_store


def _remote_store(url, cache_dir, **kw):
    files = RemoteMapFiles(url, cache_dir=cache_dir, retry=kw.pop("retry", FAST_RETRY), seed=0, **kw)
    return _open_manifest(files), files


def test_open_map_files_dispatches_on_scheme(tmp_path):
    assert isinstance(open_map_files(tmp_path), MapFiles)
    assert isinstance(open_map_files(f"file://{tmp_path}"), MapFiles)
    f = open_map_files("http://127.0.0.1:9/campus/", cache_dir=tmp_path / "c")
    assert isinstance(f, RemoteMapFiles) and f.url("a.pcd") == "http://127.0.0.1:9/campus/a.pcd"
    with pytest.raises(MapError, match="nosuchproto://x/y"):
        open_map_files("nosuchproto://x/y", cache_dir=False)
    with pytest.raises(MapError, match="not a plain relative name"):
        f.read_bytes("../secret.txt")


def test_every_entry_loads_identically_and_hits_the_cache(served, tmp_path):
    root, clouds, srv = served
    disk = open_map(root / "campus")
    store, files = _remote_store(f"{srv.url}/campus/", tmp_path / "cache")
    assert store.ids == disk.ids and store.kind == "grid" and store.params == disk.params
    for eid, (pts, inten) in clouds.items():
        p, i = store.load(eid)
        np.testing.assert_array_equal(p, pts)
        np.testing.assert_array_equal(i, inten)
    s1 = files.stats
    assert s1.cache_hits == 0 and s1.cache_misses == len(clouds)
    assert s1.fetched_files == len(clouds) + 1  # + the manifest
    for eid in clouds:
        np.testing.assert_array_equal(store.load(eid)[0], disk.load(eid)[0])
    s2 = files.stats
    assert s2.cache_hits == len(clouds) and s2.fetched_files == s1.fetched_files
    assert s2.hit_rate == pytest.approx(0.5)
    # a second robot with the same cache directory fetches only the manifest
    store2, files2 = _remote_store(f"{srv.url}/campus", tmp_path / "cache")
    store2.load_points(store2.ids)
    assert files2.stats.fetched_files == 1 and files2.stats.cache_hits == len(clouds)


def test_listing_exists_and_missing_file(served, tmp_path):
    root, clouds, srv = served
    files = RemoteMapFiles(f"{srv.url}/campus", cache_dir=False, retry=FAST_RETRY)
    assert files.exists("manifest.json") and not files.exists("nope.pcd") and files.is_dir()
    names = files.list_names()
    assert set(names) == {p.name for p in (root / "campus").iterdir() if not p.name.startswith(".")}  # hidden: not served
    before = files.stats.requests
    t0 = time.perf_counter()
    with pytest.raises(MapError, match=r"nope\.pcd: missing map file"):
        files.read_bytes("nope.pcd")
    assert files.stats.requests == before + 1  # a 404 is not retried
    assert files.online and time.perf_counter() - t0 < 1.0


def test_corrupt_cache_entry_is_refetched(served, tmp_path):
    root, clouds, srv = served
    store, files = _remote_store(f"{srv.url}/campus", tmp_path / "cache")
    eid = store.ids[1]
    store.load(eid)
    sha = store.entry(eid).sha256
    path = tmp_path / "cache" / sha[:2] / sha
    path.write_bytes(path.read_bytes()[:-10])  # truncated on disk
    p, _ = store.load(eid)
    np.testing.assert_array_equal(p, clouds[eid][0])
    assert files.cache.corrupt_dropped == 1 and files.stats.fetched_files == 3  # manifest + 2


def test_corrupt_download_is_fetched_again(served, tmp_path, monkeypatch):
    root, clouds, srv = served
    store, files = _remote_store(f"{srv.url}/campus", tmp_path / "cache")
    real = files._fs.cat_file
    calls = []

    def flaky(path, *a, **k):
        data = real(path, *a, **k)
        calls.append(path)
        if len(calls) == 1:
            return data[:100] + bytes([data[100] ^ 0xFF]) + data[101:]  # one flipped byte
        return data

    monkeypatch.setattr(files._fs, "cat_file", flaky)
    eid = store.ids[0]
    p, _ = store.load(eid)
    np.testing.assert_array_equal(p, clouds[eid][0])
    assert len(calls) == 2 and files.stats.corrupt_downloads == 1 and files.stats.retries == 1
    # the bad bytes never reached the cache
    assert files.cache.get(store.entry(eid).sha256) == (root / "campus" / store.entry(eid).file).read_bytes()


def test_persistently_corrupt_server_copy_is_a_clear_error(served, tmp_path, monkeypatch):
    root, clouds, srv = served
    store, files = _remote_store(f"{srv.url}/campus", tmp_path / "cache")
    real = files._fs.cat_file
    monkeypatch.setattr(files._fs, "cat_file", lambda path, *a, **k: real(path, *a, **k) + b"junk")
    with pytest.raises(MapError, match=r"checksum mismatch .* on all 3 tries"):
        store.load(store.ids[0])
    assert files.online  # the server answered: not counted as offline
    assert store.entry(store.ids[0]).sha256 not in files.cache


def test_server_killed_mid_run_then_back(tmp_path):
    clouds = write_grid_store(tmp_path / "campus", n_tiles=4)
    srv = MapServer(tmp_path / "campus")
    url = srv.start()
    store, files = _remote_store(url, tmp_path / "cache")
    ids = store.ids
    store.load(ids[0])
    srv.stop()  # the server disappears
    p, _ = store.load(ids[0])  # cached: still there
    np.testing.assert_array_equal(p, clouds[ids[0]][0])
    t0 = time.perf_counter()
    with pytest.raises(MapError, match=r"unreachable after 3 tries"):
        store.load(ids[1])
    assert time.perf_counter() - t0 < 5.0
    assert not files.online
    before = files.stats.requests
    t0 = time.perf_counter()
    with pytest.raises(MapError, match=r"unreachable after 1 tries \(server offline"):
        store.load(ids[2])  # offline: one quick try, no backoff
    assert files.stats.requests == before + 1 and time.perf_counter() - t0 < 1.0
    srv.start()  # the same port again
    assert srv.url == url
    for eid in ids[1:]:
        np.testing.assert_array_equal(store.load(eid)[0], clouds[eid][0])
    assert files.online
    srv.stop()
    before = files.stats.requests
    files.cache.clear()
    with pytest.raises(MapError, match="unreachable after 3 tries"):  # backoff state was reset
        store.load(ids[3])
    assert files.stats.requests == before + 3


def test_opens_offline_from_the_cached_manifest(tmp_path):
    clouds = write_grid_store(tmp_path / "campus", n_tiles=3)
    with MapServer(tmp_path / "campus") as srv:
        url = srv.url
        store, _ = _remote_store(url, tmp_path / "cache")
        store.load(store.ids[0])
    # server gone: a new process opens the map from what it cached
    files = RemoteMapFiles(url, cache_dir=tmp_path / "cache", retry=FAST_RETRY)
    assert files.exists("manifest.json") and not files.exists(".incomplete")
    again = _open_manifest(files)
    assert again.ids == store.ids and files.stats.offline_manifest == 1
    np.testing.assert_array_equal(again.load(store.ids[0])[0], clouds[store.ids[0]][0])
    with pytest.raises(MapError, match="unreachable"):
        again.load(store.ids[1])
    # no cached manifest: a clear error
    with pytest.raises(MapError, match=r"manifest\.json: unreachable after"):
        _open_manifest(RemoteMapFiles(url, cache_dir=tmp_path / "other", retry=FAST_RETRY))


def test_timeouts_are_retried_then_reported(tmp_path):
    from aiohttp import web

    hits = []

    async def slow(request):
        hits.append(request.path)
        await asyncio.sleep(1.5)
        return web.Response(body=b"late")

    app = web.Application()
    app.router.add_get("/{tail:.*}", slow)
    retry = RetryPolicy(timeout_s=0.2, retries=1, backoff_s=0.01, backoff_max_s=0.01)
    with AppThread(app) as server:
        files = RemoteMapFiles(server.url, cache_dir=False, retry=retry)
        t0 = time.perf_counter()
        with pytest.raises(MapError, match=r"x\.pcd: unreachable after 2 tries \(.*Timeout"):
            files.read_bytes("x.pcd")
        assert time.perf_counter() - t0 < 1.2
    assert len(hits) == 2


def test_server_errors_are_retried_and_client_errors_are_not(tmp_path):
    from aiohttp import web

    hits = []

    async def handler(request):
        hits.append(request.path)
        if request.path == "/flaky.bin" and hits.count("/flaky.bin") < 3:
            return web.Response(status=503)
        if request.path == "/forbidden.bin":
            return web.Response(status=403)
        return web.Response(body=b"payload")

    app = web.Application()
    app.router.add_get("/{tail:.*}", handler)
    with AppThread(app) as server:
        files = RemoteMapFiles(server.url, cache_dir=False, retry=FAST_RETRY)
        assert files.read_bytes("flaky.bin") == b"payload"
        assert files.stats.retries == 2
        with pytest.raises(MapError, match=r"forbidden\.bin: refused by the server .*403"):
            files.read_bytes("forbidden.bin")
    assert hits.count("/forbidden.bin") == 1


def test_threads_share_downloads(served, tmp_path):
    root, clouds, srv = served
    store, files = _remote_store(f"{srv.url}/campus", tmp_path / "cache")
    results, errors = {}, []
    barrier = threading.Barrier(8)

    def robot(k):
        try:
            barrier.wait(10)
            for eid in (store.ids[k % 4:] + store.ids[:k % 4]) * 3:
                results.setdefault(eid, []).append(store.load(eid)[0])
        except Exception as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=robot, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors
    for eid, arrays in results.items():
        assert len(arrays) == 24
        for a in arrays:
            np.testing.assert_array_equal(a, clouds[eid][0])
    assert files.stats.fetched_files == len(clouds) + 1  # each file downloaded once


def test_options_from_config_and_policy_validation(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from blockloc.config import Config
    from blockloc.app.assemble import remote_options as remote_options_from_config
    from blockloc.maps.remote import DEFAULT_CACHE_BYTES, default_cache_dir

    opts = remote_options_from_config(Config().map)  # fields not there yet: defaults
    assert opts["cache_dir"] is None and opts["cache_bytes"] == DEFAULT_CACHE_BYTES
    assert opts["retry"] == RetryPolicy()
    cfg = SimpleNamespace(remote_cache_dir=str(tmp_path), remote_cache_mb=8.0, remote_timeout_s=1.5,
                          remote_retries=5, remote_backoff_s=0.5)
    opts = remote_options_from_config(cfg)
    assert opts == {"cache_dir": str(tmp_path), "cache_bytes": 8 * 2**20,
                    "retry": RetryPolicy(timeout_s=1.5, retries=5, backoff_s=0.5)}
    with pytest.raises(MapError, match="retries >= 0"):
        RetryPolicy(retries=-1)
    p = RetryPolicy(backoff_s=0.1, backoff_max_s=0.5)
    import random

    rng = random.Random(0)
    delays = [p.delay(k, rng) for k in range(1, 6)]
    assert 0.05 <= delays[0] <= 0.1 and all(d <= 0.5 for d in delays) and delays[3] >= 0.25
    monkeypatch.setenv("BLOCKLOC_MAP_CACHE", str(tmp_path / "mc"))
    assert default_cache_dir() == tmp_path / "mc"
    monkeypatch.delenv("BLOCKLOC_MAP_CACHE")
    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path / "bc"))
    assert default_cache_dir() == tmp_path / "bc" / "remote-maps"
