"""The viz worker: a child process that builds, writes and serves a run's messages, so tracking does not.

Building ROS 2 messages and compressing MCAP chunks costs about 1 ms per frame in Python, a sixth
of a small-world tracking step; in a thread it would also compete for the GIL. So an observer
(:class:`~blockloc.viz.mcap_recorder.McapRecorder`, :class:`~blockloc.viz.live.LiveServer`) only
thins the frame's clouds and pickles it; a sender thread writes it to the worker's stdin (a 1 MB
pipe) and the worker does the rest on the other core.

Protocol, parent -> worker (stdin): 8-byte little-endian length + a pickle, in this order:
``("open", spec)``, ``("start", RunInfo)``, ``("frame", FrameEvent)``..., ``("finish", metrics, reason)``.
Worker -> parent (its original stdout; the worker's own fd 1 is pointed at stderr so no library
print can break the protocol): one JSON line after ``open`` (``{"ok": true, ...}`` or
``{"ok": false, "error": ...}``) and one after ``finish`` (``{"ok": true, "summary": ...}``).

The worker ignores SIGINT (Ctrl-C reaches the whole process group; the tracking process decides)
and ends when its stdin closes: if the tracking process dies, even by SIGKILL, the worker still
finishes the file (``blockloc.end`` metadata says why) and exits.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import pickle
import queue
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from blockloc.viz.events import FrameEvent, VizError

log = logging.getLogger(__name__)

_LEN = struct.Struct("<Q")
ENDED_WITHOUT_FINISH = "the tracking process ended without finish() (killed or crashed)"
WORKER_FAILED = "viz worker failed"


def make_host(spec: dict):
    """A SinkHost for ``spec`` = {"kind": "mcap" | "live", "sink": kwargs, "messages": kwargs}."""
    from blockloc.viz.sinks import FoxgloveSink, McapSink, SinkHost

    kinds = {"mcap": McapSink, "live": FoxgloveSink}
    if spec.get("kind") not in kinds:
        raise VizError(f"viz worker: sink kind {spec.get('kind')!r}: expected mcap or live")
    return SinkHost(kinds[spec["kind"]](**spec.get("sink", {})), spec.get("messages"))


# Numpy arrays pickle at ~25 us each; raw bytes + shape at ~1 us. A frame crosses as a tuple of those.
_ARRAY_FIELDS = {"T_map_body": np.float64, "covariance": np.float64, "velocity_map": np.float64,
                 "scan_lidar": np.float32, "local_map_points": np.float32}


def pack_frame(ev: FrameEvent) -> tuple:
    """A FrameEvent as plain values (arrays as (bytes, shape)) for the worker's pipe."""
    out = []
    for f in dataclasses.fields(FrameEvent):
        v = getattr(ev, f.name)
        if f.name in _ARRAY_FIELDS and v is not None:
            a = np.asarray(v, dtype=_ARRAY_FIELDS[f.name])  # tobytes gathers a strided view once
            v = (a.tobytes(), a.shape)
        out.append(v)
    return tuple(out)


def unpack_frame(values: tuple) -> FrameEvent:
    kw = {}
    for f, v in zip(dataclasses.fields(FrameEvent), values):
        if f.name in _ARRAY_FIELDS and v is not None:
            v = np.frombuffer(v[0], dtype=_ARRAY_FIELDS[f.name]).reshape(v[1])
        kw[f.name] = v
    return FrameEvent(**kw)


# ------------------------------------------------------------------ the worker (child) side
def _read_exact(stream, n: int) -> bytes | None:
    data = stream.read(n)
    return data if data is not None and len(data) == n else None


def _recv(stream):
    head = _read_exact(stream, _LEN.size)
    if head is None:
        return None
    body = _read_exact(stream, _LEN.unpack(head)[0])
    return None if body is None else pickle.loads(body)


