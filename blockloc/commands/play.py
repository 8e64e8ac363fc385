"""``blockloc play``: a sequence published as ROS 2 topics over DDS at its recorded pace."""

from __future__ import annotations

import sys

from blockloc.errors import BlocklocError


def play_command(seq: str, rate: float, loop: bool, max_frames: int | None, config: str | None,
                 data_root: str | None, discovery: str | None, points_topic: str, imu_topic: str,
                 pace_file=None) -> None:
    """``pace_file``: where to write the pace's anchor (:func:`write_pace`), or None."""
    from blockloc.commands.common import Interrupted, config_for, interruptible
    from blockloc.app.catalog import SequenceRef
    from blockloc.node.player import Player
    from blockloc.ros2.dds import Dds

    if not rate > 0:
        raise BlocklocError(f"--rate {rate}: expected a positive factor (1.0: recorded pace)")
    if pace_file is not None:
        check_pace_file(pace_file)  # before anything is published
    cfg = config_for(seq, config)
    sequence = SequenceRef.parse(seq).open(data_root=data_root, dataset_cfg=cfg.dataset)
    dds = Dds(discovery)
    try:
        player = Player(dds, sequence, rate=rate, loop=loop, max_frames=max_frames, points_topic=points_topic,
                        imu_topic=imu_topic,
                        on_pace=None if pace_file is None else lambda t, m: write_pace(pace_file, t, m, rate))
        where = "CYCLONEDDS_URI" if dds.user_uri else f"{dds.discovery} discovery"
        print(f"blockloc play: {sequence.info.name} on {points_topic}, {imu_topic}, /tf_static, "
              f"/blockloc/ground_truth at {rate:g}x (DDS domain {dds.domain}, {where})", file=sys.stderr, flush=True)
        with interruptible() as stop:
            stats = player.run(stop)
        summary = f"{stats.scans} scans, {stats.imu} IMU samples, {stats.ground_truth} ground-truth poses published"
        if stop():
            raise Interrupted(f"play stopped: {summary}", stop.exit_code)
        print(summary, file=sys.stderr)
    finally:
        dds.close()


def check_pace_file(path) -> None:
    """Before any work: ``--pace-file`` names a file play may write (BlocklocError, one line naming
    the option, otherwise): not a directory, its directory writable, and no file there that is not
    a pace file play wrote (a user's notes or figure is never replaced)."""
    from pathlib import Path

    from blockloc.outdir import check_file_replaceable, check_output_parent, check_writable

    path = Path(path)
    if path.is_dir():
        raise BlocklocError(f"--pace-file {path}: is a directory, expected a file name (e.g. pace.json)")
    check_output_parent(path, "--pace-file")
    check_writable(path, "--pace-file")
    check_file_replaceable(path, "--pace-file", is_pace_file, "the pace files")


def is_pace_file(path) -> bool:
    """True for a file :func:`write_pace` wrote (a JSON object of exactly its fields)."""
    import json
    from pathlib import Path

    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return (isinstance(doc, dict) and set(doc) == {"stamp", "monotonic", "rate", "clock"}
            and doc["clock"] == "CLOCK_MONOTONIC")


def write_pace(path, stamp: float, monotonic_s: float, rate: float) -> None:
    """The pace's anchor as JSON: a message with stamp ``t`` s is due at CLOCK_MONOTONIC second
    ``monotonic + (t - stamp) / rate`` (the same clock for every process of this machine); a scan
    is published when its sweep ends (its stamp + its last point's time offset). With --loop,
    rewritten at every start."""
    import json

    from blockloc.fileio import atomic_write_text

    atomic_write_text(path, json.dumps({"stamp": stamp, "monotonic": monotonic_s, "rate": rate,
                                        "clock": "CLOCK_MONOTONIC"}) + "\n")
