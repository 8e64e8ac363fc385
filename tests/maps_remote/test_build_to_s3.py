"""`map build` straight to s3:// (moto's S3 server on 127.0.0.1): the same entries as a local
build, a manifest only when the build completed, nothing left when it failed."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.maps.build_plan import Drive, build_map_from_drives
from blockloc.maps.store import open_map

from maps.slow_sequences import FailingSequence
from maps.synthetic import MemorySequence, route, world_points

KW = dict(block_size_m=30.0, tile_size_m=10.0, voxel_size_m=0.3, keyframe_distance_m=2.0)


@pytest.fixture()
def bucket(s3_endpoint, monkeypatch):
    import boto3

    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_endpoint)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    s3 = boto3.client("s3", endpoint_url=s3_endpoint, region_name="us-east-1")
    s3.create_bucket(Bucket="built")
    yield s3
    for obj in s3.list_objects_v2(Bucket="built").get("Contents", []):
        s3.delete_object(Bucket="built", Key=obj["Key"])
    s3.delete_bucket(Bucket="built")


def _drive(cls=MemorySequence, **kw):
    world = world_points(extent=(-30, 110), seed=6, density=0.2)
    return [Drive.of(cls(world, route([[0, 0], [80, 0], [80, 30]], speed=4.0), radius=20.0, **kw))]


def _keys(s3, prefix):
    return sorted(o["Key"] for o in s3.list_objects_v2(Bucket="built", Prefix=prefix).get("Contents", []))


@pytest.mark.parametrize("kind", ["block", "grid"])
def test_build_to_s3_matches_the_local_build(tmp_path, bucket, kind):
    local = build_map_from_drives(_drive(), kind, tmp_path / "m", **KW)
    remote = build_map_from_drives(_drive(), kind, f"s3://built/{kind}", **KW)
    assert [(e.id, e.sha256) for e in remote.entries] == [(e.id, e.sha256) for e in local.entries]
    names = {p.name for p in (tmp_path / "m").iterdir()}
    assert _keys(bucket, f"{kind}/") == sorted(f"{kind}/{n}" for n in names)  # no scratch, no marker
    body = bucket.get_object(Bucket="built", Key=f"{kind}/manifest.json")["Body"].read()
    assert body == (tmp_path / "m" / "manifest.json").read_bytes()
    again = open_map(f"s3://built/{kind}", cache_dir=False)
    p, _ = again.load(again.ids[0])
    np.testing.assert_array_equal(p, local.load(local.ids[0])[0])


def test_failed_build_to_s3_leaves_nothing(bucket):
    with pytest.raises(OSError, match="unplugged"):
        build_map_from_drives(_drive(FailingSequence, fail_after=40), "block", "s3://built/bad", **KW)
    assert _keys(bucket, "bad/") == []


def test_existing_s3_store_needs_overwrite(bucket):
    from blockloc.errors import MapError

    build_map_from_drives(_drive(), "grid", "s3://built/g", **KW)
    with pytest.raises(MapError, match="already holds a map store"):
        build_map_from_drives(_drive(), "grid", "s3://built/g", **KW)
    store = build_map_from_drives(_drive(), "grid", "s3://built/g", overwrite=True, **KW)
    assert len(store) > 0 and "g/.incomplete" not in _keys(bucket, "g/")
