"""The ``blockloc`` command line: a thin typer app.

Every command body imports what it needs lazily so ``blockloc --help`` stays instant; any
BlocklocError becomes one ``error: ...`` line and exit code 2 (a traceback only with --debug).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Optional

import typer

from blockloc import __version__

app = typer.Typer(
    name="blockloc",
    help="Localize a LiDAR + IMU robot in a large prior map, holding only the blocks it needs.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
map_app = typer.Typer(help="Build, tile, inspect and serve map stores.", no_args_is_help=True)
app.add_typer(map_app, name="map")

_state = {"debug": False}
log = logging.getLogger("blockloc")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"blockloc {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks and debug logs."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Info-level logs."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    _state["debug"] = debug
    level = logging.DEBUG if debug else (logging.INFO if verbose else logging.WARNING)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


def _console():
    from rich.console import Console

    return Console()


# ----------------------------------------------------------------------------- eval


@app.command("eval")
def eval_cmd(
    gt: Path = typer.Option(..., "--gt", help="Ground truth: TUM, KITTI or NCLT groundtruth csv."),
    est: Path = typer.Option(..., "--est", help="Estimate: TUM or KITTI."),
    align: bool = typer.Option(False, "--align", help="Umeyama SE(3) alignment before ATE."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Directory for PNG plots."),
    max_time_diff: float = typer.Option(0.02, "--max-time-diff", help="Association tolerance, s."),
    interpolate: bool = typer.Option(False, "--interpolate",
                                     help="Interpolate ground truth to the estimate's stamps (else nearest)."),
    rpe_deltas: str = typer.Option("1,10,100", "--rpe-deltas", help="RPE path-length deltas, m, comma separated."),
) -> None:
    """ATE (translation and full xyzrpy), rotation RMSE and RPE of an estimate against ground truth."""
    from blockloc.evaluation.report import evaluate_files, parse_deltas, print_metrics

    metrics = evaluate_files(gt, est, align=align, max_time_diff_s=max_time_diff, plot_dir=plot,
                             interpolate=interpolate, rpe_deltas_m=parse_deltas(rpe_deltas))
    if json_out:
        import json

        typer.echo(json.dumps(metrics))
    else:
        print_metrics(metrics, _console())


# ----------------------------------------------------------------------------- sim
@app.command("sim")
def sim_cmd(
    preset: str = typer.Option("small", "--preset", help="World preset: small | campus."),
    seed: int = typer.Option(1, "--seed", help="World and noise seed (same seed, same bytes)."),
    out: Path = typer.Option(..., "--out", help="Output directory (replaced when complete)."),
    fmt: str = typer.Option("nclt", "--format", help="nclt | rosbag1 | rosbag2."),
    azimuth_steps: Optional[int] = typer.Option(None, "--azimuth-steps",
                                                help="Columns per revolution (preset default)."),
) -> None:
    """Simulate a world and write its sessions (map, loc[, loc2]) with HDL-32E scans, IMU and ground truth."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from blockloc.sim.writer import generate_dataset

    overrides = {} if azimuth_steps is None else {"azimuth_steps": azimuth_steps}
    tasks: dict = {}
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), console=_console()) as bar:
        def progress(session: str, done: int, total: int) -> None:
            if session not in tasks:
                tasks[session] = bar.add_task(f"sim {preset}/{session}", total=total)
            bar.update(tasks[session], completed=done)

        path = generate_dataset(preset, seed, out, fmt, progress=progress, **overrides)
    typer.echo(f"wrote {path}")


# @sim-commands (anchor: the sim stage adds its command above this line)

