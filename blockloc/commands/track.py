"""``blockloc track``: a sequence tracked in a prior map, results written as it goes (the session
and the run: :mod:`blockloc.app.runs`; here: options, progress, Ctrl-C, printing)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Optional

from blockloc.app.runs import open_session, track, write_run_report
from blockloc.commands.common import (Interrupted, check_results_dir, config_for, console, interruptible,
                                      parse_pose_hint, progress, results_dir, track_bytes)
from blockloc.errors import BlocklocError, TrackingError
from blockloc.outdir import check_free_space

log = logging.getLogger("blockloc")


def init_mode(init: Optional[str], init_pose: Optional[str]) -> tuple[str, tuple | None]:
    """(--init gt | --init-pose x,y[,yaw] | neither) -> (mode, hint)."""
    if init not in (None, "gt"):
        raise TrackingError(f"--init {init!r}: expected 'gt' (or use --init-pose x,y[,yaw])")
    if init and init_pose:
        raise TrackingError("--init gt and --init-pose exclude each other")
    if init:
        return "gt", None
    if init_pose:
        return "pose", parse_pose_hint(init_pose, "--init-pose")
    return "global", None


def run_tracking(session, *, mode: str, hint, out_dir: Path | None, label: str = "tracking",
                 max_frames: int | None = None):
    """Run a session with a progress display and honest interruption; returns the RunResult.
    After a SIGINT/SIGTERM the partial results are written, then ``Interrupted`` is raised; a
    results file that cannot be written raises OutputWriteError (:func:`blockloc.app.runs.track`)."""
    total = len(session.stamps) if max_frames is None else min(max_frames, len(session.stamps))
    with interruptible() as stop, progress(label, total) as cb:
        res = track(session, mode=mode, hint=hint, max_frames=max_frames, progress=cb, should_stop=stop)
    if stop():
        done = res.metrics.get("processed", 0)
        where = f"; partial results in {out_dir}" if out_dir is not None else ""
        raise Interrupted(f"interrupted by {stop.name} after {done} of {total} frames{where}", stop.exit_code)
    return res


def run_observers(out_dir: Path, *, record: bool = True, record_path: Path | None = None, live: bool = False,
                  host: str = "127.0.0.1", port: int = 8765) -> list:
    """The results folder writer, the MCAP recording (default ``<out>/run.mcap``, with a Foxglove
    layout beside it) and, with ``live``, a Foxglove WebSocket server on ``host:port``."""
    from blockloc.evaluation.results import RunWriter

    observers = [RunWriter(out_dir)]
    if record:
        from blockloc.viz.layout import RECORDING_NAME
        from blockloc.viz.mcap_recorder import McapRecorder

        observers.append(McapRecorder(record_path or out_dir / RECORDING_NAME))
    if live:
        import sys

        from blockloc.viz.live import LiveServer

        server = LiveServer(host, port)
        web, _ = server.app_urls()
        print(f"live view: {server.url} (Foxglove: {web})", file=sys.stderr, flush=True)
        observers.append(server)
    return observers


def print_track_summary(console, m: dict, out: Optional[Path]) -> None:
    from rich.table import Table

    def f(v, fmt="{:.3f}"):
        return "-" if v is None else (fmt.format(v) if isinstance(v, float) else str(v))

    t = Table(title=f"blockloc track: {m.get('sequence')} ({m.get('backend')} map, {m.get('registration')})",
              show_header=False)
    t.add_column(style="bold")
    t.add_column(justify="right")
    init = m.get("init") or {}
    rows = [("frames", f(m.get("frames"))), ("init", f(init.get("mode"))),
            ("init error (m)", f(init.get("error_m"))),
            ("ATE translation RMSE (m)", f(m.get("ate_trans_rmse_m"))),
            ("ATE full RMSE", f(m.get("ate_full_rmse"))), ("ATE rotation RMSE (deg)", f(m.get("ate_rot_rmse_deg"))),
            ("failures / recoveries", f"{m.get('failures')} / {m.get('recoveries')}"),
            ("map switches", f(m.get("switches"))),
            ("skipped frames / map faults", f"{m.get('skipped_frames')} / {m.get('map_faults')}"),
            ("update median / p99 (ms)", f"{f(m.get('update_ms_median'), '{:.1f}')} / {f(m.get('update_ms_p99'), '{:.1f}')}"),
            ("peak RSS (MB)", f(m.get("peak_rss_mb"), "{:.0f}"))]
    for k, v in rows:
        if v != "-" or k.startswith("ATE"):
            t.add_row(k, v)
    console.print(t)
    if out is not None:
        console.print(f"results in {out}")


def track_command(seq: str, map_path: str | None, backend: str | None, init: str | None, init_pose: str | None,
                  out: Path | None, config: str | None, data_root: str | None, max_frames: int | None,
                  lidar_topic: str | None = None, imu_topic: str | None = None, poses: Path | None = None,
                  sets: list[str] | None = None, record: bool = True, record_path: Path | None = None,
                  live: bool = False, host: str = "127.0.0.1", port: int = 8765, detect_changes: bool = False,
                  changes_stride: int = 1) -> None:
    mode, hint = init_mode(init, init_pose)
    if changes_stride < 1:
        raise TrackingError(f"--changes-stride {changes_stride}: expected a positive number of frames")
    if max_frames is not None and max_frames < 1:
        raise TrackingError(f"--max-frames {max_frames}: expected a positive number of frames")
    cfg = config_for(seq, config, sets)
    out_dir = results_dir(out, seq)
    check_results_dir(out_dir, track_bytes(max_frames or 1, record))  # before any work
    observers = run_observers(out_dir, record=record, record_path=record_path, live=live, host=host, port=port)
    changes = None
    if detect_changes:  # the change detector, fed frame by frame as the session emits them
        from blockloc.app.runs import LiveChanges

        changes = LiveChanges(stride=changes_stride)
        observers.append(changes)
    session = open_session(seq, cfg=cfg, map_path=map_path, backend=backend, data_root=data_root,
                           observers=observers, out_dir=out_dir, lidar_topic=lidar_topic,
                           imu_topic=imu_topic, poses=poses)
    try:  # now that the frame count is known: room for all of them
        check_free_space(out_dir, track_bytes(min(max_frames or len(session.stamps), len(session.stamps)), record))
        if changes is not None:  # before any work: the detector needs a block store
            from blockloc.app.lifelong import check_detectable

            check_detectable(session.store, str(session.facts.get("map")))
            changes.attach(session)
    except BaseException:
        session.close()  # the map provider's thread
        raise
    ok = False
    try:
        res = run_tracking(session, mode=mode, hint=hint, out_dir=out_dir, max_frames=max_frames)
        ok = True
    finally:
        if session.result is not None:  # whatever was computed, also when interrupted
            write_run_report(session, session.result, out_dir, quiet=not ok)
            if changes is not None and not ok:  # what the frames before the stop showed
                write_detected_changes(changes, session, out_dir, interrupted=True)
    print_track_summary(console(), res.metrics, res.out_dir)
    if changes is not None:
        write_detected_changes(changes, session, out_dir)
    print_where(console(), out_dir)


def write_detected_changes(changes, session, out_dir: Path, interrupted: bool = False) -> None:
    """``--detect-changes``: ``changes.json`` from what the detector accumulated while tracking,
    drawn into the run's recording and report; after an interruption (or a failed run) from the
    frames before it, said in its params. A detector that stopped on an error writes no
    changes.json: TrackingError naming why (only logged after an interruption, whose message
    stands); the tracking results are whole either way."""
    from blockloc.app.runs import write_live_changes
    from blockloc.commands.lifelong import print_changes

    if changes.error is not None:
        msg = f"change detection stopped on an error ({changes.error}); no changes.json written"
        if interrupted:
            log.error("%s", msg)
            return
        raise TrackingError(f"--detect-changes: {msg}")
    try:
        doc = write_live_changes(changes, session, out_dir, interrupted=interrupted)
    except (OSError, BlocklocError) as exc:
        if not interrupted:
            raise
        log.error("changes.json not written: %s", exc)
        return
    if interrupted:
        print(f"changes.json written from the {doc['frames_trusted']} trusted frames before the stop: "
              f"{out_dir / 'changes.json'}", file=sys.stderr, flush=True)
        return
    print_changes(doc, out_dir / "changes.json")
    c = doc["cost"]
    console().print(f"change detection while tracking: {c['cpu_ms_per_frame_tracked']:.1f} ms CPU per frame "
                    f"tracked (p50 {c['per_frame_cpu_ms']['p50']:.1f}, p99 {c['per_frame_cpu_ms']['p99']:.1f} ms), "
                    f"{c['per_scan_cpu_ms']['p50']:.1f} ms per scan used (p99 {c['per_scan_cpu_ms']['p99']:.1f}); "
                    f"{c['final_cpu_s']:.1f} s CPU at the end; load {c['load_1min']}")


def print_where(console, out_dir: Path) -> None:
    """Where the results are and how to look at them."""
    from blockloc.viz.layout import RECORDING_NAME, REPORT_NAME

    for name, what in ((REPORT_NAME, "report"), (RECORDING_NAME, "recording (Foxglove)")):
        if (out_dir / name).exists():
            console.print(f"{what}: {out_dir / name}")
    console.print(f"how to view: blockloc view {out_dir}")
