"""DDS in tests stays on loopback with multicast off: every test gets CYCLONEDDS_URI set to the
localhost config and a ROS_DOMAIN_ID of its own (tests in parallel, or a stale process, never
cross)."""

from __future__ import annotations

import itertools
import os

import pytest

_DOMAINS = itertools.count(100 + os.getpid() % 50)


def loopback_env(domain: int) -> dict:
    """The environment variables of a loopback-only DDS domain."""
    from blockloc.ros2.dds import cyclone_config

    return {"CYCLONEDDS_URI": cyclone_config("localhost"), "ROS_DOMAIN_ID": str(domain),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


@pytest.fixture
def loopback_dds(monkeypatch) -> dict:
    """Sets the loopback DDS environment for this test (and the processes it starts); returns it."""
    env = loopback_env(200 - next(_DOMAINS) % 100)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    return env
