"""``blockloc track``: a sequence tracked in a prior map, results written as it goes."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

from blockloc.errors import MapError, TrackingError

log = logging.getLogger("blockloc")


def resolve_map(ref, map_path: str | None, backend: str, cfg, data_root: str | None) -> str:
    """``--map``, else ``map.path`` of the config, else the sequence's default map (which must
    exist: MapError with the command that builds it)."""
    from blockloc.commands.common import map_params
    from blockloc.datasets.refs import map_kind_for_backend
    from blockloc.maps.files import open_map_files

    path = map_path or cfg.map.path or None
    if path is not None:
        return str(path)
    kind = map_kind_for_backend(backend)
    default = ref.default_map_path(kind, data_root=data_root, dataset_cfg=cfg.dataset,
                                   map_params=map_params(cfg.map, kind))
    if not open_map_files(default).exists("manifest.json"):
        raise MapError(f"map for {ref.text} not found at {default}; build it with: {ref.build_hint(kind, default)}")
    return str(default)


def open_session(seq: str, *, cfg, map_path: str | None = None, backend: str | None = None,
                 data_root: str | None = None, observers=(), out_dir: Path | None = None,
                 keep_estimates: bool = False, lidar_topic: str | None = None,
                 imu_topic: str | None = None, poses=None):
    """The Session for ``--seq`` in its map (what ``track`` and the benchmarks run)."""
    from blockloc.datasets.refs import SequenceRef
    from blockloc.maps.store import open_map_from_config
    from blockloc.session import Session

    ref = SequenceRef.parse(seq)
    backend = backend or cfg.map.backend
    sequence = ref.open(data_root=data_root, dataset_cfg=cfg.dataset, lidar_topic=lidar_topic, imu_topic=imu_topic,
                        poses=poses)
    path = resolve_map(ref, map_path, backend, cfg, data_root)
    store = open_map_from_config(path, cfg.map)
    return Session.from_config(cfg, sequence, store, backend=backend, observers=observers, out_dir=out_dir,
                               keep_estimates=keep_estimates, facts={"map": path})


def init_mode(init: Optional[str], init_pose: Optional[str]) -> tuple[str, tuple | None]:
    """(--init gt | --init-pose x,y[,yaw] | neither) -> (mode, hint)."""
    from blockloc.commands.common import parse_pose_hint

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
    After a SIGINT/SIGTERM the partial results are written, then ``Interrupted`` is raised."""
    from blockloc.commands.common import Interrupted, interruptible, progress

    stop_at = None if max_frames is None else max_frames
    total = len(session.stamps) if stop_at is None else min(stop_at, len(session.stamps))
    with interruptible() as stop, progress(label, total) as cb:
        res = session.run(0, stop_at, init=mode, pose_hint=hint, progress=cb, should_stop=stop)
    if stop():
        done = res.metrics.get("processed", 0)
        where = f"; partial results in {out_dir}" if out_dir is not None else ""
        raise Interrupted(f"interrupted after {done} of {total} frames{where}", stop.exit_code)
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
        web, _ = server.app_urls
        print(f"live view: {server.url} (Foxglove: {web})", file=sys.stderr, flush=True)
        observers.append(server)
    return observers


def write_run_report(session, res, out_dir: Path) -> Path:
    """``report.html`` in the results folder: metrics, plots, config and an interactive top view."""
    from blockloc.maps.summary import map_points_xy
    from blockloc.viz.layout import REPORT_NAME
    from blockloc.viz.report import write_report

    images = {caption: out_dir / name for caption, name in (("trajectories", "trajectories.png"),
                                                             ("errors over time", "errors.png"),
                                                             ("error breakdown", "error_breakdown.png"))
              if (out_dir / name).is_file()}
    return write_report(out_dir / REPORT_NAME, metrics=res.metrics, estimate=res.trajectory,
                        ground_truth=session.ground_truth, diagnostics=res.diagnostics, config=session.config,
                        map_xy=map_points_xy(session.store) if session.store is not None else None,
                        map_entries=session.run_info().map_entries, images=images,
                        title=f"{res.metrics.get('sequence')}")


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
                  live: bool = False, host: str = "127.0.0.1", port: int = 8765) -> None:
    from blockloc.commands.common import check_results_dir, config_for, console, results_dir

    mode, hint = init_mode(init, init_pose)
    if max_frames is not None and max_frames < 1:
        raise TrackingError(f"--max-frames {max_frames}: expected a positive number of frames")
    cfg = config_for(seq, config, sets)
    out_dir = results_dir(out, seq)
    check_results_dir(out_dir)  # before any work
    observers = run_observers(out_dir, record=record, record_path=record_path, live=live, host=host, port=port)
    session = open_session(seq, cfg=cfg, map_path=map_path, backend=backend, data_root=data_root,
                           observers=observers, out_dir=out_dir, lidar_topic=lidar_topic,
                           imu_topic=imu_topic, poses=poses)
    try:
        res = run_tracking(session, mode=mode, hint=hint, out_dir=out_dir, max_frames=max_frames)
    finally:
        if session.result is not None:  # whatever was computed, also when interrupted
            write_run_report(session, session.result, out_dir)
    print_track_summary(console(), res.metrics, res.out_dir)
    print_where(console(), out_dir)


def print_where(console, out_dir: Path) -> None:
    """Where the results are and how to look at them."""
    from blockloc.viz.layout import RECORDING_NAME, REPORT_NAME

    for name, what in ((REPORT_NAME, "report"), (RECORDING_NAME, "recording (Foxglove)")):
        if (out_dir / name).exists():
            console.print(f"{what}: {out_dir / name}")
    console.print(f"how to view: blockloc view {out_dir}")
