"""Fixtures of the ROS tests: a ROS-side Zenoh router in-process (loopback, multicast off)."""

import json

import pytest
import zenoh

from aisdf.stack import endpoint, free_port


@pytest.fixture
def ros_router():
    """(its endpoint, the router's session)."""
    port = free_port()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint(port)]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as router:
        yield endpoint(port), router
