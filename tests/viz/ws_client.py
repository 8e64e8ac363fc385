"""A small Foxglove WebSocket protocol client (aiohttp) for the live-server tests.

Speaks the protocol as Foxglove does: offers the ``foxglove.sdk.v1`` / ``foxglove.websocket.v1``
subprotocols, reads the server's JSON ``serverInfo`` and ``advertise``, subscribes to the wanted
topics, and collects binary ``messageData`` frames (opcode 0x01: uint32 subscription id, uint64
log time ns, payload) per topic. Runs its own event loop in a thread.
"""

from __future__ import annotations

import asyncio
import json
import struct
import threading
import time
from collections import defaultdict

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
OP_MESSAGE_DATA, OP_TIME = 0x01, 0x02


class FoxgloveClient:
    """Connects to ``url`` and subscribes to ``topics`` (None: every advertised topic)."""

    def __init__(self, url: str, topics: list[str] | None) -> None:
        self.url, self.topics = url, topics
        self.channels: dict[str, dict] = {}
        self.messages: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
        self.counts: dict[str, int] = defaultdict(int)
        self.server_info: dict | None = None
        self.subprotocol: str | None = None
        self.last_time_ns: int | None = None
        self.error: BaseException | None = None
        self._subs: dict[int, str] = {}
        self._subscribed = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> "FoxgloveClient":
        self._thread.start()
        return self

    def wait_connected(self, timeout_s: float) -> None:
        """Until every wanted topic is subscribed (or raise)."""
        if not self._subscribed.wait(timeout_s):
            raise TimeoutError(f"no subscription within {timeout_s} s ({self.error!r})")

    def wait_for(self, topic: str, n: int, timeout_s: float) -> int:
        t0 = time.monotonic()
        while self.counts[topic] < n and time.monotonic() - t0 < timeout_s:
            time.sleep(0.02)
        return self.counts[topic]

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # surfaced through wait_connected / the test's asserts
            self.error = exc

    async def _main(self) -> None:
        import aiohttp

        async with aiohttp.ClientSession() as session:
            async with session.ws_connect(self.url, protocols=SUBPROTOCOLS, max_msg_size=0) as ws:
                self.subprotocol = ws.protocol
                next_id = 0
                while not self._stop.is_set():
                    try:
                        msg = await ws.receive(timeout=0.1)
                    except asyncio.TimeoutError:
                        continue
                    if msg.type == aiohttp.WSMsgType.TEXT:
                        body = json.loads(msg.data)
                        if body.get("op") == "serverInfo":
                            self.server_info = body
                        elif body.get("op") == "advertise":
                            subs = []
                            for ch in body["channels"]:
                                self.channels[ch["topic"]] = ch
                                if self.topics is None or ch["topic"] in self.topics:
                                    self._subs[next_id] = ch["topic"]
                                    subs.append({"id": next_id, "channelId": ch["id"]})
                                    next_id += 1
                            if subs:
                                await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": subs}))
                            wanted = set(self.topics) if self.topics is not None else set(self.channels)
                            if wanted <= set(self._subs.values()):
                                self._subscribed.set()
                    elif msg.type == aiohttp.WSMsgType.BINARY:
                        data = msg.data
                        if data[0] == OP_MESSAGE_DATA:
                            sub_id, log_time = struct.unpack_from("<IQ", data, 1)
                            topic = self._subs.get(sub_id)
                            if topic is not None:
                                self.messages[topic].append((log_time, bytes(data[13:])))
                                self.counts[topic] += 1
                        elif data[0] == OP_TIME:
                            self.last_time_ns = struct.unpack_from("<Q", data, 1)[0]
                    elif msg.type in (aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR, aiohttp.WSMsgType.CLOSE):
                        return


def main() -> None:
    """``python -m tests.viz.ws_client URL`` subscribes to every topic until stdin closes, then
    prints the message counts as JSON (a viewer in its own process, for overhead measurements)."""
    import sys

    client = FoxgloveClient(sys.argv[1], None).start()
    client.wait_connected(60.0)
    print("subscribed", flush=True)
    sys.stdin.read()
    client.stop()
    print(json.dumps(dict(client.counts)), flush=True)


if __name__ == "__main__":
    main()
