"""Resolve a ``--seq`` value to a Sequence: dataset names, simulated sessions, or paths.

Names:
- ``nclt_1``..``nclt_5``: NCLT sessions 2012-01-15, 2012-01-22, 2012-02-02, 2012-04-29,
  2012-05-11. The official downloads ``<date>_vel.tar.gz`` and ``<date>_sen.tar.gz`` both unpack
  into a ``<date>/`` directory; unpack them under ``<data_root>/nclt/`` (or ``<data_root>/``)
  and put ``groundtruth_<date>.csv`` in ``<date>/``, beside it, or in ``ground_truth/``.
- ``m2dgr_1``, ``m2dgr_2``: M2DGR ``street_01.bag`` / ``street_02.bag`` under
  ``<data_root>/m2dgr/`` (or ``<data_root>/``), ground truth ``street_0N.txt`` (TUM) beside the
  bag or in ``ground_truth/``; topics ``/velodyne_points`` and ``/handsfree/imu``.
- ``sim:<preset>/<session>[@<seed>]``: a simulated session streamed on the fly
  (``blockloc.sim.stream.open_sim_sequence``), seed 1 by default.
- a path: an NCLT-layout session directory (has ``velodyne_sync/``), a ROS1 ``.bag`` file, or
  a ROS2 bag directory (has ``metadata.yaml``).

The data root is the ``data_root`` argument, else ``dataset_cfg.data_root``, else
``$BLOCKLOC_DATA``, else ``./data``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from blockloc.datasets.base import Sequence
from blockloc.errors import DatasetError

NCLT_NAMES = {f"nclt_{i + 1}": d for i, d in enumerate(
    ("2012-01-15", "2012-01-22", "2012-02-02", "2012-04-29", "2012-05-11"))}
M2DGR_NAMES = {"m2dgr_1": "street_01", "m2dgr_2": "street_02"}

#: M2DGR: body = the Handsfree A9 IMU frame (x forward, y left, z up). The VLP-32C sits at
#: (0.27255, -0.00053, 0.17954) m in it with identity rotation: the lidar-IMU extrinsic the
#: M2DGR authors ship in their LIO configurations (extrinsic_T / extrinsic_R).
M2DGR_T_BODY_LIDAR = np.array([[1.0, 0.0, 0.0, 0.27255],
                               [0.0, 1.0, 0.0, -0.00053],
                               [0.0, 0.0, 1.0, 0.17954],
                               [0.0, 0.0, 0.0, 1.0]])
M2DGR_T_BODY_IMU = np.eye(4)
M2DGR_LIDAR_TOPIC = "/velodyne_points"
M2DGR_IMU_TOPIC = "/handsfree/imu"

_SIM_RE = re.compile(r"^sim:(?P<preset>[A-Za-z0-9_\-]+)/(?P<session>[A-Za-z0-9_\-]+)(@(?P<seed>\d+))?$")


def known_names() -> list[str]:
    """Dataset names ``open_sequence`` accepts besides paths and ``sim:`` names."""
    return list(NCLT_NAMES) + list(M2DGR_NAMES)


def resolve_data_root(data_root: str | Path | None = None, dataset_cfg=None) -> Path:
    """The data root: argument, then ``dataset_cfg.data_root``, then $BLOCKLOC_DATA, then ./data."""
    for cand in (data_root, getattr(dataset_cfg, "data_root", None), os.environ.get("BLOCKLOC_DATA")):
        if cand:
            return Path(cand).expanduser()
    return Path("data")


def open_sequence(name_or_path: str | Path, *, data_root: str | Path | None = None,
                  dataset_cfg=None, lidar_topic: str | None = None,
                  imu_topic: str | None = None) -> Sequence:
    """Open a sequence by name or path (see the module docstring).

    dataset_cfg: a ``blockloc.config.DatasetConfig`` (range limits, hits use, topics, data
    root); explicit arguments override it. Raises DatasetError with one line naming the expected
    path when data are missing, or listing the known names for an unknown name.
    """
    name = str(name_or_path)
    ranges = dict(min_range_m=float(getattr(dataset_cfg, "min_range_m", 1.0)),
                  max_range_m=float(getattr(dataset_cfg, "max_range_m", 100.0)))
    use_hits = bool(getattr(dataset_cfg, "use_hits_times", True))
    cfg_lidar = getattr(dataset_cfg, "lidar_topic", None)
    cfg_imu = getattr(dataset_cfg, "imu_topic", None)

    m = _SIM_RE.match(name)
    if m:
        from blockloc.sim.stream import open_sim_sequence

        return open_sim_sequence(m["preset"], m["session"], int(m["seed"] or 1))
    if name.startswith("sim:"):
        raise DatasetError(f"sequence {name!r}: expected sim:<preset>/<session>[@<seed>], "
                           "e.g. sim:small/loc@1")

    if name in NCLT_NAMES:
        from blockloc.datasets.nclt import NcltSequence

        root = resolve_data_root(data_root, dataset_cfg)
        date = NCLT_NAMES[name]
        cands = [root / "nclt" / date, root / "NCLT" / date, root / date]
        for c in cands:
            if (c / "velodyne_sync").is_dir():
                return NcltSequence(c, use_hits_times=use_hits, date=date, name=name, **ranges)
        raise DatasetError(
            f"{name}: NCLT session {date} not found: expected {cands[0]}/velodyne_sync/ "
            f"(unpack {date}_vel.tar.gz and {date}_sen.tar.gz from the NCLT site into {root / 'nclt'}, "
            f"put groundtruth_{date}.csv in {cands[0]}; data root from --data-root or BLOCKLOC_DATA)")

    if name in M2DGR_NAMES:
        from blockloc.datasets.rosbag import RosbagSequence

        root = resolve_data_root(data_root, dataset_cfg)
        stem = M2DGR_NAMES[name]
        cands = [root / "m2dgr" / f"{stem}.bag", root / "M2DGR" / f"{stem}.bag", root / f"{stem}.bag"]
        bag = next((c for c in cands if c.is_file()), None)
        if bag is None:
            raise DatasetError(f"{name}: M2DGR {stem}.bag not found: expected {cands[0]} "
                               f"(download {stem}.bag and its ground truth {stem}.txt from the "
                               f"M2DGR site into {root / 'm2dgr'})")
        gt = next((g for g in (bag.with_suffix(".txt"), bag.parent / "ground_truth" / f"{stem}.txt")
                   if g.is_file()), None)
        return RosbagSequence(bag, lidar_topic=lidar_topic or M2DGR_LIDAR_TOPIC,
                              imu_topic=imu_topic or M2DGR_IMU_TOPIC,
                              T_body_lidar=M2DGR_T_BODY_LIDAR, T_body_imu=M2DGR_T_BODY_IMU,
                              gravity_map=(0.0, 0.0, -9.81), ground_truth_path=gt, name=name,
                              **ranges)

    path = Path(name).expanduser()
    if path.is_dir() and (path / "velodyne_sync").is_dir():
        from blockloc.datasets.nclt import NcltSequence

        return NcltSequence(path, use_hits_times=use_hits, **ranges)
    if (path.is_file() and path.suffix == ".bag") or (path.is_dir() and (path / "metadata.yaml").is_file()):
        from blockloc.datasets.rosbag import RosbagSequence

        return RosbagSequence(path, lidar_topic=lidar_topic or cfg_lidar or "/velodyne_points",
                              imu_topic=imu_topic or cfg_imu or "/imu", **ranges)
    if path.exists():
        raise DatasetError(f"{path}: not a sequence; expected an NCLT-layout session directory "
                           "(with velodyne_sync/), a ROS1 .bag file or a ROS2 bag directory "
                           "(with metadata.yaml)")
    if "/" in name or os.sep in name or name.endswith(".bag"):
        raise DatasetError(f"{path}: no such file or directory (expected an NCLT-layout session "
                           "directory, a ROS1 .bag or a ROS2 bag directory)")
    raise DatasetError(f"unknown sequence {name!r}: expected a path or one of "
                       f"{', '.join(known_names())}, sim:<preset>/<session>[@<seed>]")
