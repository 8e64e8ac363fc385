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

    from blockloc.datasets import open_sequence
    from blockloc.demo import prepare_small_world
    from blockloc.pipeline import LocalizationPipeline

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-frames", type=int, default=None)
    args = ap.parse_args(argv)
    paths, cfg = prepare_small_world()
    seq = WithoutImu(open_sequence(paths.dataset / "loc", dataset_cfg=cfg.dataset))
    pipe = LocalizationPipeline(seq, cfg=cfg, map_path=paths.block_map, backend="block", init="gt",
                                max_frames=args.max_frames)
    m = pipe.run().metrics
    for k in ("frames", "estimated", "failures", "recoveries", "rejected", "switches", "ate_trans_rmse_m",
              "ate_rot_rmse_deg", "rpe_1m_trans_rmse_m", "rpe_10m_trans_rmse_m", "rpe_100m_trans_rmse_m",
              "update_ms_median", "registration_ms_median", "smoother_ms_median"):
        print(k, m.get(k))
    print("counters", pipe.tracker.counters, "lidar_only", pipe.tracker.lidar_only,
          f"load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
