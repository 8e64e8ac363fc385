"""A reader with ``ignore_own``: the node reads /tf for the robot's odometry and writes /tf itself;
its own transforms must not come back to it (they did, inside every ``write``, on the worker)."""

from __future__ import annotations

import time

import numpy as np

from tests.node.conftest import wait_until


def test_a_reader_ignoring_its_own_participant_gets_only_the_others_samples(loopback_dds):
    from blockloc.ros2 import convert
    from blockloc.ros2 import dds as d
    from blockloc.ros2 import messages as m

    node, robot = d.Dds(), d.Dds()
    try:
        own, everything = [], []
        node.reader("/tf", m.TFMessage, own.append, d.SENSOR_DATA, ignore_own=True)
        node.reader("/tf", m.TFMessage, everything.append, d.SENSOR_DATA)
        node_tf = node.writer("/tf", m.TFMessage, d.RELIABLE)
        robot_tf = robot.writer("/tf", m.TFMessage, d.RELIABLE)
        time.sleep(0.3)  # discovery on loopback
        node_tf.write(m.TFMessage(transforms=[convert.transform_stamped(np.eye(4), 1.0, "map", "base_link")]))
        robot_tf.write(m.TFMessage(transforms=[convert.transform_stamped(np.eye(4), 1.0, "odom", "base_link")]))
        wait_until(lambda: len(everything) >= 2 and own, 10, "the transforms")
        time.sleep(0.2)
        assert [x.transforms[0].header.frame_id for x in own] == ["odom"]
        assert sorted(x.transforms[0].header.frame_id for x in everything) == ["map", "odom"]
    finally:
        node.close()
        robot.close()
