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
                 no_data_timeout_s: float = 5.0, queue_size: int = 2, frames: dict | None = None,
                 detect_changes: bool = False, changes_stride: int = 1, backend: str | None = None) -> None:
    """``backend``: the map policy (``--map-backend``; None: the config's ``map.backend``)."""
    from blockloc.app.runs import write_run_report
    from blockloc.commands.common import Interrupted, check_results_dir, config_for, interruptible, parse_pose_hint
    from blockloc.commands.track import run_observers
    from blockloc.node import _assemble
    from blockloc.node.node import LocalizationNode, NodeSettings
    from blockloc.node.player import FrameNames
    from blockloc.ros2.dds import Dds

    from blockloc.errors import TrackingError

    if detect_changes and out is None:
        raise TrackingError("--detect-changes: needs --out DIR (changes.json is written there at shutdown)")
    if changes_stride < 1:
        raise TrackingError(f"--changes-stride {changes_stride}: expected a positive number of frames")
    hint = parse_pose_hint(init_pose, "--init-pose") if init_pose else None
    cfg = config_for(None, config, sets)
    store = _assemble.open_store(map_path, cfg)
    _assemble.check_backend(store, cfg, backend)  # before listening: a grid map for 'block' is one line now
    gravity_map = map_gravity(store, gravity)
    lo = np.min([e.bounds_min[:2] for e in store.entries], axis=0)
    hi = np.max([e.bounds_max[:2] for e in store.entries], axis=0)
    if out is not None:
        check_results_dir(out)
    observers = run_observers(out) if out is not None else []
    changes = None
    if detect_changes:  # the change detector, fed each processed scan on a worker thread of its own
        from blockloc.app.lifelong import check_detectable
        from blockloc.app.runs import LiveChanges
        from blockloc.node.changes import NodeChanges

        check_detectable(store, map_path)  # before listening
        changes = NodeChanges(LiveChanges(stride=changes_stride))

    def make_session(info, imu):
        session = _assemble.build_session(cfg, store, map_path, info, imu, backend=backend, observers=observers,
                                          out_dir=out)
        if changes is not None:
            changes.begin(session)
        return session

    dds = Dds(discovery)
    settings = NodeSettings(points_topic=points_topic, imu_topic=imu_topic, frames=FrameNames(**(frames or {})),
                            queue_size=queue_size, no_data_timeout_s=no_data_timeout_s)
    node = LocalizationNode(dds, make_session, settings=settings, gravity_map=gravity_map,
                            map_bounds=(tuple(lo), tuple(hi)), init_pose=hint, on_frame=changes,
                            on_restart=changes.restart if changes is not None else None)
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
        try:
            if res is not None and out is not None:
                write_run_report(node.session, res, out)
        finally:
            if changes is not None:
                write_node_changes(changes, node.session, out)
            dds.close()
    s = node.stats
    summary = (f"{s.processed} scans processed, {s.published} poses published, {s.dropped} dropped, "
               f"{s.bad_scans} bad, {s.restarts} restarts")
    if interrupted:  # the run folder is written only when a scan made a session
        written = out is not None and res is not None
        raise Interrupted(f"node stopped: {summary}" + (f"; results in {out}" if written else ""), stop.exit_code)
    print(summary, file=sys.stderr)


def write_node_changes(changes, session, out: Path) -> None:
    """``--detect-changes`` at shutdown: the scans still waiting are detected on, then
    ``out/changes.json`` (temp then rename) with the detector's cost and what it cost the node.
    Nothing to write (no scan came, or the detector stopped on an error) is one log line: the
    node's own exit code stands."""
    from blockloc.app.runs import write_live_changes
    from blockloc.errors import BlocklocError

    changes.close()
    live = changes.live
    if session is None or live.detector is None:
        log.warning("--detect-changes: no scan was processed; no changes.json written")
        return
    if live.error is not None:
        log.error("change detection stopped on an error (%s); no changes.json written", live.error)
        return
    try:
        doc = write_live_changes(live, session, out, during="node --detect-changes", cost=changes.cost())
    except (OSError, BlocklocError) as exc:
        log.error("changes.json not written: %s", exc)
        return
    c = doc["cost"]
    print(f"changes.json written: {out / 'changes.json'} ({doc['scans_used']} scans used of "
          f"{doc['frames_trusted']} trusted frames, {c['scans_dropped']} dropped for detection; "
          f"{c['per_scan_cpu_ms']['p50']:.1f} ms CPU per scan used, p99 {c['per_scan_cpu_ms']['p99']:.1f}; "
          f"load {c['load_1min']})", file=sys.stderr, flush=True)
