"""Fixtures of the viz tests: a synthetic run recorded once, and both ways of reading it back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.viz.synthetic import make_run

LOST = tuple(range(40, 46))  # frames reported lost: no pose, no TF, no scan


@pytest.fixture(scope="session")
def synthetic_run():
    return make_run(duration_s=24.0, scan_points=20_000, lost_frames=LOST, map_points=150_000, seed=3)


@pytest.fixture(scope="session")
def recording(synthetic_run, tmp_path_factory):
    """(path, recorder) of the synthetic run recorded with the default worker process, a points
    budget small enough that some scans are dropped, and the TUM file of its poses."""
    from blockloc.trajectory_io import write_tum
    from blockloc.geometry import Trajectory
    from blockloc.viz.mcap_recorder import McapRecorder

    out = tmp_path_factory.mktemp("rec")
    rec = McapRecorder(out / "run.mcap", points_budget_mb_per_min=12.0, scan_points_max=6000,
                       map_points_max=50_000)
    rec.start(synthetic_run.info)
    for ev in synthetic_run.events:
        rec.frame(ev)
    rec.finish({"frames": len(synthetic_run.events), "note": "synthetic"})
    loc = synthetic_run.localized
    write_tum(out / "poses.tum", Trajectory(np.array([e.stamp for e in loc]), np.array([e.T_map_body for e in loc])))
    return out / "run.mcap", rec


def read_mcap_ros2(path: Path):
    """[(topic, log_time_ns, message)] decoded by the mcap library's ROS 2 decoder."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(ch.topic, m.log_time, msg) for _, ch, m, msg in reader.iter_decoded_messages(log_time_order=True)]


def read_rosbags(path: Path):
    """[(topic, log_time_ns, message)] read by rosbags' MCAP reader and deserialized by its typestore."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(path) as reader:
        return [(c.topic, t, store.deserialize_cdr(raw, c.msgtype)) for c, t, raw in reader.messages()]


READERS = {"mcap_ros2": read_mcap_ros2, "rosbags": read_rosbags}


@pytest.fixture(scope="session", params=sorted(READERS))
def decoded(request, recording):
    """The recording read back by one reader: {topic: [(log_time_ns, message)]}."""
    out: dict[str, list] = {}
    for topic, t, msg in READERS[request.param](recording[0]):
        out.setdefault(topic, []).append((t, msg))
    for v in out.values():
        v.sort(key=lambda x: x[0])
    return out
