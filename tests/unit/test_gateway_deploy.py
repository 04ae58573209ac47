"""deploy/router.json5 loads and runs as a router; make_zenoh_config builds working sessions."""

from __future__ import annotations

import json
import socket
import threading
from pathlib import Path

import pytest
import zenoh

from bus_agent.gateway.zenoh_config import ZenohConfigError, from_settings, make_zenoh_config

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_router_config_routes_between_two_clients():
    conf = zenoh.Config.from_file(str(ROOT / "deploy" / "router.json5"))
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    ep = f"tcp/127.0.0.1:{free_port()}"
    conf.insert_json5("listen/endpoints", json.dumps([ep]))
    got = threading.Event()
    with zenoh.open(conf):
        with zenoh.open(make_zenoh_config("client", [], [ep])) as a, \
                zenoh.open(make_zenoh_config("client", [], [ep])) as b:
            sub = a.declare_subscriber("t/x", lambda s: got.set())
            pub = b.declare_publisher("t/x")
            for _ in range(100):
                pub.put(b"1")
                if got.wait(0.05):
                    break
            sub.undeclare()
            pub.undeclare()
    assert got.is_set()


def test_defaults():
    c = make_zenoh_config("peer", ["tcp/127.0.0.1:0"], ["tcp/127.0.0.1:1"])
    assert json.loads(c.get_json("scouting/multicast/enabled")) is False
    assert json.loads(c.get_json("transport/link/tx/lease")) == 3000
    assert json.loads(c.get_json("connect/timeout_ms")) == -1          # peers retry in the background
    assert json.loads(make_zenoh_config("client", [], ["tcp/127.0.0.1:1"]).get_json("connect/timeout_ms")) > 0
    assert json.loads(make_zenoh_config("peer").get_json("listen/endpoints")) == []


@pytest.mark.parametrize("kwargs, words", [
    ({"mode": "server"}, "mode"),
    ({"listen": ["127.0.0.1:7447"]}, "locator"),
    ({"connect": ["tcp/"]}, "locator"),
    ({"link_lease_ms": 10}, "lease"),
])
def test_bad_settings_are_named(kwargs, words):
    with pytest.raises(ZenohConfigError, match=words):
        make_zenoh_config(**kwargs)


def test_from_agent_settings():
    from bus_agent.config import ZenohConfig

    c = from_settings(ZenohConfig(mode="client", connect=("tcp/127.0.0.1:1",), scouting=True))
    assert json.loads(c.get_json("mode")) == "client"
    assert json.loads(c.get_json("scouting/multicast/enabled")) is True
