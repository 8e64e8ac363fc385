"""DDS in tests stays on loopback with multicast off: every test gets CYCLONEDDS_URI set to the
localhost config and a ROS_DOMAIN_ID of its own (tests in parallel, or a stale process, never
cross)."""

from __future__ import annotations

import itertools
import os

import pytest

# Parallel test workers (pytest-xdist: PYTEST_XDIST_WORKER gw0, gw1, ...) draw from ranges of
# their own, so two workers' tests never share a domain; the PID offset keeps a stale process of
# an earlier run out of the way. Domain IDs stay within Cyclone's 0-232.
_WORKER = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:] or 0) % 4
_SPAN = 30
_DOMAINS = itertools.count(os.getpid() % _SPAN)
#: A domain of this worker's that no loopback_dds test takes (for a participant with another config).
OWN_CONFIG_DOMAIN = 225 + _WORKER


def loopback_env(domain: int) -> dict:
    """The environment variables of a loopback-only DDS domain."""
    from blockloc.ros2.dds import cyclone_config

    return {"CYCLONEDDS_URI": cyclone_config("localhost"), "ROS_DOMAIN_ID": str(domain),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


@pytest.fixture
def loopback_dds(monkeypatch) -> dict:
    """Sets the loopback DDS environment for this test (and the processes it starts); returns it."""
    env = loopback_env(100 + _WORKER * _SPAN + next(_DOMAINS) % _SPAN)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    return env
