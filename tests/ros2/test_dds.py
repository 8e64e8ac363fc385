"""Discovery stays on this machine unless told otherwise; topics, domains and QoS as ROS 2 names them."""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET

import pytest

from blockloc.ros2 import dds as d
from blockloc.ros2 import messages as m


def test_localhost_config_has_only_loopback_and_no_multicast():
    root = ET.fromstring(d.cyclone_config("localhost"))
    dom = root.find("Domain")
    assert dom.findtext("General/AllowMulticast") == "false"
    assert [e.get("address") for e in dom.iter("NetworkInterface")] == ["127.0.0.1"]
    assert [e.get("address") for e in dom.iter("Peer")] == ["127.0.0.1"]
    assert dom.findtext("Discovery/ParticipantIndex") == "auto"
    assert int(dom.findtext("Discovery/MaxAutoParticipantIndex")) >= 8  # several nodes on one machine
    # every address anywhere in it is loopback
    addresses = [v for e in root.iter() for k, v in e.attrib.items() if k == "address"]
    assert addresses and set(addresses) == {"127.0.0.1"}


def test_the_node_default_is_localhost_and_the_environment_opens_it():
    assert d.discovery_range(None, {}) == "localhost"
    assert d.discovery_range(None, {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}) == "localhost"
    assert d.discovery_range(None, {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}) == "subnet"
    assert d.discovery_range("localhost", {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}) == "localhost"
    assert "AllowMulticast" not in d.cyclone_config("subnet")
    with pytest.raises(d.DdsError, match="--discovery"):
        d.discovery_range("world", {})


def test_domain_id_from_ros_domain_id():
    assert d.domain_id({}) == 0
    assert d.domain_id({"ROS_DOMAIN_ID": "42"}) == 42
    for bad in ("x", "-1", "300"):
        with pytest.raises(d.DdsError, match="ROS_DOMAIN_ID"):
            d.domain_id({"ROS_DOMAIN_ID": bad})


def test_ros_topic_names():
    assert d.dds_topic("/points") == "rt/points"
    assert d.dds_topic("/blockloc/pose") == "rt/blockloc/pose"
    with pytest.raises(d.DdsError):
        d.dds_topic("/")


def test_without_cyclonedds_uri_the_participant_uses_its_own_localhost_config(loopback_dds):
    from tests.ros2.conftest import OWN_CONFIG_DOMAIN

    # no CYCLONEDDS_URI; a domain no loopback_dds test of this process uses (Cyclone refuses a
    # second configuration for a domain this process has already joined)
    env = {"ROS_DOMAIN_ID": str(OWN_CONFIG_DOMAIN)}
    p = d.Dds(environ=env)
    try:
        assert p.user_uri is None and p.config == d.cyclone_config("localhost")
        assert p.domain == int(env["ROS_DOMAIN_ID"])
    finally:
        p.close()


def test_publish_and_subscribe_over_loopback_with_a_latched_topic(loopback_dds):
    p = d.Dds()
    assert p.user_uri == loopback_dds["CYCLONEDDS_URI"]
    try:
        latched = p.writer("/tf_static", m.TFMessage, d.LATCHED)
        latched.write(m.TFMessage(transforms=[m.TransformStamped(child_frame_id="lidar")]))
        w = p.writer("/points", m.Header, d.SENSOR_DATA)
        got, late = [], []
        p.reader("/points", m.Header, got.append, d.SENSOR_DATA)
        p.reader("/tf_static", m.TFMessage, late.append, d.LATCHED)  # joins after the write
        t0 = time.monotonic()
        while len(got) < 5 and time.monotonic() - t0 < 10:
            w.write(m.Header(stamp=m.Time(sec=len(got)), frame_id="lidar"))
            time.sleep(0.05)
        assert len(got) >= 5 and got[0].frame_id == "lidar"
        while not late and time.monotonic() - t0 < 10:
            time.sleep(0.05)
        assert late and late[0].transforms[0].child_frame_id == "lidar"  # transient local reached a late reader
    finally:
        p.close()
