"""Write a simulated dataset: every session of a preset, as NCLT-layout directories or ROS bags.

Layout of ``out`` (NCLT, the default)::

    out/sim.json        preset, seed, sessions, frame conventions (no timestamps: reproducible)
    out/map/            the mapping drive: velodyne_sync/, velodyne_hits.bin, ms25.csv,
                        groundtruth_<date>.csv, slam_poses_<date>.csv (offline-SLAM poses)
    out/loc/            a localization drive on another day (campus: also out/loc2/)
    out/loc_m3/ ...     with ``months``: the changing world's later days, each with
                        point_labels/<utime>.npy and changes.json (``blockloc.sim.changes``)

``--format rosbag1`` writes ``out/<session>.bag``, ``rosbag2`` a bag directory ``out/<session>/``
(sqlite3), each with ``out/<session>_groundtruth.csv`` (NCLT csv, T_map_body; mapping drives
also ``out/<session>_slam_poses.csv``) and a sidecar ``out/<session>[.bag].blockloc.json``
holding the nominal extrinsics, gravity and those file names, which
``blockloc.datasets.rosbag.RosbagSequence`` reads: ``map build``, ``init`` and ``track`` work on
the bags as on the NCLT layout.

The whole dataset is written into a temp directory beside ``out`` and renamed at the end.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from blockloc.errors import SimError
from blockloc.fileio import replace_dir
from blockloc.sim.parallel import FramePool, default_workers
from blockloc.sim.presets import get_preset
from blockloc.sim.stream import SimSequence

log = logging.getLogger(__name__)

FORMATS = ("nclt", "rosbag1", "rosbag2")
Progress = Callable[[str, int, int], None]  # (session, frames done, frames total)


def _counting(frames, seq: SimSequence, progress: Progress | None):
    total = len(seq)
    for k, f in enumerate(frames):
        yield f
        if progress is not None:
            progress(seq.session, k + 1, total)


def generate_dataset(preset: str, seed: int, out: Path, fmt: str = "nclt", *,
                     progress: Progress | None = None, sessions: tuple[str, ...] | None = None,
                     max_frames: int | None = None, months: tuple[int, ...] = (), workers: int | None = None,
                     **overrides) -> Path:
    """Simulate every session of ``preset`` with ``seed`` and write them under ``out``.

    fmt: nclt | rosbag1 | rosbag2. progress: called after each frame. sessions: a subset (default
    all). max_frames: cap per session (tests). months: also write the changing world's later days
    (``blockloc.sim.changes``: 3 -> loc_m3, 12 -> loc_m12 and map_m12; NCLT format only), each
    with ``point_labels/`` and ``changes.json``, rendered in this process. workers: processes
    rendering the preset's own sessions while this one writes (0: render here; None:
    :func:`blockloc.sim.parallel.default_workers`); the bytes written do not depend on it.
    overrides: preset fields (``azimuth_steps``...).
    Returns ``out``. An existing ``out`` is replaced only when the new dataset is complete.
    """
    from blockloc.datasets.nclt import NCLT_GRAVITY_MAP, NCLT_T_BODY_IMU, NCLT_T_BODY_LIDAR, write_session

    if fmt not in FORMATS:
        raise SimError(f"sim format {fmt!r}: expected one of {', '.join(FORMATS)}")
    p = get_preset(preset, **overrides)
    from blockloc.sim import changes

    later = changes.sessions_for_months(months)
    if later and fmt != "nclt":
        raise SimError(f"--months with --format {fmt}: the changed days are written in the nclt format only")
    names = tuple(dict.fromkeys((tuple(sessions) if sessions else p.sessions) + later))  # each once
    for s in names:
        if s not in p.sessions + later:
            raise SimError(f"sim session {s!r}: preset {p.name} has {', '.join(p.sessions)}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    seqs = {s: SimSequence(p, s, seed) if s in p.sessions else changes.ChangedSimSequence(p, s, seed)
            for s in names}
    counts = {s: len(q) if max_frames is None else min(len(q), int(max_frames)) for s, q in seqs.items()}
    if workers is None:
        workers = default_workers(sum(counts.values()))
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    pool = FramePool(workers) if workers > 0 else None
    try:
        own = [s for s in names if s in p.sessions]
        # nclt: the workers write the frames' bytes beside the sessions' files-to-be (the same
        # filesystem: write_session moves them in), none of them crosses the pipe
        scratch = [tmp / f".{s}-frames" for s in own] if fmt == "nclt" and pool is not None else None
        for d in scratch or ():
            d.mkdir()
        pooled = {} if pool is None else dict(zip(own, pool.runs(
            p, int(seed), [(s, 0, counts[s]) for s in own], encode=fmt == "nclt", write_to=scratch)))
        meta = {"generator": "blockloc.sim", "format_version": 1, "preset": p.name, "seed": int(seed),
                "format": fmt, "sessions": {}, "azimuth_steps": p.lidar.azimuth_steps,
                "frames": {"map": "NCLT map, z down", "body": "x forward, y right, z down",
                           "T_body_lidar": np.asarray(NCLT_T_BODY_LIDAR).tolist(),
                           "T_body_imu": np.asarray(NCLT_T_BODY_IMU).tolist(),
                           "gravity_map": list(NCLT_GRAVITY_MAP)}}
        for s in names:
            seq, n = seqs[s], counts[s]
            if s not in p.sessions:  # a changed day: labelled frames, rendered here
                rendered = changes.labelled_frames(seq, n, tmp / f".{s}-labels")
            else:
                rendered = seq.frames(0, n) if pool is None else pooled[s]  # encoded there for nclt
            frames = _counting(rendered, seq, progress)
            imu = seq.imu()
            gt = seq.ground_truth()
            if max_frames is not None:  # keep IMU / ground truth to the frames' time span
                t_end = seq.frame_stamps()[n - 1] + 0.2 if n else gt.stamps[0]
                imu = imu.between(imu.t[0], t_end)
                keep = gt.stamps <= t_end
                gt = type(gt)(gt.stamps[keep], gt.poses[keep])
            slam = None
            if p.is_mapping(s):
                slam = seq.mapping_poses()
                slam = type(slam)(slam.stamps[: len(gt)], slam.poses[: len(gt)])
            if fmt == "nclt":
                write_session(tmp / s, date=seq.date, frames=frames, imu=imu, ground_truth=gt,
                              slam_poses=slam, write_hits=True)
                if s not in p.sessions:
                    changes.finish_session(tmp / s, tmp / f".{s}-labels", seq)
                else:
                    shutil.rmtree(tmp / f".{s}-frames", ignore_errors=True)  # moved in: empty
            else:
                from blockloc.datasets.nclt import write_groundtruth_csv
                from blockloc.datasets.rosbag import write_rosbag, write_sidecar

                target = tmp / (f"{s}.bag" if fmt == "rosbag1" else s)
                write_rosbag(target, frames, imu, version="ros1" if fmt == "rosbag1" else "ros2-sqlite3",
                             lidar_topic="/velodyne_points", imu_topic="/imu")
                write_groundtruth_csv(tmp / f"{s}_groundtruth.csv", gt)
                if slam is not None:
                    write_groundtruth_csv(tmp / f"{s}_slam_poses.csv", slam)
                write_sidecar(target, T_body_lidar=NCLT_T_BODY_LIDAR, T_body_imu=NCLT_T_BODY_IMU,
                              gravity_map=NCLT_GRAVITY_MAP, ground_truth=f"{s}_groundtruth.csv",
                              mapping_poses=f"{s}_slam_poses.csv" if slam is not None else None)
            meta["sessions"][s] = {"date": seq.date, "frames": n,
                                   "duration_s": round(float(seq.trajectory.duration), 3),
                                   "path_length_m": round(seq.trajectory.path_length(), 2)}
            log.info("sim %s/%s: %d frames", p.name, s, n)
        (tmp / "sim.json").write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
        replace_dir(tmp, out, "simulated dataset")
        return out
    except BaseException:
        if pool is not None:
            # the workers first: one still writing its frame into tmp while it is removed left the
            # directory behind on Ctrl-C (tests/faults/test_signals.py, about 1 run in 6)
            pool.close()
            pool = None
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if pool is not None:
            pool.close()
