"""Where a run's ROS 2 messages go: an MCAP file or a Foxglove WebSocket server.

A :class:`SinkHost` turns thinned :class:`~blockloc.viz.events.FrameEvent`s into messages
(:class:`~blockloc.viz.ros_messages.RunMessages`) and hands them to one sink. It runs in the
viz worker process (:mod:`blockloc.viz.worker`) or, with ``background=False``, in the tracking
process itself.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path

import numpy as np

from blockloc.fileio import atomic_write_text, to_jsonable
from blockloc.viz.events import FrameEvent, RunInfo, VizError
from blockloc.viz.ros_codec import schema_text
from blockloc.viz.ros_messages import LATCHED, TOPICS, Outgoing, RunMessages

log = logging.getLogger(__name__)

PARTIAL_SUFFIX = ".partial"


def _library() -> str:
    from blockloc import __version__

    return f"blockloc {__version__} (mcap python)"


class McapSink:
    """Messages -> ``path`` (ROS 2 profile, zstd chunks, indexes, summary).

    Written as ``<path>.partial``; :meth:`finish` writes the summary and renames it to ``path``.
    The open chunk is closed and flushed to the OS every ``flush_period_s`` of sensor time, so a
    kill loses at most that much. ``layout_path``: also write the Foxglove layout there.
    """

    def __init__(self, path: str | Path, *, chunk_size: int = 1 << 20, flush_period_s: float = 2.0,
                 layout_path: str | Path | None = None) -> None:
        self.path = Path(path)
        self.partial_path = self.path.with_name(self.path.name + PARTIAL_SUFFIX)
        self.chunk_size, self.flush_period_s = int(chunk_size), float(flush_period_s)
        self.layout_path = Path(layout_path) if layout_path is not None else None
        self.counts: dict[str, int] = {t: 0 for t in TOPICS}
        self._stream = self._writer = None
        self._channels: dict[str, int] = {}
        self._last_flush: float | None = None
        self._failed = False
        self._done = False

    def open(self) -> dict:
        from mcap.writer import CompressionType, Writer

        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._stream = open(self.partial_path, "wb")
        except OSError as exc:
            raise VizError(f"recording {self.path}: cannot create {self.partial_path.name} ({exc.strerror})") from None
        self._writer = Writer(self._stream, chunk_size=self.chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library=_library())
        return {"path": str(self.path)}

    def wants(self, topic: str) -> bool:
        return topic in self._channels

    def start(self, info: RunInfo) -> None:
        from mcap.well_known import MessageEncoding, SchemaEncoding

        for topic, msgtype in TOPICS.items():
            if topic == "/ground_truth/path" and info.ground_truth is None:
                continue
            schema_id = self._writer.register_schema(msgtype, SchemaEncoding.ROS2, schema_text(msgtype).encode())
            self._channels[topic] = self._writer.register_channel(topic, MessageEncoding.CDR, schema_id)
        self._writer.add_metadata("blockloc.run", {
            "sequence": str(info.sequence), "map_kind": str(info.map_kind),
            "tile_size_m": "" if info.tile_size_m is None else f"{info.tile_size_m:g}",
            "map_entries": str(len(info.map_entries)),
            "T_body_lidar": json.dumps(np.asarray(info.T_body_lidar, float).tolist()),
            "frames": "map -> odom (identity) -> base_link (body) -> lidar",
            "config": json.dumps(to_jsonable(info.config)),
        })
        if self.layout_path is not None:
            from blockloc.viz.layout import write_layout

            write_layout(self.layout_path)
        log.info("recording to %s", self.path)

    def write(self, outgoing: list[Outgoing], stamp: float | None) -> None:
        if self._writer is None or self._failed:
            return
        for msg in outgoing:
            channel = self._channels.get(msg.topic)
            if channel is None:
                continue
            if not self._guard(self._writer.add_message, channel, msg.log_time_ns, msg.data, msg.log_time_ns,
                               self.counts[msg.topic]):
                return
            self.counts[msg.topic] += 1
        if stamp is None:
            return
        if self._last_flush is None:
            self._last_flush = stamp
        elif stamp - self._last_flush >= self.flush_period_s:
            self._last_flush = stamp
            flush = getattr(self._writer, "flush", None)  # Writer.flush: mcap >= 1.6; before, chunks close by size only
            if flush is not None:
                self._guard(flush)

    def finish(self, metrics: dict | None, reason: str) -> dict:
        """Summary, rename; ``reason`` ('finished' or why the run ended early) goes to the
        ``blockloc.end`` metadata record, ``metrics`` to ``blockloc.metrics``."""
        if self._done or self._writer is None:
            return {"counts": self.counts, "path": str(self.path)}
        self._done = True
        try:
            if not self._failed:
                self._writer.add_metadata("blockloc.end", {"reason": reason})
                if metrics is not None:
                    self._writer.add_metadata("blockloc.metrics", {"json": json.dumps(to_jsonable(metrics))})
            self._writer.finish()
            self._stream.close()
            os.replace(self.partial_path, self.path)
        except OSError as exc:
            raise VizError(f"recording {self.path}: cannot finish ({exc.strerror}); the partial "
                           f"recording stays at {self.partial_path}") from None
        finally:
            if not self._stream.closed:
                self._stream.close()
        size = self.path.stat().st_size
        log.info("recording %s: %d messages, %.1f MB", self.path, sum(self.counts.values()), size / 1e6)
        return {"counts": self.counts, "path": str(self.path), "bytes": size}

    def _guard(self, fn, *args) -> bool:
        """Run a write; on an OS error (disk full) log once and stop recording, not tracking."""
        try:
            fn(*args)
            return True
        except OSError as exc:
            self._failed = True
            log.error("recording %s stopped: %s (tracking goes on; the file keeps what was written)",
                      self.partial_path, exc)
            return False


def _make_listener(on_latched=None):
    """A foxglove ServerListener remembering the latched topics a client just subscribed to;
    ``on_latched()`` is called (from the server's thread) after each such subscription."""
    from foxglove.websocket import ServerListener

    class LatchListener(ServerListener):
        def __init__(self) -> None:
            self.lock = threading.Lock()
            self.resend: set[str] = set()

        def on_subscribe(self, client, channel) -> None:
            if channel.topic in LATCHED:
                with self.lock:
                    self.resend.add(channel.topic)
                if on_latched is not None:
                    on_latched()

        def pending(self) -> set[str]:
            with self.lock:
                return set(self.resend)

        def take_resend(self) -> set[str]:
            with self.lock:
                out, self.resend = self.resend, set()
            return out

    return LatchListener()


def _timer(delay_s: float, fn, *args) -> None:
    t = threading.Timer(delay_s, fn, args)
    t.daemon = True  # never keeps a finished run's process alive
    t.start()


class FoxgloveSink:
    """Messages -> a Foxglove WebSocket server (foxglove-sdk) on ``host:port`` (port 0: any free).

    Only topics some client subscribed to are built. ``channel.log`` never waits: the SDK queues
    up to ``message_backlog_size`` messages per client and drops the oldest beyond. A client
    subscribing to a latched topic (blocks, local map, paths) gets its last message again, right
    away (a paused or finished run sends no next frame). The server advertises the Time
    capability and broadcasts each frame's sensor time.
    """

    #: seconds after a subscription before the latched message is sent again: the SDK calls the
    #: listener before the new subscriber is among the channel's sinks
    RESEND_DELAY_S = 0.05

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, name: str = "blockloc",
                 message_backlog_size: int = 256) -> None:
        self.host, self.requested_port = host, int(port)
        self.name, self.message_backlog_size = name, int(message_backlog_size)
        self.counts: dict[str, int] = {t: 0 for t in TOPICS}
        self._listener = None
        self._last: dict[str, Outgoing] = {}
        self._server = None
        self._channels: dict = {}
        self._live_file: Path | None = None
        self._send_lock = threading.Lock()  # write() (the run's thread) and resends (a timer's)

    def open(self) -> dict:
        import foxglove
        from foxglove.websocket import Capability

        self._context = foxglove.Context()
        self._listener = _make_listener(self._resend_soon)
        try:
            self._server = foxglove.start_server(
                name=self.name, host=self.host, port=self.requested_port, context=self._context,
                capabilities=[Capability.Time], server_listener=self._listener,
                supported_encodings=["cdr"], session_id=f"blockloc-{os.getpid()}-{time.time_ns()}",
                message_backlog_size=self.message_backlog_size)
        except Exception as exc:  # the SDK raises RuntimeError on a port in use or a bad address
            raise VizError(f"live view on {self.host}:{self.requested_port}: cannot start the Foxglove "
                           f"WebSocket server ({exc}); pick another --port") from None
        for topic, msgtype in TOPICS.items():
            schema = foxglove.Schema(name=msgtype, encoding="ros2msg", data=schema_text(msgtype).encode())
            self._channels[topic] = foxglove.Channel(topic, schema=schema, message_encoding="cdr",
                                                     context=self._context)
        self.port = int(self._server.port)
        return {"port": self.port, "url": self.url}

    @property
    def url(self) -> str:
        host = self.host if self.host not in ("0.0.0.0", "::", "") else "127.0.0.1"
        return f"ws://{host}:{self.port}"

    def wants(self, topic: str) -> bool:
        ch = self._channels.get(topic)
        # Latched topics are always built: a client subscribing later needs their last message.
        return ch is not None and (topic in LATCHED or ch.has_sinks())

    def start(self, info: RunInfo) -> None:
        if info.out_dir is not None:
            from blockloc.viz.layout import LAYOUT_NAME, LIVE_NAME, write_layout

            out = Path(info.out_dir)
            if not (out / LAYOUT_NAME).exists():
                write_layout(out / LAYOUT_NAME)
            self._live_file = out / LIVE_NAME
            atomic_write_text(self._live_file, json.dumps({"url": self.url, "pid": os.getpid()}) + "\n")
        log.info("live view: %s (Foxglove: Open connection > Foxglove WebSocket)", self.url)

    def write(self, outgoing: list[Outgoing], stamp: float | None) -> None:
        if self._server is None:
            return
        with self._send_lock:
            self._resend_latched()
            for msg in outgoing:
                if msg.topic in LATCHED:
                    self._last[msg.topic] = msg
                if self._channels[msg.topic].has_sinks():
                    self._log(msg)
            if stamp is not None:
                self._server.broadcast_time(int(round(stamp * 1e9)))

    def _resend_latched(self) -> None:
        for topic in self._listener.take_resend():
            if topic in self._last:
                self._log(self._last[topic])

    def _resend_soon(self, tries: int = 20) -> None:
        """Send the latched messages just subscribed to, shortly, from a timer thread; again a
        little later while the new subscription is not yet among the channel's sinks."""

        def fire(left: int) -> None:
            with self._send_lock:
                if self._server is None:
                    return
                again = left > 0 and any(not self._channels[t].has_sinks()
                                         for t in self._listener.pending() if t in self._channels)
                if not again:
                    self._resend_latched()
            if again:
                _timer(self.RESEND_DELAY_S, fire, left - 1)

        _timer(self.RESEND_DELAY_S, fire, tries)

    def _log(self, msg: Outgoing) -> None:
        self._channels[msg.topic].log(msg.data, log_time=msg.log_time_ns)
        self.counts[msg.topic] += 1

    def finish(self, metrics: dict | None, reason: str) -> dict:
        with self._send_lock:
            server, self._server = self._server, None
        if server is not None:
            server.stop()
        if self._live_file is not None:
            self._live_file.unlink(missing_ok=True)
        return {"counts": self.counts, "url": self.url if hasattr(self, "port") else None}


class SinkHost:
    """RunMessages feeding one sink; the half of an observer that may live in the worker process."""

    def __init__(self, sink, message_options: dict | None = None) -> None:
        self.sink = sink
        self.messages = RunMessages(**(message_options or {}))
        self.started = False
        self.frames = 0

    def open(self) -> dict:
        opened = self.sink.open()
        self.messages.ros.prime()
        return opened

    def start(self, info: RunInfo) -> None:
        self.messages.start(info)
        self.sink.start(info)
        self.started = True

    def frame(self, event: FrameEvent) -> None:
        if not self.started:
            return
        self.sink.write(self.messages.frame(event, self.sink.wants), event.stamp)
        self.frames += 1

    def finish(self, metrics: dict | None, reason: str = "finished") -> dict:
        if self.started:
            self.sink.write(self.messages.finish(self.sink.wants), None)
        summary = self.sink.finish(metrics, reason)
        summary.update(frames=self.frames, reason=reason)
        return summary
