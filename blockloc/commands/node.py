"""``blockloc node``: localize live from ROS 2 topics over DDS; ``--out`` writes a run folder as ``track`` does."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np


log = logging.getLogger("blockloc")


def map_gravity(store, option: str | None) -> np.ndarray:
    """Gravity (3,) in the map frame, m/s^2: ``--gravity`` (down | up | X,Y,Z), else the map's
    (:func:`blockloc.node._assemble.map_gravity`), else z up (REP 103) with a warning."""
    from blockloc.commands.map import parse_gravity
    from blockloc.node._assemble import map_gravity as gravity_of_map

    if option is not None:
        return parse_gravity(option)
    g = gravity_of_map(store)
    if g is not None:
        return g
    log.warning("the map's gravity is unknown (no place index, no mapping sequence): z up; "
                "give --gravity down|up|X,Y,Z")
    return parse_gravity("up")


def node_command(map_path: str, config: str | None, init_pose: str | None, points_topic: str, imu_topic: str,
                 out: Path | None, discovery: str | None, gravity: str | None = None, sets: list[str] | None = None,
                 no_data_timeout_s: float = 5.0, queue_size: int = 2, frames: dict | None = None) -> None:
    from blockloc.app.runs import write_run_report
    from blockloc.commands.common import Interrupted, check_results_dir, config_for, interruptible, parse_pose_hint
    from blockloc.commands.track import run_observers
    from blockloc.node import _assemble
    from blockloc.node.node import LocalizationNode, NodeSettings
    from blockloc.node.player import FrameNames
    from blockloc.ros2.dds import Dds

    hint = parse_pose_hint(init_pose, "--init-pose") if init_pose else None
    cfg = config_for(None, config, sets)
    store = _assemble.open_store(map_path, cfg)
    gravity_map = map_gravity(store, gravity)
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
    node = LocalizationNode(dds, make_session, settings=settings, gravity_map=gravity_map,
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
