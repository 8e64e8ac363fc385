"""Tiny inputs for the fault-injection suite: an NCLT-layout session, a scan folder and a block
map, each small enough that a whole ``blockloc track`` on them takes seconds.

The session is the analytic circle drive of :mod:`tests.tracking.synthetic` (exact IMU, motion
distorted scans of a scene of walls and boxes) written with ``write_session``; its block map is
built from the same session's ground truth with the real builder.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from blockloc.datasets.base import ImuData
from blockloc.geometry import Trajectory
from tests.tracking.synthetic import T_BODY_LIDAR, CircleTrajectory, imu_from_trajectory, make_scan, make_scene

DATE = "2020-01-01"
T0 = 1.0  # first scan stamp, s (the analytic trajectory is defined for any t)
RATE_HZ = 10.0
BLOCK_SIZE_M = 8.0

#: The config every tiny run uses (a file given with --config): the defaults with the sensor
#: rates of the tiny session and a small scan budget.
CONFIG = {
    "lidar": {"rate_hz": RATE_HZ, "max_points": 6000},
    "map": {"block_size_m": BLOCK_SIZE_M, "prefetch": False},
    "evaluation": {"plots": False},
}


def scene() -> np.ndarray:
    """(N, 3) map points, z up, metres."""
    return make_scene(seed=0, half_size=35.0, spacing=0.5)


def write_tiny_session(out: Path, n_frames: int = 40, *, imu_gap: tuple[float, float] | None = None,
                       drop_frames: tuple[int, ...] = (), max_points: int = 5000) -> Path:
    """A session of ``n_frames`` scans at 10 Hz along the circle (NCLT layout, ``write_session``).

    imu_gap: (t0, t1) s, IMU samples in it left out. drop_frames: scan indices not written (a
    LiDAR dropout)."""
    from blockloc.datasets.nclt import write_session

    traj = CircleTrajectory(radius=20.0, speed=5.0, z_up=True)
    pts = scene()
    stamps = T0 + np.arange(n_frames) / RATE_HZ
    frames = (make_scan(pts, traj, float(t), T_BODY_LIDAR, index=i, max_points=max_points, max_range=30.0)
              for i, t in enumerate(stamps) if i not in drop_frames)
    imu = imu_from_trajectory(traj, T0 - 1.0, float(stamps[-1]) + 0.5)
    if imu_gap is not None:
        keep = (imu.t < imu_gap[0]) | (imu.t > imu_gap[1])
        imu = ImuData(imu.t[keep], imu.acc[keep], imu.gyro[keep])
    t_gt = np.arange(T0 - 1.0, float(stamps[-1]) + 0.5, 0.01)
    gt = Trajectory(t_gt, traj.pose(t_gt))
    return write_session(out, date=DATE, frames=frames, imu=imu, ground_truth=gt,
                         T_body_lidar=T_BODY_LIDAR, T_body_imu=np.eye(4), gravity_map=traj.gravity_map)


def write_config(path: Path, **sections) -> Path:
    """CONFIG, with ``sections`` merged in (section -> {key: value}), as a YAML file."""
    cfg = {k: dict(v) for k, v in CONFIG.items()}
    for name, values in sections.items():
        cfg.setdefault(name, {}).update(values)
    path.write_text(yaml.safe_dump(cfg))
    return path


def build_tiny_map(session: Path, out: Path) -> Path:
    """The block map of ``session`` from its ground truth (blocks of BLOCK_SIZE_M)."""
    from blockloc.datasets.nclt import NcltSequence
    from blockloc.maps.build_plan import build_block_map_from_sequence

    build_block_map_from_sequence(NcltSequence(session), block_size_m=BLOCK_SIZE_M, voxel_size_m=0.2,
                                  keyframe_distance_m=1.0, out=out)
    return out


def write_tiny_scan_folder(out: Path, session: Path) -> Path:
    """The scans of an NCLT-layout ``session`` as a scan folder: ``scans/<stamp>.pcd`` (binary PCD
    with a per-point ``time`` field), ``poses.tum``, ``imu.csv`` and ``extrinsics.yaml``."""
    from blockloc.datasets.nclt import NcltSequence
    from blockloc.datasets.pointclouds import write_point_cloud
    from blockloc.trajectory_io import write_tum

    seq = NcltSequence(session)
    (out / "scans").mkdir(parents=True)
    for f in seq.frames():
        write_point_cloud(out / "scans" / f"{f.stamp:.6f}.pcd", f.points, intensity=f.intensity,
                          extra={"time": np.asarray(f.time_offsets, np.float32)})
    gt = seq.ground_truth()
    write_tum(out / "poses.tum", Trajectory(seq.frame_stamps(), gt.interpolate(seq.frame_stamps())))
    imu = seq.imu()
    rows = np.column_stack([imu.t, imu.acc, imu.gyro])
    (out / "imu.csv").write_text("t,ax,ay,az,gx,gy,gz\n" + "\n".join(",".join(f"{v:.9g}" for v in r)
                                                                       for r in rows) + "\n")
    (out / "extrinsics.yaml").write_text(yaml.safe_dump({
        "T_body_lidar": np.asarray(seq.info.T_body_lidar).tolist(),
        "T_body_imu": np.asarray(seq.info.T_body_imu).tolist(),
        "gravity_map": np.asarray(seq.info.gravity_map).tolist()}))
    return out
