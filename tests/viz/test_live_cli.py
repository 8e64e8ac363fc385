"""``blockloc track ... --live --port N`` as a user types it: a Foxglove WebSocket client on
127.0.0.1 subscribes while the run tracks and receives its poses (this once exited at start with
``TypeError: cannot unpack non-iterable method object``)."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import threading
import time

import pytest

from tests.faults import tiny
from tests.faults.conftest import blockloc_env
from tests.viz.ws_client import FoxgloveClient


@pytest.fixture(scope="module")
def tiny_run_inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("live_cli")
    session = tiny.write_tiny_session(root / "sess", n_frames=120)
    return {"session": session, "map": tiny.build_tiny_map(session, root / "map"),
            "config": tiny.write_config(root / "cfg.yaml"), "root": root}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_track_live_serves_the_run_to_a_websocket_client(tiny_run_inputs):
    port = free_port()
    out = tiny_run_inputs["root"] / "out"
    # a paced IMU-free run would end too fast for a client to join: --no-record keeps it short,
    # and the client joins from the "live view:" line on, before the first frames are tracked
    proc = subprocess.Popen([sys.executable, "-m", "blockloc.cli", "track", "--seq", str(tiny_run_inputs["session"]),
                             "--map", str(tiny_run_inputs["map"]), "--config", str(tiny_run_inputs["config"]),
                             "--init", "gt", "--out", str(out), "--no-record", "--live", "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=blockloc_env())
    err = bytearray()
    reader = threading.Thread(target=lambda: [err.extend(c) for c in iter(lambda: os.read(proc.stderr.fileno(), 4096), b"")],
                              daemon=True)
    reader.start()
    client = None
    try:
        t0 = time.monotonic()
        while b"live view:" not in err:
            assert proc.poll() is None, f"exited {proc.returncode} before serving: {err.decode()[-800:]}"
            assert time.monotonic() - t0 < 120, err.decode()[-800:]
            time.sleep(0.02)
        url = re.search(r"live view: (ws://\S+)", err.decode()).group(1)
        assert url == f"ws://127.0.0.1:{port}"
        client = FoxgloveClient(url, ["/localization/pose"]).start()
        client.wait_connected(60.0)
        got = client.wait_for("/localization/pose", 5, 120.0)
        assert got >= 5, f"{got} poses received; stderr: {err.decode()[-800:]}"
        from rosbags.typesys import Stores, get_typestore

        store = get_typestore(Stores.ROS2_HUMBLE)
        schema = client.channels["/localization/pose"]["schemaName"]
        msg = store.deserialize_cdr(client.messages["/localization/pose"][0][1], schema)
        assert msg.header.frame_id == "map"
        assert proc.wait(300) == 0, err.decode()[-800:]
        assert (out / "metrics.json").is_file()
    finally:
        if client is not None:
            client.stop()
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
