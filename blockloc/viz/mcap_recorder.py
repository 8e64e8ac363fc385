"""``McapRecorder``: a run as an MCAP file of ROS 2 messages, for Foxglove, RViz (``ros2 bag play``) and rosbags.

Topics, frames and decimation: :mod:`blockloc.viz.ros_messages`. The file is written with the
``mcap`` library's writer (ROS 2 profile, zstd chunks, message indexes, summary) and named
``<name>.partial`` while the run lasts; ``finish`` writes the summary and renames it to the final
name, also after an exception mid-run (the partial recording is then a complete, valid MCAP whose
``blockloc.end`` metadata says why it ended).

By default the messages are built and written by a worker process (:mod:`blockloc.viz.worker`);
the tracking process only thins the clouds and hands each frame over. Interrupted runs:

- the tracking process killed (SIGKILL, OOM, crash): the worker sees its input close, finishes
  the file normally (summary, index, rename; ``blockloc.end`` = "ended without finish()");
- both killed at once (SIGKILL to the process group, power cut): ``<name>.partial`` stays, with
  every chunk written up to the last flush (every ``flush_period_s`` of sensor time): a valid MCAP
  data section without summary. ``mcap.stream_reader.StreamReader`` reads it up to the cut, and
  ``mcap recover`` (the mcap CLI) rewrites it with an index.
"""

from __future__ import annotations

import logging
from pathlib import Path

from blockloc.viz.events import FrameEvent, RunInfo
from blockloc.viz.ros_messages import Decimator
from blockloc.viz.sinks import PARTIAL_SUFFIX

log = logging.getLogger(__name__)


class McapRecorder:
    """Record a run to ``path`` (a RunObserver).

    points_budget_mb_per_min: raw point bytes per minute of sensor time for the scan and local-map
    clouds together (:class:`~blockloc.viz.ros_messages.Decimator`; at the defaults a 10 Hz run
    keeps about one scan in three, of at most ``scan_points_max`` points). chunk_size: bytes of
    messages per compressed chunk. flush_period_s: sensor seconds between forced chunk flushes.
    write_layout: also write ``foxglove_layout.json`` beside the file. background: build and write
    in the worker process (False: in this process, about 1 ms a frame). message_options: keyword
    arguments of :class:`~blockloc.viz.ros_messages.RunMessages` (path decimation).

    After ``finish``, ``summary`` holds the message counts per topic (``summary["counts"]``) and
    ``decimator.counts`` the scans kept and dropped.
    """

    def __init__(self, path: str | Path, *, points_budget_mb_per_min: float | None = 20.0,
                 scan_points_max: int = 8000, map_points_max: int = 100_000, chunk_size: int = 1 << 20,
                 flush_period_s: float = 2.0, write_layout: bool = True, background: bool = True,
                 message_options: dict | None = None) -> None:
        from blockloc.viz.layout import LAYOUT_NAME

        self.path = Path(path)
        self.partial_path = self.path.with_name(self.path.name + PARTIAL_SUFFIX)
        self.decimator = Decimator(points_budget_mb_per_min=points_budget_mb_per_min,
                                   scan_points_max=scan_points_max, map_points_max=map_points_max)
        self.spec = {"kind": "mcap", "messages": dict(message_options or {}),
                     "sink": {"path": str(self.path), "chunk_size": int(chunk_size),
                              "flush_period_s": float(flush_period_s),
                              "layout_path": str(self.path.parent / LAYOUT_NAME) if write_layout else None}}
        self.background = background
        self.summary: dict | None = None
        self._host = None

    def start(self, info: RunInfo) -> None:
        from blockloc.viz.worker import Hosted

        self.decimator.start()
        self._host = Hosted(self.spec, background=self.background, drop_when_busy=False,
                            what=f"recording {self.path}")
        self._host.start(info)

    def frame(self, event: FrameEvent) -> None:
        if self._host is not None and self.summary is None:
            self._host.frame(self.decimator.thin(event))

    @property
    def worker(self):
        """The background worker (:class:`~blockloc.viz.worker.WorkerProxy`: its ``proc``,
        ``unread_bytes()``) once started with ``background``, else None (for measurement)."""
        host = getattr(self, "_host", None)
        return None if host is None else host.proxy

    def finish(self, metrics: dict, reason: str = "finished") -> None:
        """Close the recording (safe after an exception, and twice). ``reason``: recorded in the
        file's ``blockloc.end`` metadata, e.g. the exception that ended the run."""
        if self._host is None or self.summary is not None:
            return
        self.summary = {}  # set first: a finish that raises is not tried again
        self.summary = self._host.finish(metrics, reason)
        if self._host.waited_s > 1.0:
            log.info("recording: tracking waited %.1f s in total for the viz worker", self._host.waited_s)
