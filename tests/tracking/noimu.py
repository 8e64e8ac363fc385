"""A sequence with its IMU withheld: the LiDAR-only tests' view of a simulated session.

    python -m tests.tracking.noimu [--max-frames N]

tracks the `small` world's loc session LiDAR-only from the first ground-truth pose and prints the
figures (a development measurement on a shared machine).
"""

from __future__ import annotations

import numpy as np

from blockloc.datasets.base import ImuData


class WithoutImu:
    """Wraps any ``Sequence``; everything passes through except ``imu()``, which is empty."""

    def __init__(self, seq) -> None:
        self._seq = seq
        self.info = seq.info

    def __len__(self) -> int:
        return len(self._seq)

    def __getattr__(self, name):
        return getattr(self._seq, name)

    def imu(self) -> ImuData:
        return ImuData(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))


def main(argv=None) -> int:
    import argparse
    import os

    from blockloc.app.runs import prepare_small_world
    from blockloc.app.catalog import open_sequence
    from blockloc.maps.store import open_map
    from blockloc.app.assemble import build_session

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-frames", type=int, default=None)
    args = ap.parse_args(argv)
    paths, cfg = prepare_small_world()
    seq = WithoutImu(open_sequence(paths.loc, dataset_cfg=cfg.dataset))
    session = build_session(cfg, seq, open_map(paths.block_map), backend="block")
    m = session.run(0, args.max_frames, init="gt").metrics
    for k in ("frames", "estimated", "failures", "recoveries", "rejected", "switches", "ate_trans_rmse_m",
              "ate_rot_rmse_deg", "rpe_1m_trans_rmse_m", "rpe_10m_trans_rmse_m", "rpe_100m_trans_rmse_m",
              "update_ms_median", "registration_ms_median", "smoother_ms_median"):
        print(k, m.get(k))
    print("counters", session.tracker.counters, "lidar_only", session.tracker.lidar_only,
          f"load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
