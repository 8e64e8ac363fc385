"""The ``blockloc`` command line: a thin typer app.

Options are declared here; every command body is in :mod:`blockloc.commands` and imported lazily,
so ``blockloc --help`` stays instant. Errors end in one line and a non-zero exit, without a
traceback unless ``--debug``: a BlocklocError (bad input, missing data, no match) exits 2 with
``error: ...``; a usage error names the option and exits 2; Ctrl-C / SIGTERM exit 130 / 143.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import List, Optional

from blockloc.threads import limit_blas_threads

limit_blas_threads()  # before any command imports numpy

import typer  # noqa: E402

from blockloc import __version__  # noqa: E402

app = typer.Typer(
    name="blockloc",
    help="Localize a LiDAR + IMU robot in a large prior map, holding only the blocks it needs.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
map_app = typer.Typer(help="Build, tile, inspect and serve map stores.", no_args_is_help=True,
                      rich_markup_mode=None)
app.add_typer(map_app, name="map")
export_app = typer.Typer(help="Write a sequence in another tool's layout.", no_args_is_help=True,
                         rich_markup_mode=None)
app.add_typer(export_app, name="export")

_state = {"debug": False}
log = logging.getLogger("blockloc")

# Option metavars shown in --help and usage lines.
SEQ = "SEQ"
MAP = "MAP"
DIR = "DIR"
FILE = "FILE"
SET_HELP = "Override one setting, e.g. registration.method=vgicp (repeatable)."


def _version(value: bool) -> None:
    if value:
        typer.echo(f"blockloc {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks and debug logs (anywhere on the command line)."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Info-level logs."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    _state["debug"] = debug
    level = logging.DEBUG if debug else (logging.INFO if verbose else logging.WARNING)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


# ----------------------------------------------------------------------------- eval
@app.command("eval")
def eval_cmd(
    gt: Path = typer.Option(..., "--gt", metavar=FILE, help="Ground truth: TUM, KITTI or NCLT groundtruth csv."),
    est: Path = typer.Option(..., "--est", metavar=FILE, help="Estimate: TUM or KITTI."),
    align: bool = typer.Option(False, "--align", help="Umeyama SE(3) alignment before ATE."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object."),
    plot: Optional[Path] = typer.Option(None, "--plot", metavar=DIR, help="Directory for PNG plots."),
    max_time_diff: float = typer.Option(0.02, "--max-time-diff", metavar="S", min=0.0,
                                        help="Association tolerance, s."),
    interpolate: bool = typer.Option(False, "--interpolate",
                                     help="Interpolate ground truth to the estimate's stamps (else nearest)."),
    rpe_deltas: str = typer.Option("1,10,100", "--rpe-deltas", metavar="M,M,...",
                                   help="RPE path-length deltas, m, comma separated."),
) -> None:
    """ATE (translation and full xyzrpy), rotation RMSE and RPE of an estimate against ground truth."""
    from blockloc.commands.eval import eval_command

    if plot is not None:
        from blockloc.fileio import check_output_dir

        check_output_dir(plot, "--plot")  # before any work
    eval_command(gt, est, align, json_out, plot, max_time_diff, interpolate, rpe_deltas)


# ----------------------------------------------------------------------------- sim
@app.command("sim")
def sim_cmd(
    preset: str = typer.Option("small", "--preset", metavar="NAME", help="World preset: small | campus | city | tiny."),
    seed: int = typer.Option(1, "--seed", metavar="N", min=0, help="World and noise seed (same seed, same bytes)."),
    out: Path = typer.Option(..., "--out", metavar=DIR, help="Output directory (replaced when complete)."),
    fmt: str = typer.Option("nclt", "--format", metavar="FORMAT", help="nclt | rosbag1 | rosbag2."),
    azimuth_steps: Optional[int] = typer.Option(None, "--azimuth-steps", metavar="N", min=8,
                                                help="Columns per revolution (preset default)."),
    months: str = typer.Option("", "--months", metavar="3,12",
                               help="Also write the changed world's later days: 3 -> loc_m3, 12 -> loc_m12 and "
                                    "map_m12, with point labels and changes.json (nclt format)."),
) -> None:
    """Simulate a world and write its sessions (map, loc[, loc2]) with HDL-32E scans, IMU and ground truth."""
    from blockloc.commands.sim import sim_command

    sim_command(preset, seed, out, fmt, azimuth_steps, months)


@export_app.command("dynamicmap")
def export_dynamicmap_cmd(
    seq: str = typer.Option(..., "--seq", metavar=SEQ,
                            help="Sequence: name (sim:small/map_m12@2) or path (a session blockloc sim wrote)."),
    out: Path = typer.Option(..., "--out", metavar=DIR, help="Output folder (pcd/, gt_cloud.pcd; replaced when complete)."),
    poses: Optional[Path] = typer.Option(None, "--poses", metavar=FILE,
                                         help="Trajectory T_map_body (TUM, KITTI, NCLT csv; default: the ground truth)."),
    start: int = typer.Option(0, "--start", metavar="N", min=0, help="First frame."),
    frames: Optional[int] = typer.Option(None, "--frames", metavar="N", min=1, help="Scans to write (default: to the end)."),
    step: int = typer.Option(1, "--step", metavar="N", min=1, help="Every N-th frame."),
    min_range: float = typer.Option(2.5, "--min-range", metavar="M", min=0.0, help="Leave out points nearer (m)."),
    max_range: float = typer.Option(50.0, "--max-range", metavar="M", min=0.1, help="Leave out points further (m)."),
    data_root: Optional[str] = typer.Option(None, "--data-root", metavar=DIR, help="Root of the datasets."),
) -> None:
    """Write scans in the DynamicMap Benchmark layout (world frame, sensor pose in VIEWPOINT) with
    the labelled gt_cloud.pcd when the sequence has labels (the simulator's changed days)."""
    from blockloc.commands.export import dynamicmap_command

    dynamicmap_command(seq, out, poses, start, frames, step, min_range, max_range, data_root)


# ----------------------------------------------------------------------------- map
@map_app.command("build")
def map_build_cmd(
    seq: Optional[List[str]] = typer.Option(
        None, "--seq", metavar=SEQ,
        help="Mapping sequence: name (nclt_2, sim:small/map) or path; NAME[START:STOP] maps frames "
             "START..STOP-1. Repeat to merge drives sharing one map frame (any order: they are "
             "taken by first keyframe stamp, then name)."),
    poses: Optional[List[str]] = typer.Option(
        None, "--poses", metavar=FILE,
        help="Mapping trajectory (TUM, KITTI): T_map_body at the scans' stamps. With several --seq: "
             "once per --seq, same order ('-': that sequence's own poses)."),
    from_pcd: Optional[Path] = typer.Option(None, "--from-pcd", metavar=FILE,
                                            help="Build from a global map PCD and --poses instead of --seq."),
    sensor_range: float = typer.Option(60.0, "--sensor-range", metavar="M", min=0.0,
                                       help="With --from-pcd: what a keyframe sees, m."),
    gravity: Optional[str] = typer.Option(None, "--gravity", metavar="down|up|X,Y,Z",
                                          help="With --from-pcd: gravity in the map frame, for the place "
                                               "index (default up: the map's z axis points up)."),
    kind: str = typer.Option("block", "--kind", metavar="KIND", help="block | grid"),
    out: str = typer.Option(..., "--out", metavar=DIR, help="Output map directory or s3:// URL (written atomically)."),
    config: Optional[str] = typer.Option(None, "--config", metavar=FILE, help="Config file or preset name."),
    data_root: Optional[str] = typer.Option(None, "--data-root", metavar=DIR, help="Root of the datasets."),
    block_size: Optional[float] = typer.Option(None, "--block-size", metavar="M", min=0.0, help="Block size S, m."),
    tile_size: Optional[float] = typer.Option(None, "--tile-size", metavar="M", min=0.0, help="Grid tile side, m."),
    voxel: Optional[float] = typer.Option(None, "--voxel", metavar="M", min=0.0,
                                          help="Voxel filter size, m (0: no filter)."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", metavar="N", min=1,
                                             help="Use only the first N frames of each drive."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing map store at --out (only a map store)."),
    cluster: Optional[str] = typer.Option(None, "--cluster", metavar="local:N|tcp://HOST:PORT",
                                          help="Build on Dask: local:N starts N worker processes here; "
                                               "tcp://HOST:PORT uses a running scheduler. Default: serial, same bytes."),
    calibrate_mounting: Optional[bool] = typer.Option(
        None, "--calibrate-mounting/--nominal-mounting",
        help="Estimate the LiDAR mounting (T_body_lidar) from the drives' scans first and build "
             "with it; the estimate is logged and kept in the manifest. Default (map.calibrate_mounting: "
             "true): drives whose poses are the body's, a failed estimate keeps the nominal mounting; "
             "--calibrate-mounting: every drive, a failed estimate is an error; --nominal-mounting: none."),
    refine_poses: Optional[bool] = typer.Option(
        None, "--refine-poses/--no-refine-poses",
        help="Refine each drive's keyframe poses against its own scans (neighbours and revisits, "
             "a pose graph) before the map is built; a drive without revisits is left as it came. "
             "Default (map.refine_poses: true): the drives whose mounting the build estimated (poses "
             "of the body); --refine-poses: every drive; --no-refine-poses: none."),
    remove_dynamic: Optional[bool] = typer.Option(
        None, "--remove-dynamic/--keep-dynamic",
        help="Leave moving objects (pedestrians, passing cars: space the drive's own scans see "
             "through around each keyframe) out of the map. Default: map.remove_dynamic (false)."),
) -> None:
    """Build a block map or grid tiles from mapping sequences and their poses (or a global PCD),
    serial or on a Dask cluster."""
    from blockloc.commands.map import build_command

    build_command(seq, kind, out, config, data_root, block_size, tile_size, voxel, max_frames, overwrite,
                  poses=poses, from_pcd=from_pcd, sensor_range_m=sensor_range, cluster=cluster,
                  gravity=gravity, calibrate_mounting=calibrate_mounting, refine_poses=refine_poses,
                  remove_dynamic=remove_dynamic)


@map_app.command("tile")
def map_tile_cmd(
    global_pcd: Path = typer.Argument(..., metavar="GLOBAL_PCD", help="Global map PCD file."),
    tile_size: float = typer.Option(..., "--tile-size", metavar="M", min=0.0, help="Tile side, m."),
    out: Path = typer.Option(..., "--out", metavar=DIR, help="Output map directory (written atomically)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing map store at --out (only a map store)."),
) -> None:
    """Cut a global PCD map into grid-puzzle tiles named by their centre (Autoware metadata too)."""
    from blockloc.commands.map import tile_command

    tile_command(global_pcd, tile_size, out, overwrite)


@map_app.command("index")
def map_index_cmd(
    map_path: str = typer.Argument(..., metavar=MAP, help="Local map directory."),
    gravity: Optional[str] = typer.Option(None, "--gravity", metavar="down|up|X,Y,Z",
                                          help="Gravity in the map frame (default: the mapping sequence's)."),
    config: Optional[str] = typer.Option(None, "--config", metavar=FILE, help="Config file or preset name."),
    precompute: bool = typer.Option(False, "--precompute",
                                    help="Also fill the global-init caches of every block/tile (pyramids, sorted "
                                         "points, refinement statistics: ~50 bytes a point under the cache "
                                         "directory), so that no relocalization of a session or node with the "
                                         "same --config builds them."),
) -> None:
    """Build (or rebuild) the place index of a map: no-hint relocalization."""
    from blockloc.commands.map import index_command

    index_command(map_path, gravity, config, precompute)


@map_app.command("info")
def map_info_cmd(
    map_path: str = typer.Argument(..., metavar=MAP, help="Map directory (or URL)."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object."),
    quick: bool = typer.Option(False, "--quick", help="Skip the overlap ratio (reads every file)."),
) -> None:
    """Blocks/tiles, points, bytes and overlap ratio of a map."""
    from blockloc.commands.map import info_command

    info_command(map_path, json_out, quick)


@map_app.command("plot")
def map_plot_cmd(
    map_path: str = typer.Argument(..., metavar=MAP, help="Map directory (or URL)."),
    seq: Optional[str] = typer.Option(None, "--seq", metavar=SEQ, help="Sequence whose trajectory to draw."),
    out: Optional[Path] = typer.Option(None, "--out", metavar=FILE, help="PNG path (default: <map>.png)."),
    data_root: Optional[str] = typer.Option(None, "--data-root", metavar=DIR, help="Root of the datasets."),
) -> None:
    """PNG of the blocks/tiles from above, with a sequence's trajectory."""
    from blockloc.commands.map import plot_command

    plot_command(map_path, seq, out, data_root)


@map_app.command("serve")
def map_serve_cmd(
    map_path: Path = typer.Argument(..., metavar=MAP, help="Map store directory, or a directory of map stores."),
    host: str = typer.Option("127.0.0.1", "--host", metavar="ADDRESS", help="Address to bind (loopback by default)."),
    port: int = typer.Option(8765, "--port", metavar="PORT", min=0, max=65535, help="TCP port (0: any free port)."),
) -> None:
    """Serve a map store read-only over HTTP (GET/HEAD, ETag/304, Range) until Ctrl-C."""
    from blockloc.commands.map import serve_command

    serve_command(map_path, host, port)


@map_app.command("changes")
def map_changes_cmd(
    map_path: str = typer.Option(..., "--map", metavar=MAP, help="Block map store the run tracked in."),
    run: Path = typer.Option(..., "--run", metavar=DIR, help="Results folder of a blockloc track run."),
    seq: Optional[str] = typer.Option(None, "--seq", metavar=SEQ,
                                      help="The run's sequence (default: the one its metrics.json names)."),
    out: Optional[Path] = typer.Option(None, "--out", metavar=FILE, help="Report (default: RUN/changes.json)."),
    data_root: Optional[str] = typer.Option(None, "--data-root", metavar=DIR, help="Root of the datasets."),
    stride: int = typer.Option(1, "--stride", metavar="N", min=1, help="Use every N-th trusted frame."),
) -> None:
    """What changed since the map was made, per block, from a run's verified frames (changes.json)."""
    from blockloc.commands.lifelong import changes_command

    changes_command(map_path, run, seq, out, data_root, stride)


@map_app.command("update")
def map_update_cmd(
    map_path: str = typer.Argument(..., metavar=MAP, help="Local block map store."),
    runs: List[Path] = typer.Option(..., "--run", metavar=DIR, help="Results folder of a track run (repeatable)."),
    seqs: Optional[List[str]] = typer.Option(None, "--seq", metavar=SEQ,
                                             help="Each run's sequence, once per --run (default: from the runs)."),
    out: Optional[Path] = typer.Option(None, "--out", metavar=DIR,
                                       help="Write the updated map here (default: a new version of MAP, in place)."),
    data_root: Optional[str] = typer.Option(None, "--data-root", metavar=DIR, help="Root of the datasets."),
    stride: int = typer.Option(1, "--stride", metavar="N", min=1, help="Use every N-th trusted frame."),
    strong_scans: int = typer.Option(15, "--strong-scans", metavar="N", min=1,
                                     help="A change one run saw in fewer scans waits for a second run."),
    min_runs: int = typer.Option(2, "--min-runs", metavar="N", min=1, help="Runs that confirm a change on their own."),
) -> None:
    """Rebuild the blocks with confirmed changes from verified runs, as a new map version."""
    from blockloc.commands.lifelong import update_command

    update_command(map_path, runs, seqs, out, data_root, stride, strong_scans, min_runs)


@map_app.command("rollback")
def map_rollback_cmd(
    map_path: str = typer.Argument(..., metavar=MAP, help="Local block map store."),
    to: int = typer.Option(..., "--to", metavar="V", min=1, help="Version to make current (see map info)."),
) -> None:
    """Make an earlier (or later) version of a map current again (atomic; nothing is deleted)."""
    from blockloc.commands.lifelong import rollback_command

    rollback_command(map_path, to)


# ----------------------------------------------------------------------------- init
@app.command("init")
def init_cmd(
    seq: str = typer.Option(..., "--seq", metavar=SEQ, help="Sequence name (sim:small/loc, nclt_2, ...) or path."),
    frame: int = typer.Option(..., "--frame", metavar="N", min=0, help="0-based index of the LiDAR scan (time order)."),
    map_path: str = typer.Option(..., "--map", metavar=MAP, help="Map store directory or URL."),
    pose_hint: Optional[str] = typer.Option(None, "--pose-hint", metavar="X,Y[,YAW]",
                                            help="x,y[,yaw] in the map frame (m, rad); none: whole map."),
    window: Optional[float] = typer.Option(None, "--window", metavar="M", min=0.0,
                                           help="Search window side, m (default 40)."),
    yaw_window: Optional[float] = typer.Option(None, "--yaw-window", metavar="DEG", min=0.0, max=360.0,
                                               help="Yaw window around the hint, deg."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object."),
    data_root: Optional[str] = typer.Option(None, "--data-root", metavar=DIR, help="Root of the datasets."),
    config: Optional[str] = typer.Option(None, "--config", metavar=FILE, help="Config file or preset name."),
    poses: Optional[Path] = typer.Option(None, "--poses", metavar=FILE,
                                         help="Reference trajectory (TUM, KITTI): reports the error."),
    sets: Optional[list[str]] = typer.Option(None, "--set", metavar="SECTION.KEY=VALUE", help=SET_HELP),
) -> None:
    """Global initialization: the body's pose in the map by branch-and-bound + verification."""
    from blockloc.commands.init import init_command

    init_command(seq, frame, map_path, pose_hint, window, yaw_window, json_out, data_root, config, poses, sets)


# ----------------------------------------------------------------------------- track / demo
@app.command("track")
def track_cmd(
    seq: str = typer.Option(..., "--seq", metavar=SEQ, help="Sequence: sim:small/loc, nclt_2, m2dgr_1, or a path."),
    map_path: Optional[str] = typer.Option(None, "--map", metavar=MAP, help="Map store (default: the sequence's map)."),
    backend: Optional[str] = typer.Option(None, "--map-backend", metavar="BACKEND", help="block | grid | srt | global."),
    init: Optional[str] = typer.Option(None, "--init", metavar="gt", help="gt: start at the first ground-truth pose."),
    init_pose: Optional[str] = typer.Option(None, "--init-pose", metavar="X,Y[,YAW]",
                                            help="x,y[,yaw]: global init around a hint."),
    out: Optional[Path] = typer.Option(None, "--out", metavar=DIR, help="Results directory (default results/<seq>_<time>)."),
    config: Optional[str] = typer.Option(None, "--config", metavar=FILE, help="Config file or preset name."),
    data_root: Optional[str] = typer.Option(None, "--data-root", metavar=DIR, help="Root of NCLT / M2DGR data."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", metavar="N", min=1,
                                             help="Stop after this many frames."),
    lidar_topic: Optional[str] = typer.Option(None, "--lidar-topic", metavar="TOPIC",
                                              help="ROS bags: the PointCloud2 topic (default from the config)."),
    imu_topic: Optional[str] = typer.Option(None, "--imu-topic", metavar="TOPIC",
                                            help="ROS bags: the Imu topic (default from the config)."),
    poses: Optional[Path] = typer.Option(None, "--poses", metavar=FILE,
                                         help="Reference trajectory (TUM, KITTI): ground truth for --init gt and the metrics."),
    no_imu: bool = typer.Option(False, "--no-imu", help="Ignore the IMU: LiDAR-only tracking (a motion prior)."),
    sets: Optional[list[str]] = typer.Option(None, "--set", metavar="SECTION.KEY=VALUE", help=SET_HELP),
    record: Optional[Path] = typer.Option(None, "--record", metavar="FILE",
                                          help="MCAP recording for Foxglove / ROS 2 (default: run.mcap in --out)."),
    no_record: bool = typer.Option(False, "--no-record", help="Write no MCAP recording."),
    live: bool = typer.Option(False, "--live", help="Serve the run live to Foxglove over WebSocket."),
    host: str = typer.Option("127.0.0.1", "--host", metavar="ADDRESS", help="--live: address to bind (loopback)."),
    port: int = typer.Option(8765, "--port", metavar="PORT", help="--live: TCP port (0: any free port)."),
    detect_changes: bool = typer.Option(False, "--detect-changes",
                                        help="Then find what changed in the (block) map from the run's verified "
                                             "frames: changes.json, drawn into run.mcap and report.html."),
    changes_stride: int = typer.Option(1, "--changes-stride", metavar="N", min=1,
                                       help="--detect-changes: use every N-th trusted frame."),
) -> None:
    """Track a sequence in a prior map (sliding-window IMU + scan-to-map factors); writes poses, metrics,
    plots, an MCAP recording and report.html."""
    from blockloc.commands.track import track_command

    track_command(seq, map_path, backend, init, init_pose, out, config, data_root, max_frames,
                  lidar_topic, imu_topic, poses=poses, sets=(sets or []) + (["tracking.use_imu=false"] if no_imu else []),
                  record=not no_record, record_path=record, live=live, host=host, port=port,
                  detect_changes=detect_changes, changes_stride=changes_stride)


@app.command("demo")
def demo_cmd(
    out: Optional[Path] = typer.Option(None, "--out", metavar=DIR, help="Results directory (default results/demo_<time>)."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", metavar="N", min=1,
                                             help="Track only this many frames."),
    no_record: bool = typer.Option(False, "--no-record", help="Write no MCAP recording."),
) -> None:
    """Simulate the small world, build its block map, localize from a rough hint, track, evaluate;
    writes the results folder with report.html and a Foxglove recording."""
    from blockloc.commands.demo import demo_command

    demo_command(out, max_frames, record=not no_record)


# ----------------------------------------------------------------------------- live: ROS 2 over DDS
@app.command("node")
def node_cmd(
    map_path: str = typer.Option(..., "--map", metavar=MAP, help="Map store directory or URL."),
    backend: Optional[str] = typer.Option(None, "--map-backend", metavar="BACKEND", help="block | grid | srt | global."),
    config: Optional[str] = typer.Option(None, "--config", metavar=FILE, help="Config file or preset name."),
    init_pose: Optional[str] = typer.Option(None, "--init-pose", metavar="X,Y[,YAW]",
                                            help="x,y[,yaw]: global init around a hint (default: the whole map)."),
    points_topic: str = typer.Option("/points", "--points-topic", metavar="TOPIC", help="sensor_msgs/PointCloud2 in."),
    imu_topic: str = typer.Option("/imu/data", "--imu-topic", metavar="TOPIC", help="sensor_msgs/Imu in (none: LiDAR-only)."),
    out: Optional[Path] = typer.Option(None, "--out", metavar=DIR, help="Also write a results folder as track does."),
    discovery: Optional[str] = typer.Option(None, "--discovery", metavar="localhost|subnet",
                                            help="DDS discovery range (default localhost, or ROS_AUTOMATIC_DISCOVERY_RANGE)."),
    gravity: Optional[str] = typer.Option(None, "--gravity", metavar="down|up|X,Y,Z",
                                          help="Gravity in the map frame (default: the map's place index's)."),
    no_data_timeout: float = typer.Option(5.0, "--no-data-timeout", metavar="S", min=0.0,
                                          help="Seconds without a scan before the diagnostics say 'no data'."),
    map_frame: str = typer.Option("map", "--map-frame", metavar="FRAME", help="TF name of the map frame."),
    odom_frame: str = typer.Option("odom", "--odom-frame", metavar="FRAME", help="TF name of the odometry frame."),
    base_frame: str = typer.Option("base_link", "--base-frame", metavar="FRAME", help="TF name of the body frame."),
    sets: Optional[list[str]] = typer.Option(None, "--set", metavar="SECTION.KEY=VALUE", help=SET_HELP),
    detect_changes: bool = typer.Option(False, "--detect-changes",
                                        help="Find what changed in the (block) map from the verified scans as they "
                                             "come (needs --out): changes.json written at shutdown."),
    changes_stride: int = typer.Option(1, "--changes-stride", metavar="N", min=1,
                                       help="--detect-changes: use every N-th trusted frame."),
) -> None:
    """Localize live: a ROS 2 node over DDS (PointCloud2 + Imu in; pose, odometry, /tf, diagnostics
    and the local map out) until Ctrl-C."""
    from blockloc.commands.node import node_command

    node_command(map_path, config, init_pose, points_topic, imu_topic, out, discovery, gravity, sets or [],
                 no_data_timeout_s=no_data_timeout, frames={"map": map_frame, "odom": odom_frame, "base": base_frame},
                 detect_changes=detect_changes, changes_stride=changes_stride, backend=backend)


@app.command("play")
def play_cmd(
    seq: str = typer.Option(..., "--seq", metavar=SEQ, help="Sequence: sim:small/loc, nclt_2, a bag, a scan folder."),
    rate: float = typer.Option(1.0, "--rate", metavar="X", help="Pace: 1.0 as recorded, 3.0 three times faster."),
    loop: bool = typer.Option(False, "--loop", help="Start over at the end (the stamps jump back)."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", metavar="N", min=1, help="Play only this many scans."),
    config: Optional[str] = typer.Option(None, "--config", metavar=FILE, help="Config file or preset name."),
    data_root: Optional[str] = typer.Option(None, "--data-root", metavar=DIR, help="Root of the datasets."),
    discovery: Optional[str] = typer.Option(None, "--discovery", metavar="localhost|subnet",
                                            help="DDS discovery range (default localhost)."),
    points_topic: str = typer.Option("/points", "--points-topic", metavar="TOPIC", help="PointCloud2 out."),
    imu_topic: str = typer.Option("/imu/data", "--imu-topic", metavar="TOPIC", help="Imu out."),
    pace_file: Optional[Path] = typer.Option(
        None, "--pace-file", metavar=FILE,
        help="Write where the pace starts (JSON: a stamp, the CLOCK_MONOTONIC second it was due, the rate), "
             "so a listener on this machine can tell when each stamp was due."),
) -> None:
    """Publish a sequence as ROS 2 topics over DDS at its recorded pace (clouds, IMU, /tf_static, ground truth)."""
    from blockloc.commands.play import play_command

    play_command(seq, rate, loop, max_frames, config, data_root, discovery, points_topic, imu_topic, pace_file)


@app.command("view")
def view_cmd(
    run_dir: Path = typer.Argument(..., metavar=DIR, help="A results folder (or one .mcap file)."),
) -> None:
    """How to look at a run: the recording and layout in Foxglove, the live server, report.html."""
    from blockloc.viz.layout import view_instructions

    print(view_instructions(run_dir))


def _click_exception_modules() -> list:
    """The exception modules of the click typer runs on: typer >= 0.29 vendors its own
    (``typer._click``), older ones use click itself; both are handled."""
    mods = [sys.modules[typer.BadParameter.__module__]]
    try:
        import click
    except ImportError:  # typer >= 0.29 does not need click
        return mods
    if click.exceptions not in mods:
        mods.append(click.exceptions)
    return mods


def _classes(name: str) -> tuple:
    return tuple(getattr(m, name) for m in _click_exception_modules() if hasattr(m, name))


def _usage_error(exc) -> str:
    """One line for a click usage error, naming the option (or argument) it concerns."""
    param = getattr(exc, "param", None)
    name = None
    if param is not None and getattr(param, "param_type_name", None) == "argument":
        name = getattr(param, "metavar", None) or getattr(param, "name", None)  # as --help shows it
    elif param is not None:
        name = "/".join(getattr(param, "opts", []) or []) or getattr(param, "human_readable_name", None)
    if isinstance(exc, _classes("MissingParameter")):
        return f"missing {name or 'a required value'}" + (f" ({param.help})" if getattr(param, "help", None) else "")
    if isinstance(exc, _classes("NoSuchOption")):
        msg = f"no such option {exc.option_name}"
        if exc.possibilities:
            msg += f" (did you mean {', '.join(sorted(exc.possibilities))}?)"
        return msg
    message = exc.format_message() if hasattr(exc, "format_message") else str(exc)
    if name and name not in message:
        return f"{name}: {message}"
    return message


def _end_progress_bars() -> None:
    """Close the tqdm bars an error left open (blockloc draws none; a library may) (a bar redraws with \\r and ends no line), so the
    message starts a line of its own and no bar is redrawn after it."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ()) or ()):
        try:
            bar.close()
        except Exception:  # noqa: BLE001 - a bar that cannot close must not hide the message
            pass


def _say(message: str) -> None:
    _end_progress_bars()
    typer.echo(message, err=True)


def _debug_first(args: list[str]) -> list[str]:
    """``args`` with every ``--debug`` before a ``--`` moved to the front, where the group's option
    is parsed: ``blockloc map changes ... --debug`` (as the error line's hint suggests) works as
    ``blockloc --debug map changes ...`` does. No command has an option or value of that name."""
    end = args.index("--") if "--" in args else len(args)
    if "--debug" not in args[:end]:
        return args
    return ["--debug"] + [a for a in args[:end] if a != "--debug"] + args[end:]


def main() -> None:
    """Console-script entry point: run the app, turn known errors into one line.

    SIGINT and SIGTERM raise ``Stopped`` (blockloc.commands.common), which unwinds the command
    (temp directories removed, a tracking run's partial results kept) and exits 130 / 143."""
    from blockloc.commands.common import RECEIVED, Interrupted, Stopped, install_signal_handlers
    from blockloc.errors import BlocklocError

    install_signal_handlers()
    try:
        try:
            code = app(args=_debug_first(sys.argv[1:]), standalone_mode=False)
        except (Exception, KeyboardInterrupt):
            if RECEIVED:  # the Stopped a signal raised became another error where it landed
                raise Stopped(RECEIVED[-1]) from None
            raise
        if RECEIVED:  # ... or was swallowed, and the command went on to its end
            raise Stopped(RECEIVED[-1])
        # typer >= 0.29 without standalone mode returns the code of an Exit (and turns a
        # KeyboardInterrupt into Exit(130)) instead of exiting with it
        if isinstance(code, int) and code:
            if code == 130:
                _say("interrupted")
            sys.exit(code)
    except Stopped as exc:
        _say(f"interrupted ({exc})")
        sys.exit(exc.exit_code)
    except Interrupted as exc:  # stopped after saving what was computed: the message says where
        _say(str(exc))
        sys.exit(exc.exit_code)
    except BlocklocError as exc:
        if _state["debug"]:
            raise
        _say(f"error: {exc}")
        sys.exit(getattr(exc, "exit_code", 2))
    except _classes("UsageError") as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":  # a group without its command: its help
            typer.echo(exc.format_message(), err=True)
            sys.exit(2)
        ctx = getattr(exc, "ctx", None)
        where = ctx.command_path if ctx is not None else "blockloc"
        _say(f"error: {_usage_error(exc)} (see '{where} --help')")
        sys.exit(2)
    except _classes("Abort") + (KeyboardInterrupt,):
        _say("interrupted")
        sys.exit(130)
    except _classes("Exit") + (typer.Exit,) as exc:
        sys.exit(getattr(exc, "exit_code", 0) or 0)
    except _classes("ClickException") as exc:
        _say(f"error: {exc.format_message()}")
        sys.exit(getattr(exc, "exit_code", 1))
    except SystemExit:
        raise
    except Exception as exc:  # the unexpected: one line, the traceback with --debug
        if _state["debug"]:
            raise
        _say(f"error: {type(exc).__name__}: {exc} (rerun with --debug for a traceback)")
        sys.exit(1)
    finally:  # the output locks this command took (blockloc.outdir.claim_output); a command that
        # took none never loaded outdir, and --help stays as light as it was
        outdir = sys.modules.get("blockloc.outdir")
        if outdir is not None:
            outdir.release_outputs()


if __name__ == "__main__":
    main()
