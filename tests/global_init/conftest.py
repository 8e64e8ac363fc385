"""Fixtures of the global-init tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def small_world():
    """(SmallWorld, Config): the sim:small sessions (simulated on the fly) and their block map
    (as tests/tracking uses; built once per machine)."""
    from blockloc.app.runs import prepare_small_world

    return prepare_small_world()


def prepared_scans(seq, indices):
    """(InitScan, T_map_body ground truth at its stamp) for frames ``indices`` of ``seq``, prepared
    as ``blockloc init`` prepares them (:func:`blockloc.global_init.scan_prep.prepare_for_init`)."""
    import numpy as np

    from blockloc.global_init.scan_prep import prepare_for_init

    imu = seq.imu()
    gt = seq.ground_truth()
    out = []
    for i in indices:
        scan = prepare_for_init(seq.frame(int(i)), imu, seq.info)
        out.append((scan, gt.interpolate(np.array([scan.stamp]))[0] if gt is not None else None))
    return out