# ----------------------------------------------------------------------------- map
@map_app.command("build")
def map_build_cmd(
    seq: str = typer.Option(..., "--seq", help="Mapping sequence: name (nclt_2, sim:small/map) or path."),
    kind: str = typer.Option("block", "--kind", help="block | grid"),
    out: Path = typer.Option(..., "--out", help="Output map directory (written atomically)."),
    config: Optional[str] = typer.Option(None, "--config", help="Config file or preset name."),
    data_root: Optional[str] = typer.Option(None, "--data-root", help="Root of the datasets."),
    block_size: Optional[float] = typer.Option(None, "--block-size", help="Block size S, m."),
    tile_size: Optional[float] = typer.Option(None, "--tile-size", help="Grid tile side, m."),
    voxel: Optional[float] = typer.Option(None, "--voxel", help="Voxel filter size, m."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", help="Use only the first N frames."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing map."),
) -> None:
    """Build a block map or grid tiles from a mapping sequence and its poses."""
    import dataclasses

    from blockloc.datasets import open_sequence
    from blockloc.maps.tools import build_map, map_summary, print_summary

    from blockloc.config import load_config_for_sequence

    cfg = load_config_for_sequence(seq, config)
    overrides = {k: v for k, v in (("block_size_m", block_size), ("tile_size_m", tile_size),
                                   ("voxel_size_m", voxel)) if v is not None}
    map_cfg = dataclasses.replace(cfg.map, **overrides)
    sequence = open_sequence(seq, data_root=data_root, dataset_cfg=cfg.dataset)
    store = build_map(sequence, kind, out, map_cfg, overwrite=overwrite, max_frames=max_frames)
    print_summary(map_summary(store), _console())


@map_app.command("tile")
def map_tile_cmd(
    global_pcd: Path = typer.Argument(..., help="Global map PCD file."),
    tile_size: float = typer.Option(..., "--tile-size", help="Tile side, m."),
    out: Path = typer.Option(..., "--out", help="Output map directory (written atomically)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing map."),
) -> None:
    """Cut a global PCD map into grid-puzzle tiles named by their centre (Autoware metadata too)."""
    from blockloc.maps.grid_tiles import tile_pcd_file
    from blockloc.maps.tools import map_summary, print_summary

    store = tile_pcd_file(global_pcd, tile_size, out, overwrite=overwrite, progress=True)
    print_summary(map_summary(store), _console())