def child_main() -> None:
    """Entry point of the worker process (``python -c ...child_main()``)."""
    reply_fd = os.dup(1)
    os.dup2(2, 1)
    reply = os.fdopen(reply_fd, "w", buffering=1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def on_term(signum, frame):
        raise SystemExit(f"viz worker stopped by signal {signum}")

    signal.signal(signal.SIGTERM, on_term)
    stdin = sys.stdin.buffer

    def answer(obj) -> None:
        try:
            reply.write(json.dumps(obj) + "\n")
        except OSError:  # the tracking process is gone; nobody to tell
            pass

    host = None
    try:
        cmd = _recv(stdin)
        if cmd is None or cmd[0] != "open":
            return
        spec = cmd[1]
        logging.basicConfig(level=spec.get("log_level", logging.INFO), stream=sys.stderr,
                            format="%(levelname)s viz-worker: %(message)s")
        host = make_host(spec)
        answer({"ok": True, **host.open()})
    except Exception as exc:
        answer({"ok": False, "error": str(exc) if isinstance(exc, VizError) else f"{type(exc).__name__}: {exc}"})
        return
    metrics, reason = None, ENDED_WITHOUT_FINISH
    try:
        while True:
            cmd = _recv(stdin)
            if cmd is None:
                break
            if cmd[0] == "start":
                host.start(cmd[1])
            elif cmd[0] == "frame":
                host.frame(unpack_frame(cmd[1]))
            elif cmd[0] == "finish":
                metrics, reason = cmd[1], cmd[2]
                break
    except SystemExit as exc:
        reason = str(exc)
    except Exception as exc:
        log.exception("viz worker failed; closing what it wrote")
        reason = f"{WORKER_FAILED}: {type(exc).__name__}: {exc}"
    try:
        answer({"ok": True, "summary": host.finish(metrics, reason)})
    except Exception as exc:
        answer({"ok": False, "error": str(exc)})


# ------------------------------------------------------------------ the tracking (parent) side
class WorkerProxy:
    """Starts a worker for ``spec`` and feeds it (the tracking process's half).

    drop_when_busy: when ``max_queued`` frames wait, drop new frames (live view) instead of
    waiting for the worker (recording: every pose belongs in the file). The sender thread, not
    the tracking thread, makes the pipe writes: measured on 2 busy cores, writing from the
    tracking thread cost a median 0.5-1.0 ms a frame against 0.18 ms through the queue (a write
    wakes the worker, which then competes with the writer). The pipe is enlarged to
    ``pipe_bytes`` (Linux allows 1 MB unprivileged) so the sender rarely waits.
    """

    def __init__(self, spec: dict, *, drop_when_busy: bool, max_queued: int = 256, pipe_bytes: int = 1 << 20,
                 open_timeout_s: float = 120.0) -> None:
        self.drop_when_busy = drop_when_busy
        self.dropped = 0
        self.waited_s = 0.0
        self.failed: str | None = None
        self._finished = False
        spec = dict(spec, log_level=logging.getLogger("blockloc").getEffectiveLevel())
        root = str(Path(__file__).resolve().parents[2])  # the same blockloc as this process
        code = f"import sys; sys.path.insert(0, {root!r}); from blockloc.viz.worker import child_main; child_main()"
        self.proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self.pipe_bytes = _set_pipe_size(self.proc.stdin.fileno(), pipe_bytes)
        self._write(self._pack(("open", spec)))
        answer = self._answer(open_timeout_s)
        if not answer.get("ok"):
            self._close_pipes()
            raise VizError(answer.get("error") or "viz worker failed to start")
        self.opened = answer
        self._queue: queue.Queue = queue.Queue(maxsize=max_queued)
        self._sender = threading.Thread(target=self._send_loop, name="blockloc-viz-sender", daemon=True)
        self._sender.start()

    @staticmethod
    def _pack(obj) -> bytes:
        body = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        return _LEN.pack(len(body)) + body

    def _write(self, data: bytes) -> None:
        self.proc.stdin.write(data)
        self.proc.stdin.flush()

    def _send_loop(self) -> None:
        while True:
            data = self._queue.get()
            try:
                if data is None:
                    return
                if not self.failed:
                    self._write(data)
            except OSError as exc:  # the worker died: keep tracking, say so once
                self.failed = f"viz worker gone ({exc.__class__.__name__}); exit code {self.proc.poll()}"
                log.error("%s: no more frames are recorded or served", self.failed)
            finally:
                self._queue.task_done()

    def _answer(self, timeout_s: float) -> dict:
        """The worker's next JSON line, or a failure dict when it dies or stays silent."""
        fd = self.proc.stdout.fileno()
        ready, _, _ = select.select([fd], [], [], timeout_s)
        line = self.proc.stdout.readline() if ready else b""
        if not line:
            code = self.proc.poll()
            return {"ok": False, "error": f"viz worker {'exited with code ' + str(code) if code is not None else 'did not answer'}"
                                          " (its log is above)"}
        return json.loads(line)

    def send(self, obj) -> None:
        """Queue one command; with drop_when_busy a full queue drops it."""
        if self.failed or self._finished:
            return
        data = self._pack(obj)
        if self.drop_when_busy:
            try:
                self._queue.put_nowait(data)
            except queue.Full:
                self.dropped += 1
            return
        try:
            self._queue.put_nowait(data)
        except queue.Full:
            t0 = time.perf_counter()
            self._queue.put(data)
            self.waited_s += time.perf_counter() - t0

    def drain(self, timeout_s: float = 60.0) -> bool:
        """Wait until every queued frame is in the worker's pipe; False on timeout."""
        t0 = time.monotonic()
        while self._queue.unfinished_tasks and time.monotonic() - t0 < timeout_s:
            time.sleep(0.005)
        return not self._queue.unfinished_tasks

    def unread_bytes(self) -> int:
        """Bytes in the worker's pipe it has not read yet."""
        return 0 if self._finished else _unread_bytes(self.proc.stdin.fileno())

    def finish(self, metrics: dict | None, reason: str = "finished", timeout_s: float = 300.0) -> dict:
        """Send finish, wait for the worker's summary; raises VizError when it failed."""
        if self._finished:
            return self.summary
        self._finished = True
        self._queue.put(self._pack(("finish", metrics, reason)))
        self._queue.put(None)
        self._sender.join()
        # Read the answer even after a broken pipe: a worker that failed mid-run still closed its
        # file and said why before exiting.
        answer = self._answer(timeout_s)
        if not answer.get("ok") and self.failed:
            answer["error"] = f"{self.failed}; {answer.get('error')}"
        self._close_pipes()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        if not answer.get("ok"):
            raise VizError(answer.get("error", "viz worker failed"))
        self.summary = answer["summary"]
        return self.summary

    def _close_pipes(self) -> None:
        for f in (self.proc.stdin, self.proc.stdout):
            try:
                f.close()
            except OSError:
                pass


def _set_pipe_size(fd: int, size: int) -> int:
    """Enlarge a pipe (Linux F_SETPIPE_SZ); returns its size in bytes (64 KiB where not possible)."""
    import fcntl

    try:
        return int(fcntl.fcntl(fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), size))
    except OSError:
        return 1 << 16


