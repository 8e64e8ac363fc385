"""The live Foxglove WebSocket server, seen by a client speaking the Foxglove WS protocol on 127.0.0.1."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time

import numpy as np
import pytest

from blockloc.viz.events import VizError
from tests.viz.synthetic import make_run
from tests.viz.ws_client import FoxgloveClient


def deserialize(client: FoxgloveClient, topic: str):
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    msgtype = client.channels[topic]["schemaName"]
    return [(t, store.deserialize_cdr(data, msgtype)) for t, data in client.messages[topic]]


@pytest.fixture
def server():
    from blockloc.viz.live import LiveServer

    srv = LiveServer(port=0)
    yield srv
    srv.finish({})


def test_client_receives_the_poses_of_a_short_run(server):
    run = make_run(duration_s=15.0, scan_points=20_000, lost_frames=(20, 21, 22))
    assert server.url == f"ws://127.0.0.1:{server.port}"  # loopback unless told otherwise
    client = FoxgloveClient(server.url, ["/localization/pose", "/points/aligned", "/diagnostics"]).start()
    try:
        client.wait_connected(30.0)
        assert client.subprotocol in ("foxglove.sdk.v1", "foxglove.websocket.v1")
        assert client.channels["/localization/pose"]["encoding"] == "cdr"
        assert client.channels["/localization/pose"]["schemaEncoding"] == "ros2msg"
        server.start(run.info)
        for ev in run.events:  # at 5x real time
            server.frame(ev)
            time.sleep(0.02)
        want = len(run.localized)
        got = client.wait_for("/localization/pose", want, 30.0)
        assert got >= 0.9 * want, f"{got} of {want} poses"
        stamps = {int(round(e.stamp * 1e9)): e for e in run.localized}
        for t, msg in deserialize(client, "/localization/pose"):
            p = msg.pose.pose.position
            assert np.allclose([p.x, p.y, p.z], stamps[t].T_map_body[:3, 3], atol=1e-9)
        assert client.counts["/points/aligned"] >= 0.9 * want  # no budget live: every scan, thinned
        assert client.counts["/diagnostics"] >= 0.9 * len(run.events)
        assert client.last_time_ns is not None and client.last_time_ns in stamps
    finally:
        client.stop()


def test_late_client_gets_the_latched_topics(server):
    run = make_run(duration_s=3.0, scan_points=500)
    server.start(run.info)
    for ev in run.events[:10]:
        server.frame(ev)
    time.sleep(1.0)
    client = FoxgloveClient(server.url, ["/map/blocks", "/ground_truth/path", "/map/local"]).start()
    try:
        client.wait_connected(30.0)
        # no further frame (a paused run): subscribing alone brings what was latched
        for topic in ("/map/blocks", "/ground_truth/path", "/map/local"):
            assert client.wait_for(topic, 1, 30.0) >= 1, topic
        ((_, gt),) = deserialize(client, "/ground_truth/path")[:1]
        assert len(gt.poses) > 10
    finally:
        client.stop()


def test_port_in_use_is_a_viz_error():
    from blockloc.viz.live import LiveServer

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(VizError, match="cannot start the Foxglove WebSocket server"):
            LiveServer(port=s.getsockname()[1])


def test_a_stalled_viewer_drops_frames_instead_of_blocking(server):
    """With the worker stopped (SIGSTOP), frame() still returns: frames are dropped."""
    run = make_run(duration_s=60.0, scan_points=2000)
    server.start(run.info)
    pid = server._host.proxy.proc.pid
    os.kill(pid, signal.SIGSTOP)
    try:
        done = threading.Event()

        def feed():
            for ev in run.events:
                server.frame(ev)
            done.set()

        threading.Thread(target=feed, daemon=True).start()
        assert done.wait(120.0), "frame() blocked on a stalled worker"
        assert server.dropped > 0
    finally:
        os.kill(pid, signal.SIGCONT)
