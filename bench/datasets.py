"""Sequence loader/writer speed: NCLT layout (with and without velodyne_hits.bin) and ROS bags.

    python -m bench.datasets

Synthetic HDL-32E-sized sweeps (32 lasers x 2170 azimuth steps = 69,440 points, times over 0.1 s)
are written with ``write_session`` / ``write_rosbag`` into a temp dir, then read back. Writes
``docs/bench/datasets.md``.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from blockloc.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
N_FRAMES = 30
REPEATS = 5


def _sweep(i: int, stamp: float):
    from blockloc.datasets.base import LidarFrame

    rng = np.random.default_rng(i)
    n_az, n_las = 2170, 32
    az = np.repeat(np.arange(n_az) * 2 * np.pi / n_az, n_las)
    el = np.tile(np.deg2rad(np.linspace(-30.67, 10.67, n_las)), n_az)
    r = rng.uniform(2.0, 90.0, len(az))
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    return LidarFrame(i, stamp, pts, rng.uniform(0, 255, len(az)).astype(np.float32),
                      (az / (2 * np.pi) * 0.1 - 0.1).astype(np.float32),
                      np.tile(np.arange(n_las, dtype=np.uint16), n_az))


def _median_ms(fn, args_list):
    ts = []
    for _ in range(REPEATS):
        for a in args_list:
            t0 = time.perf_counter()
            fn(a)
            ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts))


def main() -> int:
    sys.path.insert(0, str(ROOT))
    from bench.__main__ import machine
    from blockloc.datasets.base import ImuData
    from blockloc.datasets.nclt import NcltSequence, write_session
    from blockloc.datasets.rosbag import RosbagSequence, write_rosbag
    from blockloc.geometry import Trajectory

    t0 = 1326030000.0
    stamps = t0 + 0.1 * (np.arange(N_FRAMES) + 1)
    t_imu = t0 + np.arange(int(0.1 * (N_FRAMES + 1) * 100)) / 100.0
    imu = ImuData(t_imu, np.zeros((len(t_imu), 3)), np.zeros((len(t_imu), 3)))
    gt = Trajectory(t_imu, np.tile(np.eye(4), (len(t_imu), 1, 1)))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        frames = lambda: (_sweep(i, s) for i, s in enumerate(stamps))  # noqa: E731
        t = time.perf_counter()
        sess = write_session(tmp / "s", date="bench", frames=frames(), imu=imu, ground_truth=gt)
        write_s = (time.perf_counter() - t) / N_FRAMES
        rows.append(("NCLT write_session (sync + hits), per frame", 1e3 * write_s))
        seq = NcltSequence(sess, max_range_m=200.0)
        t = time.perf_counter()
        seq.frame(0)  # first call indexes velodyne_hits.bin (numba kernel compiled/cached)
        rows.append(("NCLT first frame: import numba, load cached kernel, index hits of the session", 1e3 * (time.perf_counter() - t)))
        idx = list(range(N_FRAMES))
        rows.append(("NCLT frame load, per-point times from hits", _median_ms(seq.frame, idx)))
        seq_nohits = NcltSequence(sess, max_range_m=200.0, use_hits_times=False)
        rows.append(("NCLT frame load, azimuth times (no hits)", _median_ms(seq_nohits.frame, idx)))
        for version in ("ros1", "ros2-sqlite3", "ros2-mcap"):
            path = tmp / ("b.bag" if version == "ros1" else f"b-{version}")
            t = time.perf_counter()
            write_rosbag(path, frames(), imu, version=version)
            rows.append((f"{version} write_rosbag, per frame", 1e3 * (time.perf_counter() - t) / N_FRAMES))
            t = time.perf_counter()
            bag = RosbagSequence(path, lidar_topic="/velodyne_points", imu_topic="/imu")
            rows.append((f"{version} open (index lidar topic, {N_FRAMES} msgs)", 1e3 * (time.perf_counter() - t)))
            rows.append((f"{version} frame load (random access)", _median_ms(bag.frame, idx)))
            t = time.perf_counter()
            n = sum(1 for _ in bag.frames())
            rows.append((f"{version} frames() sequential, per frame", 1e3 * (time.perf_counter() - t) / n))
            bag.close()
    n_pts = len(_sweep(0, 0.0))
    lines = ["## Sequence loaders (datasets)", "",
             f"Machine: {machine()}. Command: `python -m bench.datasets` "
             f"({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}).",
             f"Synthetic HDL-32E-sized sweeps of {n_pts:,} points, {N_FRAMES} frames; "
             f"frame loads are medians over {REPEATS} passes (page cache warm).", "",
             "| step | ms |", "|---|---:|"]
    lines += [f"| {name} | {ms:.2f} |" for name, ms in rows]
    out = ROOT / "docs" / "bench" / "datasets.md"
    atomic_write_text(out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
