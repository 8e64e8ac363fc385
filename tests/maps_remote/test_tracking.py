"""Tracking a short stretch of the small simulated session with the map from HTTP and from s3://
gives the same trajectory as with the map on disk.

The pipeline opens maps with ``blockloc.maps.store.open_map``; until that dispatches URLs to
``RemoteMapFiles`` itself, this test routes URLs there (the change proposed for ``open_map``).
"""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.maps.remote import RemoteMapFiles, is_url
from blockloc.maps.server import MapServer

from .conftest import FAST_RETRY

N_FRAMES = 40


@pytest.fixture(scope="module")
def small_world():
    from blockloc.config import load_config
    from blockloc.demo import DemoPaths, ensure_block_map, ensure_dataset

    cfg = load_config("sim")
    paths = DemoPaths.default()
    ensure_dataset(paths)
    ensure_block_map(paths, cfg)
    return paths, cfg


class _Remote:
    def __init__(self):
        self.made: list[RemoteMapFiles] = []  # the files objects open_map made
        self.options: dict = {}  # extra RemoteMapFiles options


@pytest.fixture
def remote_open_map(monkeypatch, tmp_path):
    """open_map that reads URLs through RemoteMapFiles."""
    from blockloc.maps import store as store_mod

    remote = _Remote()
    local_open = store_mod.open_map

    def open_map(path, **kw):
        if not is_url(path):
            return local_open(path)
        files = RemoteMapFiles(str(path), **{"cache_dir": tmp_path / "cache", "retry": FAST_RETRY,
                                              **remote.options})
        remote.made.append(files)
        return store_mod._open_manifest(files)

    monkeypatch.setattr(store_mod, "open_map", open_map)
    return remote


def _track(small_world, map_path):
    from blockloc.datasets import open_sequence
    from blockloc.pipeline import LocalizationPipeline

    paths, cfg = small_world
    seq = open_sequence(paths.dataset / "loc", dataset_cfg=cfg.dataset)
    res = LocalizationPipeline(seq, cfg=cfg, map_path=map_path, backend="block", init="gt",
                               max_frames=N_FRAMES).run()
    return res.trajectory


@pytest.fixture(scope="module")
def from_disk(small_world):
    return _track(small_world, small_world[0].block_map)


def _same(a, b):
    assert len(a.stamps) == len(b.stamps) == N_FRAMES
    np.testing.assert_array_equal(a.stamps, b.stamps)
    np.testing.assert_allclose(a.poses, b.poses, atol=1e-9)


def test_tracking_from_http_equals_disk(small_world, from_disk, remote_open_map):
    paths, _ = small_world
    with MapServer(paths.block_map) as srv:
        traj = _track(small_world, srv.url + "/")
    _same(traj, from_disk)
    (files,) = remote_open_map.made
    assert files.stats.fetched_files >= 2 and files.stats.failures == 0


def test_tracking_from_s3_equals_disk(small_world, from_disk, remote_open_map, s3_endpoint):
    import boto3

    paths, _ = small_world
    s3 = boto3.client("s3", endpoint_url=s3_endpoint, region_name="us-east-1")
    s3.create_bucket(Bucket="trackmaps")
    for p in sorted(paths.block_map.iterdir()):
        s3.upload_file(str(p), "trackmaps", f"small/{p.name}")
    remote_open_map.options["storage_options"] = {"client_kwargs": {"endpoint_url": s3_endpoint}}
    traj = _track(small_world, "s3://trackmaps/small/")
    _same(traj, from_disk)
    (files,) = remote_open_map.made
    assert files.stats.fetched_files >= 2 and files.stats.failures == 0
