"""The node's tests: a tiny world (a 120-scan NCLT-layout session, its block map with a place
index, the config) built once, DDS on loopback (``loopback_dds``), and an in-process harness
that feeds the node messages as a robot would and listens to what it publishes."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

from tests.faults import tiny
from tests.ros2.conftest import loopback_dds, loopback_env  # noqa: F401 - fixtures for this folder


@pytest.fixture(scope="session")
def tiny_live_world(tmp_path_factory):
    from blockloc.datasets.nclt import NcltSequence
    from blockloc.global_init.place_index import write_place_index

    root = tmp_path_factory.mktemp("live")
    session = tiny.write_tiny_session(root / "sess", n_frames=120)
    store = tiny.build_tiny_map(session, root / "map")
    seq = NcltSequence(session)
    write_place_index(store, seq.info.gravity_map)
    return {"root": root, "session": session, "map": store, "config": tiny.write_config(root / "cfg.yaml"),
            "seq": seq}


def wait_until(cond, timeout_s: float, what: str) -> None:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"not within {timeout_s} s: {what}")
        time.sleep(0.02)


class Harness:
    """A node in this process on loopback DDS, a robot's publishers and a listener of its output."""

    def __init__(self, world, **settings) -> None:
        from blockloc.config import load_config
        from blockloc.node import _assemble
        from blockloc.node.node import LocalizationNode, NodeSettings
        from blockloc.ros2 import dds as d
        from blockloc.ros2 import messages as m

        cfg = load_config(str(world["config"]))
        store = _assemble.open_store(str(world["map"]), cfg)
        lo = np.min([e.bounds_min[:2] for e in store.entries], axis=0)
        hi = np.max([e.bounds_max[:2] for e in store.entries], axis=0)
        self.seq = world["seq"]
        self.node_dds = d.Dds()
        init_pose = settings.pop("init_pose", None)
        self.node = LocalizationNode(
            self.node_dds, lambda info, imu: _assemble.build_session(cfg, store, str(world["map"]), info, imu),
            settings=NodeSettings(**settings), gravity_map=self.seq.info.gravity_map,
            map_bounds=(tuple(lo), tuple(hi)), init_pose=init_pose).start()
        self.dds = d.Dds()
        self.points = self.dds.writer("/points", m.PointCloud2, d.SENSOR_DATA)
        self.imu = self.dds.writer("/imu/data", m.Imu, d.SENSOR_DATA)
        self.tf_static = self.dds.writer("/tf_static", m.TFMessage, d.LATCHED)
        self.initialpose = self.dds.writer("/initialpose", m.PoseWithCovarianceStamped, d.RELIABLE)
        self.relocalize = self.dds.writer("/blockloc/relocalize", m.Empty, d.RELIABLE)
        self.poses, self.diags, self.tf, self.odom, self.local_maps = [], [], [], [], []
        self.dds.reader("/blockloc/pose", m.PoseWithCovarianceStamped, self.poses.append, d.RELIABLE)
        self.dds.reader("/blockloc/odom", m.Odometry, self.odom.append, d.RELIABLE)
        self.dds.reader("/diagnostics", m.DiagnosticArray, self.diags.append, d.RELIABLE)
        self.dds.reader("/tf", m.TFMessage, self.tf.append, d.RELIABLE)
        self.dds.reader("/blockloc/local_map", m.PointCloud2, self.local_maps.append, d.LATCHED)
        self.frames = list(self.seq.frames())
        self.all_imu = self.seq.imu()
        self._imu_next = 0
        self._waited = False
        time.sleep(0.3)  # discovery on loopback

    def publish_static(self) -> None:
        from blockloc.ros2 import convert
        from blockloc.ros2 import messages as m

        info = self.seq.info
        self.tf_static.write(m.TFMessage(transforms=[
            convert.transform_stamped(info.T_body_lidar, 0.0, "base_link", "lidar"),
            convert.transform_stamped(info.T_body_imu, 0.0, "base_link", "imu")]))

    def send_scan(self, i: int, *, imu: bool = True, stamp_shift: float = 0.0, wait: bool = True,
                  timeout_s: float = 60.0) -> None:
        """Scan i with the IMU samples up to its sweep's end; waits until the node processed it."""
        from blockloc.ros2 import convert

        f = self.frames[i]
        t_end = f.stamp + float(np.max(f.time_offsets))
        if imu:
            self.send_imu_until(t_end, stamp_shift)
        done = self.node.stats.processed + self.node.stats.bad_scans + self.node.stats.failed_scans
        self.points.write(convert.cloud_from_points(f.points, f.stamp + stamp_shift, "lidar",
                                                    time_offsets=f.time_offsets, intensity=f.intensity))
        if wait:
            # the node's first scan in a process compiles its numba kernels (global init, NDT,
            # deskew): on a fresh checkout with both cores busy that alone can take minutes
            first = done == 0 and not self._waited
            self._waited = True
            wait_until(lambda: self.node.stats.processed + self.node.stats.bad_scans
                       + self.node.stats.failed_scans > done, max(timeout_s, 300.0) if first else timeout_s,
                       f"scan {i} processed")

    def send_imu_until(self, t_end: float, stamp_shift: float = 0.0) -> None:
        from blockloc.ros2 import convert

        imu = self.all_imu
        j = self._imu_next
        while j < len(imu.t) and imu.t[j] <= t_end:
            self.imu.write(convert.imu_message(imu.t[j] + stamp_shift, imu.acc[j], imu.gyro[j], "imu"))
            j += 1
            if j % 5 == 0:
                time.sleep(0.001)  # best effort, keep-last 5: let the node's reader take them
        self._imu_next = j

    def diag_values(self) -> list[dict]:
        return [{kv.key: kv.value for kv in d.status[0].values} for d in list(self.diags)]

    def close(self):
        try:
            return self.node.close(interrupted=False)
        finally:
            self.dds.close()
            self.node_dds.close()


@pytest.fixture
def harness(tiny_live_world, loopback_dds):
    made = []

    def make(**settings):
        h = Harness(tiny_live_world, **settings)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()


@pytest.fixture
def node_log(caplog):
    caplog.set_level(logging.INFO, logger="blockloc")
    return caplog