@map_app.command("info")
def map_info_cmd(
    map_path: str = typer.Argument(..., help="Map directory (or URL)."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object."),
    quick: bool = typer.Option(False, "--quick", help="Skip the overlap ratio (reads every file)."),
) -> None:
    """Blocks/tiles, points, bytes and overlap ratio of a map."""
    from blockloc.maps.store import open_map
    from blockloc.maps.tools import map_summary, print_summary

    summary = map_summary(open_map(map_path), with_overlap=not quick)
    if json_out:
        import json

        typer.echo(json.dumps(summary))
    else:
        print_summary(summary, _console())


@map_app.command("plot")
def map_plot_cmd(
    map_path: str = typer.Argument(..., help="Map directory (or URL)."),
    seq: Optional[str] = typer.Option(None, "--seq", help="Sequence whose trajectory to draw."),
    out: Optional[Path] = typer.Option(None, "--out", help="PNG path (default: <map>.png)."),
    data_root: Optional[str] = typer.Option(None, "--data-root", help="Root of the datasets."),
) -> None:
    """PNG of the blocks/tiles from above, with a sequence's trajectory."""
    from blockloc.maps.store import open_map
    from blockloc.maps.tools import plot_map

    store = open_map(map_path)
    traj = None
    if seq:
        from blockloc.datasets import open_sequence

        s = open_sequence(seq, data_root=data_root)
        traj = s.ground_truth() or s.mapping_poses()
    png = out or Path(str(map_path).rstrip("/") + ".png")
    typer.echo(str(plot_map(store, png, traj)))


@map_app.command("serve")
def map_serve_cmd(
    map_path: Path = typer.Argument(..., help="Map store directory, or a directory of map stores."),
    host: str = typer.Option("127.0.0.1", "--host", help="Address to bind (loopback by default)."),
    port: int = typer.Option(8765, "--port", help="TCP port (0: any free port)."),
) -> None:
    """Serve a map store read-only over HTTP (GET/HEAD, ETag/304, Range) until Ctrl-C."""
    from blockloc.maps.server import serve

    def ready(url: str, stores: list) -> None:
        for s in stores:
            typer.echo(f"serving {url}/{s + '/' if s else ''}", err=True)
        typer.echo("press Ctrl-C to stop", err=True)

    serve(map_path, host, port, on_ready=ready)


# @map-commands (anchor: the maps stage adds its commands above this line)

# ----------------------------------------------------------------------------- init
@app.command("init")
def init_cmd(
    seq: str = typer.Option(..., "--seq", help="Sequence name (sim:small/loc, nclt_2, ...) or path."),
    frame: int = typer.Option(..., "--frame", help="0-based index of the LiDAR scan (time order)."),
    map_path: str = typer.Option(..., "--map", help="Map store directory or URL."),
    pose_hint: Optional[str] = typer.Option(None, "--pose-hint",
                                            help="x,y[,yaw] in the map frame (m, rad); none: whole map."),
    window: Optional[float] = typer.Option(None, "--window", help="Search window side, m (default 40)."),
    yaw_window: Optional[float] = typer.Option(None, "--yaw-window", help="Yaw window around the hint, deg."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object."),
    data_root: Optional[str] = typer.Option(None, "--data-root", help="Root of the datasets."),
    config: Optional[str] = typer.Option(None, "--config", help="Config file or preset name."),
) -> None:
    """Global initialization: the body's pose in the map by branch-and-bound + NDT verification."""
    from blockloc.errors import GlobalInitError
    from blockloc.global_init.command import print_result, run_init, to_json

    res, summ = run_init(seq, frame, map_path, pose_hint, window, yaw_window, config, data_root)
    if json_out:
        typer.echo(to_json(summ))
    else:
        print_result(summ, _console())
    if not res.verified:
        raise GlobalInitError(f"no verified match (best score {res.score:.3f}, fitness {res.fitness:.3f})")


# @init-commands (anchor: the global-init stage adds its command above this line)

# ----------------------------------------------------------------------------- track / demo
def _results_dir(out: Optional[Path], name: str) -> Path:
    import time as _time

    if out is not None:
        return out
    safe = name.replace(":", "_").replace("/", "_").replace("@", "_")
    return Path("results") / f"{safe}_{_time.strftime('%Y%m%d-%H%M%S')}"


def _track_progress(console, label: str):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    prog = Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    console=console, transient=True)
    task = prog.add_task(label, total=None)
    return prog, (lambda done, total: prog.update(task, completed=done, total=total))


def _print_track_summary(console, m: dict, out: Optional[Path]) -> None:
    from rich.table import Table

    def f(v, fmt="{:.3f}"):
        return "-" if v is None else (fmt.format(v) if isinstance(v, float) else str(v))

    t = Table(title=f"blockloc track: {m.get('sequence')} ({m.get('backend')} map)", show_header=False)
    t.add_column(style="bold")
    t.add_column(justify="right")
    init = m.get("init") or {}
    rows = [("frames", f(m.get("frames"))), ("init", f(init.get("mode"))),
            ("init error (m)", f(init.get("error_m"))),
            ("ATE translation RMSE (m)", f(m.get("ate_trans_rmse_m"))),
            ("ATE full RMSE", f(m.get("ate_full_rmse"))), ("ATE rotation RMSE (deg)", f(m.get("ate_rot_rmse_deg"))),
            ("failures / recoveries", f"{m.get('failures')} / {m.get('recoveries')}"),
            ("map switches", f(m.get("switches"))),
            ("update median / p99 (ms)", f"{f(m.get('update_ms_median'), '{:.1f}')} / {f(m.get('update_ms_p99'), '{:.1f}')}"),
            ("peak RSS (MB)", f(m.get("peak_rss_mb"), "{:.0f}"))]
    for k, v in rows:
        if v != "-" or k.startswith("ATE"):
            t.add_row(k, v)
    console.print(t)
    if out is not None:
        console.print(f"results in {out}")


@app.command("track")
def track_cmd(
    seq: str = typer.Option(..., "--seq", help="Sequence: sim:small/loc, nclt_2, m2dgr_1, or a path."),
    map_path: Optional[str] = typer.Option(None, "--map", help="Map store (default: the sequence's map)."),
    backend: Optional[str] = typer.Option(None, "--map-backend", help="block | grid | srt | global."),
    init: Optional[str] = typer.Option(None, "--init", help="gt: start at the first ground-truth pose."),
    init_pose: Optional[str] = typer.Option(None, "--init-pose", help="x,y[,yaw]: global init around a hint."),
    out: Optional[Path] = typer.Option(None, "--out", help="Results directory (default results/<seq>_<time>)."),
    config: Optional[str] = typer.Option(None, "--config", help="Config file or preset name."),
    data_root: Optional[str] = typer.Option(None, "--data-root", help="Root of NCLT / M2DGR data."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", help="Stop after this many frames."),
) -> None:
    """Track a sequence in a prior map (sliding-window IMU + NDT); writes poses, metrics and plots."""
    from blockloc.config import load_config_for_sequence
    from blockloc.errors import TrackingError
    from blockloc.pipeline import LocalizationPipeline, parse_init_pose

    if init not in (None, "gt"):
        raise TrackingError(f"--init {init!r}: expected 'gt' (or use --init-pose x,y[,yaw])")
    if init and init_pose:
        raise TrackingError("--init gt and --init-pose exclude each other")
    cfg = load_config_for_sequence(seq, config)
    mode = "gt" if init else ("pose" if init_pose else "global")
    console = _console()
    out_dir = _results_dir(out, seq)
    prog, cb = _track_progress(console, "tracking")
    pipe = LocalizationPipeline(seq, cfg=cfg, map_path=map_path, backend=backend, init=mode,
                                init_pose=parse_init_pose(init_pose) if init_pose else None, out=out_dir,
                                data_root=data_root, progress=cb, max_frames=max_frames)
    with prog:
        res = pipe.run()
    _print_track_summary(console, res.metrics, res.out_dir)


@app.command("demo")
def demo_cmd(
    out: Optional[Path] = typer.Option(None, "--out", help="Results directory (default results/demo_<time>)."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", help="Track only this many frames."),
) -> None:
    """Simulate the small world, build its block map, localize from a rough hint, track, evaluate."""
    from blockloc.demo import run_demo

    console = _console()
    out_dir = _results_dir(out, "demo")
    prog, cb = _track_progress(console, "tracking")
    say = lambda msg: console.print(f"[bold cyan]demo[/] {msg}")  # noqa: E731
    started = []

    def progress(done, total):
        if not started:
            started.append(prog.start())
        cb(done, total)

    try:
        res = run_demo(out_dir, say=say, progress=progress, max_frames=max_frames)
    finally:
        prog.stop()
    init = res.metrics.get("init") or {}
    if init.get("time_s") is not None:
        say(f"global init: {init.get('error_m', float('nan')):.2f} m from the truth in {init['time_s']:.2f} s")
    _print_track_summary(console, res.metrics, res.out_dir)


# @track-commands (anchor: the tracking stage adds its commands above this line)


def main() -> None:
    """Console-script entry point: run the app, turn known errors into one line."""
    from blockloc.errors import BlocklocError

    try:
        app(standalone_mode=False)
    except BlocklocError as exc:
        if _state["debug"]:
            raise
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except (typer.Exit, SystemExit) as exc:
        code = getattr(exc, "exit_code", getattr(exc, "code", 0))
        sys.exit(code or 0)
    except typer.Abort:
        typer.echo("aborted", err=True)
        sys.exit(130)
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        sys.exit(130)
    except Exception as exc:  # click usage errors and the unexpected
        import click

        if isinstance(exc, click.exceptions.ClickException):
            exc.show()
            sys.exit(exc.exit_code)
        if _state["debug"]:
            raise
        typer.echo(f"error: {type(exc).__name__}: {exc} (rerun with --debug for a traceback)", err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