def _unread_bytes(fd: int) -> int:
    """Bytes written to a pipe and not yet read (FIONREAD; 0 where unsupported)."""
    import array
    import fcntl
    import termios

    buf = array.array("i", [0])
    try:
        fcntl.ioctl(fd, termios.FIONREAD, buf, True)
    except OSError:
        return 0
    return int(buf[0])


class Hosted:
    """One sink behind one interface: in a worker process (background) or in this one.

    The observers' shared half: ``start``, ``frame`` (a thinned event), ``finish``. ``what``
    names the output in errors (e.g. "recording run.mcap"). ``proxy`` is the WorkerProxy or None.
    """

    def __init__(self, spec: dict, *, background: bool, drop_when_busy: bool, what: str) -> None:
        self.what = what
        if background:
            self.proxy = WorkerProxy(spec, drop_when_busy=drop_when_busy)
            self._local = None
            self.opened = self.proxy.opened
        else:
            self.proxy = None
            self._local = make_host(spec)
            self.opened = self._local.open()

    @property
    def dropped(self) -> int:
        return self.proxy.dropped if self.proxy is not None else 0

    @property
    def waited_s(self) -> float:
        return self.proxy.waited_s if self.proxy is not None else 0.0

    def start(self, info) -> None:
        if self.proxy is not None:
            self.proxy.send(("start", info))
        else:
            self._local.start(info)

    def frame(self, thin: FrameEvent) -> None:
        if self.proxy is not None:
            self.proxy.send(("frame", pack_frame(thin)))
        else:
            self._local.frame(thin)

    def finish(self, metrics: dict | None, reason: str) -> dict:
        """The sink's summary; raises VizError when the worker failed mid-run (its output was
        still closed cleanly with what came before)."""
        summary = (self.proxy.finish(metrics, reason) if self.proxy is not None
                   else self._local.finish(metrics, reason))
        failure = str(summary.get("reason", ""))
        if failure.startswith(WORKER_FAILED):
            raise VizError(f"{self.what}: {failure} (after {summary.get('frames', 0)} frames; "
                           f"what came before is kept)")
        return summary
