"""``blockloc node``: localize live from ROS 2 topics over DDS; ``--out`` writes a run folder as ``track`` does."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np

from blockloc.errors import BlocklocError

log = logging.getLogger("blockloc")

GRAVITY = {"up": (0.0, 0.0, -9.81), "down": (0.0, 0.0, 9.81)}  # the map's z axis (REP 103: up)


def node_command(map_path: str, config: str | None, init_pose: str | None, points_topic: str, imu_topic: str,
                 out: Path | None, discovery: str | None, gravity: str = "up", sets: list[str] | None = None,
                 no_data_timeout_s: float = 5.0, queue_size: int = 2, frames: dict | None = None) -> None:
    from blockloc.commands.common import Interrupted, check_results_dir, config_for, interruptible, parse_pose_hint
    from blockloc.commands.track import run_observers, write_run_report
    from blockloc.node import _assemble
    from blockloc.node.node import LocalizationNode, NodeSettings
    from blockloc.node.player import FrameNames
    from blockloc.ros2.dds import Dds

    if gravity not in GRAVITY:
        raise BlocklocError(f"--gravity {gravity!r}: expected up or down (the map's z axis)")
    hint = parse_pose_hint(init_pose, "--init-pose") if init_pose else None
    cfg = config_for(None, config, sets)
    store = _assemble.open_store(map_path, cfg)
    lo = np.min([e.bounds_min[:2] for e in store.entries], axis=0)
    hi = np.max([e.bounds_max[:2] for e in store.entries], axis=0)
    if out is not None:
        check_results_dir(out)
    observers = run_observers(out) if out is not None else []

    def make_session(info, imu):
        return _assemble.build_session(cfg, store, map_path, info, imu, observers=observers, out_dir=out)

    dds = Dds(discovery)
    settings = NodeSettings(points_topic=points_topic, imu_topic=imu_topic, frames=FrameNames(**(frames or {})),
                            queue_size=queue_size, no_data_timeout_s=no_data_timeout_s)
    node = LocalizationNode(dds, make_session, settings=settings, gravity_map=GRAVITY[gravity],
                            map_bounds=(tuple(lo), tuple(hi)), init_pose=hint)
    where = "CYCLONEDDS_URI" if dds.user_uri else f"{dds.discovery} discovery"
    print(f"blockloc node: map {map_path}; listening on {points_topic} and {imu_topic} "
          f"(DDS domain {dds.domain}, {where}); Ctrl-C stops", file=sys.stderr, flush=True)
    res = None
    interrupted = False
    try:
        with interruptible() as stop:
            node.start()
            try:
                node.spin(stop)
            finally:
                interrupted = stop()
                res = node.close(interrupted=True)
    finally:
        if res is not None and out is not None:
            write_run_report(node.session, res, out)
        dds.close()
    s = node.stats
    summary = (f"{s.processed} scans processed, {s.published} poses published, {s.dropped} dropped, "
               f"{s.bad_scans} bad, {s.restarts} restarts")
    if interrupted:
        raise Interrupted(f"node stopped: {summary}" + (f"; results in {out}" if out is not None else ""),
                          stop.exit_code)
    print(summary, file=sys.stderr)
