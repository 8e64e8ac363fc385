"""``LiveServer``: a Foxglove WebSocket server streaming a run while it tracks (a RunObserver).

The same topics as the recording (:mod:`blockloc.viz.ros_messages`), served by foxglove-sdk's
WebSocket server on ``host:port`` (loopback by default; ``0.0.0.0`` exposes it to the network).
Open it in Foxglove: Open connection > Foxglove WebSocket > ``ws://127.0.0.1:8765``, or the link
of :func:`blockloc.viz.layout.websocket_app_urls`.

It never makes tracking wait: the server runs in the viz worker process
(:mod:`blockloc.viz.worker`) from construction on (so a viewer can connect before the run
starts); frames it cannot take yet are dropped here (``dropped``), and the SDK drops the oldest
messages of a client that reads too slowly. Messages are built only for topics a client
subscribed to, plus the latched ones (blocks, local map, paths), which a late client gets again.
"""

from __future__ import annotations

import logging

from blockloc.viz.events import FrameEvent, RunInfo
from blockloc.viz.ros_messages import Decimator

log = logging.getLogger(__name__)


class LiveServer:
    """Serve a run live on ``ws://host:port`` (port 0: a free port, see ``port`` after construction).

    points_budget_mb_per_min: as for the recording, None (default) for no budget: every scan is
    sent, thinned to ``scan_points_max`` points (8000 points at 10 Hz is ~1 MB/s on loopback).
    background: serve from the worker process (False: from this process, for debugging).
    message_options: keyword arguments of :class:`~blockloc.viz.ros_messages.RunMessages`.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, points_budget_mb_per_min: float | None = None,
                 scan_points_max: int = 8000, map_points_max: int = 100_000, background: bool = True,
                 message_options: dict | None = None, message_backlog_size: int = 256) -> None:
        from blockloc.viz.worker import Hosted

        self.decimator = Decimator(points_budget_mb_per_min=points_budget_mb_per_min,
                                   scan_points_max=scan_points_max, map_points_max=map_points_max)
        # The live view shows the path as it grows: send it every second, not every five.
        options = {"path_period_s": 1.0, **(message_options or {})}
        spec = {"kind": "live", "messages": options,
                "sink": {"host": host, "port": int(port), "message_backlog_size": int(message_backlog_size)}}
        self._host = Hosted(spec, background=background, drop_when_busy=True, what=f"live view on {host}:{port}")
        opened = self._host.opened
        self.port: int = int(opened["port"])
        self.url: str = opened["url"]
        self.summary: dict | None = None
        log.info("live view: %s", self.url)

    @property
    def worker(self):
        """The background worker (:class:`~blockloc.viz.worker.WorkerProxy`: its ``proc``,
        ``unread_bytes()``) once started with ``background``, else None (for measurement)."""
        host = getattr(self, "_host", None)
        return None if host is None else host.proxy

    @property
    def dropped(self) -> int:
        """Frames dropped because the worker was busy (always 0 with background=False)."""
        return self._host.dropped

    def app_urls(self) -> tuple[str, str]:
        """(https://app.foxglove.dev link, foxglove:// desktop link) opening this server."""
        from blockloc.viz.layout import websocket_app_urls

        return websocket_app_urls(self.url)

    def start(self, info: RunInfo) -> None:
        self.decimator.start()
        self._host.start(info)

    def frame(self, event: FrameEvent) -> None:
        if self.summary is None:
            self._host.frame(self.decimator.thin(event))

    def finish(self, metrics: dict, reason: str = "finished") -> None:
        """Stop the server (safe after an exception, and twice)."""
        if self.summary is not None:
            return
        self.summary = {}  # set first: a finish that raises is not tried again
        self.summary = self._host.finish(metrics, reason)
        if self.dropped:
            log.info("live view: %d frames dropped while the viewer was busy", self.dropped)
