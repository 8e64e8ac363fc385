"""LiDAR-only end to end on the `small` simulated world with its IMU withheld: the pipeline's frame
loop, block map, NDT, the constant-velocity prior and twist deskewing (the simulated scans have
per-point times), from a ground-truth pose. One run over frames 150..500 (two block switches, at
191 and 490) is shared by the assertions."""

import csv

import numpy as np
import pytest

from blockloc.evaluation.results import RunWriter
from blockloc.maps.store import open_map
from blockloc.app.assemble import build_session
from tests.tracking.noimu import WithoutImu

START, STOP = 150, 500


@pytest.fixture(scope="module")
def no_imu_run(small_world, tmp_path_factory):
    from blockloc.app.catalog import open_sequence

    paths, cfg = small_world
    seq = WithoutImu(open_sequence(paths.loc, dataset_cfg=cfg.dataset))
    assert len(seq.imu()) == 0 and seq.frame(0).time_offsets is not None
    out = tmp_path_factory.mktemp("track_noimu") / "run"
    session = build_session(cfg, seq, open_map(paths.block_map), backend="block", observers=[RunWriter(out)],
                                  out_dir=out, keep_estimates=True)
    return session.run(START, STOP, init="gt"), session, seq


def test_small_world_without_imu_is_tracked(no_imu_run):
    res, pipe, seq = no_imu_run
    m = res.metrics
    assert pipe.tracker.lidar_only
    assert m["frames"] == STOP - START and m["estimated"] == STOP - START
    assert m["failures"] == 0 and m["recoveries"] == 0 and m["rejected"] == 0
    # measured on frames 0..500 of the realistic sim: 0.055 m, 0.45 deg (its 0.3 deg extrinsic
    # error sets that floor); issue 14's target is 0.10 m. On the old sim: 0.019 m, 0.065 deg.
    assert m["ate_trans_rmse_m"] <= 0.10
    assert m["ate_rot_rmse_deg"] <= 0.8
    assert {e.diagnostics.status for e in res.estimates} == {"ok"}
    # no IMU: no biases estimated, the velocity comes from the twist
    assert all(np.all(e.acc_bias == 0) and np.all(e.gyro_bias == 0) for e in res.estimates)
    gt = seq.ground_truth()
    stamps = np.array([e.stamp for e in res.estimates[20:]])
    h = 0.05
    p = gt.interpolate(np.r_[stamps - h, stamps + h])[:, :3, 3]
    v_true = (p[len(stamps):] - p[:len(stamps)]) / (2 * h)
    v_est = np.array([e.velocity_map for e in res.estimates[20:]])
    assert np.median(np.linalg.norm(v_est - v_true, axis=1)) < 0.15


def test_switches_and_outputs_are_as_with_an_imu(no_imu_run):
    res, pipe, seq = no_imu_run
    ests = res.estimates
    sw = [i for i, e in enumerate(ests) if e.diagnostics.switched]
    assert len(sw) >= 2 and res.metrics["switches"] == len(sw)
    for k in sw:
        assert ests[k].diagnostics.window_size == 5 and ests[k - 1].diagnostics.window_size == 20
    for name in ("poses.tum", "metrics.json", "diagnostics.csv", "config.yaml"):
        assert (res.out_dir / name).is_file(), name
    with open(res.out_dir / "diagnostics.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == STOP - START and "rotation_retries" in rows[0]
