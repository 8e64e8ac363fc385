"""The store read from s3:// (moto's S3 server on 127.0.0.1): identical entries, cache, faults."""

from __future__ import annotations

import time

import numpy as np
import pytest

from blockloc.errors import MapError
from blockloc.maps.remote import RemoteMapFiles
from blockloc.maps.store import _open_manifest, open_map

from .conftest import FAST_RETRY, write_grid_store


def _upload(endpoint, bucket, prefix, directory):
    import boto3

    s3 = boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1")
    try:
        s3.create_bucket(Bucket=bucket)
    except s3.exceptions.BucketAlreadyOwnedByYou:
        pass
    for p in sorted(directory.iterdir()):
        s3.upload_file(str(p), bucket, f"{prefix}/{p.name}")
    return s3


def _s3_files(url, endpoint, cache_dir):
    return RemoteMapFiles(url, cache_dir=cache_dir, retry=FAST_RETRY, seed=0,
                          storage_options={"client_kwargs": {"endpoint_url": endpoint}})


def test_every_entry_loads_identically_from_s3_and_hits_the_cache(s3_endpoint, tmp_path):
    clouds = write_grid_store(tmp_path / "campus", n_tiles=4)
    _upload(s3_endpoint, "maps", "campus", tmp_path / "campus")
    disk = open_map(tmp_path / "campus")
    files = _s3_files("s3://maps/campus/", s3_endpoint, tmp_path / "cache")
    assert files.exists("manifest.json") and not files.exists("nope.pcd") and files.is_dir()
    assert set(files.list_names()) == {p.name for p in (tmp_path / "campus").iterdir()}
    store = _open_manifest(files)
    assert store.ids == disk.ids
    for eid, (pts, inten) in clouds.items():
        p, i = store.load(eid)
        np.testing.assert_array_equal(p, pts)
        np.testing.assert_array_equal(i, inten)
    for eid in clouds:
        store.load(eid)
    s = files.stats
    assert s.cache_misses == 4 and s.cache_hits == 4 and s.fetched_files == 5
    with pytest.raises(MapError, match=r"s3://maps/campus/nope\.pcd: missing map file"):
        files.read_bytes("nope.pcd")


def test_endpoint_from_the_environment(s3_endpoint, tmp_path, monkeypatch):
    clouds = write_grid_store(tmp_path / "m", n_tiles=2, seed=3)
    _upload(s3_endpoint, "envmaps", "m", tmp_path / "m")
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_endpoint)
    store = _open_manifest(RemoteMapFiles("s3://envmaps/m", cache_dir=False, retry=FAST_RETRY))
    for eid, (pts, _) in clouds.items():
        np.testing.assert_array_equal(store.load(eid)[0], pts)


def test_changed_object_is_refetched_until_it_matches(s3_endpoint, tmp_path):
    """An object replaced behind the manifest's back: a clear checksum error, never bad data."""
    write_grid_store(tmp_path / "m", n_tiles=2, seed=4)
    s3 = _upload(s3_endpoint, "maps", "changed", tmp_path / "m")
    files = _s3_files("s3://maps/changed", s3_endpoint, tmp_path / "cache")
    store = _open_manifest(files)
    e = store.entry(store.ids[0])
    s3.put_object(Bucket="maps", Key=f"changed/{e.file}", Body=b"garbage")
    with pytest.raises(MapError, match=r"checksum mismatch .* on all 3 tries"):
        store.load(e.id)
    assert files.stats.corrupt_downloads == 3 and files.online


def test_s3_server_killed_mid_run_then_back(s3_endpoint, tmp_path):
    """A second moto server on its own port: stopped and restarted (moto keeps its buckets)."""
    from moto.server import ThreadedMotoServer

    clouds = write_grid_store(tmp_path / "m", n_tiles=3, seed=5)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    port = server._server.server_port
    endpoint = f"http://127.0.0.1:{port}"
    try:
        _upload(endpoint, "killmaps", "m", tmp_path / "m")
        files = _s3_files("s3://killmaps/m", endpoint, tmp_path / "cache")
        store = _open_manifest(files)
        ids = store.ids
        store.load(ids[0])
        server.stop()
        np.testing.assert_array_equal(store.load(ids[0])[0], clouds[ids[0]][0])  # cached
        t0 = time.perf_counter()
        with pytest.raises(MapError, match=r"s3://killmaps/m/.*: unreachable after 3 tries"):
            store.load(ids[1])
        assert time.perf_counter() - t0 < 15 and not files.online
        server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
        server.start()
        for eid in ids[1:]:
            np.testing.assert_array_equal(store.load(eid)[0], clouds[eid][0])
        assert files.online
    finally:
        server.stop()
