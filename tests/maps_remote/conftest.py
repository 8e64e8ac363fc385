"""Fixtures for the remote map tests: a small store, the project's server and an S3 emulator.

All network traffic goes to 127.0.0.1 on ports the OS picks.
"""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest

from blockloc.maps.remote import RetryPolicy
from blockloc.maps.server import MapServer
from blockloc.maps.store import MapWriter

# Short timeouts and backoff: the fault tests stay fast, the loops stay bounded.
FAST_RETRY = RetryPolicy(timeout_s=2.0, retries=2, backoff_s=0.02, backoff_max_s=0.1)


def write_grid_store(out, n_tiles=4, points_per_tile=300, seed=0):
    """A grid store of ``n_tiles`` 10 m tiles in a row; returns {tile id: (points, intensity)}."""
    rng = np.random.default_rng(seed)
    clouds = {}
    with MapWriter(out, "grid", params={"tile_size_m": 10.0}) as w:
        for k in range(n_tiles):
            eid = f"{10 * k + 5:.1f}_5.0"
            pts = (rng.uniform(0, 10, (points_per_tile, 3)) + [10 * k, 0, 0]).astype(np.float32)
            inten = rng.uniform(0, 100, points_per_tile).astype(np.float32)
            w.add(eid, pts, inten)
            clouds[eid] = (pts, inten)
        w.commit()
    return clouds


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """(server root, {id: clouds}, running MapServer) with the store at <url>/campus/."""
    root = tmp_path_factory.mktemp("served")
    clouds = write_grid_store(root / "campus")
    (root / "secret.txt").write_text("not a map file\n")  # beside the store, inside the root
    srv = MapServer(root)
    srv.start()
    yield root, clouds, srv
    srv.stop()


class AppThread:
    """Any aiohttp application on 127.0.0.1 in a background thread (fault-injecting servers)."""

    def __init__(self, app):
        self.app = app
        self.port = 0
        self._ready = threading.Event()
        self._loop = None
        self._stop = None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        from aiohttp import web

        async def main():
            self._stop = asyncio.Event()
            runner = web.AppRunner(self.app, access_log=None, shutdown_timeout=0.5)
            await runner.setup()
            site = web.TCPSite(runner, "127.0.0.1", 0)
            await site.start()
            self.port = runner.addresses[0][1]
            self._ready.set()
            await self._stop.wait()
            await runner.cleanup()

        self._loop = asyncio.new_event_loop()
        self._loop.run_until_complete(main())
        self._loop.close()

    @property
    def url(self):
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self):
        self._thread.start()
        assert self._ready.wait(10)
        return self

    def __exit__(self, *exc):
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)


@pytest.fixture(scope="module")
def s3_endpoint():
    """URL of a moto S3 server on 127.0.0.1 (fake credentials in the environment)."""
    pytest.importorskip("s3fs")  # optional dependencies of s3:// maps and of these tests
    ThreadedMotoServer = pytest.importorskip("moto.server").ThreadedMotoServer

    mp = pytest.MonkeyPatch()
    for k, v in {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
                 "AWS_DEFAULT_REGION": "us-east-1"}.items():
        mp.setenv(k, v)
    mp.delenv("AWS_PROFILE", raising=False)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    yield f"http://127.0.0.1:{server._server.server_port}"
    server.stop()
    mp.undo()
