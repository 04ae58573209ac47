"""Sim control over Zenoh: two peer sessions on loopback, fault injection into a SimBus."""

from __future__ import annotations

import socket
import threading
import time
from typing import Iterator

import msgpack
import pytest
import zenoh

from bus_agent.bus.base import ALState
from bus_agent.bus.sim_bus import SimBus
from bus_agent.cia402.states import State
from bus_agent.sim.control import SimControl, SimControlError, parse_control_key, sim_inject
from bus_agent.gateway.zenoh_config import make_zenoh_config

pytestmark = pytest.mark.timeout(60)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    port = free_port()
    server = zenoh.open(make_zenoh_config("peer", listen=[f"tcp/127.0.0.1:{port}"]))
    client = zenoh.open(make_zenoh_config("peer", connect=[f"tcp/127.0.0.1:{port}"]))
    yield server, client
    client.close()
    server.close()


def wait_served(client: zenoh.Session, segment: str, deadline_s: float = 10.0) -> None:
    """Wait until the client's queries reach the segment's queryable (routes propagate async)."""
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        try:
            sim_inject(client, segment, 0, "wkc_fault", on=False, timeout_s=0.5)
            return
        except SimControlError as exc:
            if "no simulator answered" not in str(exc):
                raise
    raise AssertionError(f"segment {segment} not reachable within {deadline_s} s")


@pytest.fixture()
def served(sessions: tuple[zenoh.Session, zenoh.Session], request: pytest.FixtureRequest):
    server, client = sessions
    segment = "seg" + str(abs(hash(request.node.name)) % 100000)
    bus = SimBus(3, segment_name=segment, clock=lambda: 0.0)
    bus.open()
    bus.start()
    ctl = SimControl(server, segment, bus.control_handlers(), n_slaves=3)
    wait_served(client, segment)
    yield bus, client, segment
    ctl.close()
    ctl.close()


def test_fault_injection_reaches_the_model(served) -> None:
    bus, client, seg = served
    assert sim_inject(client, seg, 1, "fault", error_code=0x7500) == ["slave 1: fault 0x7500 injected"]
    assert bus.model(1).state is State.FAULT_REACTION_ACTIVE
    assert bus.model(1).error_code == 0x7500
    assert bus.model(0).state is not State.FAULT_REACTION_ACTIVE


def test_unplug_plug_and_wkc_fault(served) -> None:
    bus, client, seg = served
    sim_inject(client, seg, 2, "unplug")
    assert bus.read_al_status()[2].state is ALState.NONE
    sim_inject(client, seg, 2, "plug")
    assert bus.read_al_status()[2].state is ALState.INIT
    sim_inject(client, seg, 0, "wkc_fault", on=True)
    assert bus.exchange() == 3  # slave 0 lost, slave 2 in INIT


def test_wildcard_slave_hits_every_slave(served) -> None:
    bus, client, seg = served
    details = sim_inject(client, seg, "*", "fault", error_code=0x1000)
    assert sorted(details) == [f"slave {i}: fault 0x1000 injected" for i in range(3)]
    assert all(bus.model(i).error_code == 0x1000 for i in range(3))


@pytest.mark.parametrize("slave, action, args, message", [
    (0, "explode", {}, "unknown action"),
    (7, "fault", {"error_code": 0x1000}, "no such slave"),
    (0, "fault", {}, "error_code"),
    (0, "fault", {"error_code": "0x1000"}, "error_code"),
    (0, "fault", {"error_code": 0}, "1..0xFFFF"),
    (0, "wkc_fault", {"on": 1}, "on"),
    (0, "unplug", {"now": True}, "no arguments"),
])
def test_bad_requests_get_clear_errors_and_change_nothing(served, slave, action, args, message) -> None:
    bus, client, seg = served
    before = [bus.model(i).state for i in range(3)]
    with pytest.raises(SimControlError, match=message):
        sim_inject(client, seg, slave, action, **args)
    assert [bus.model(i).state for i in range(3)] == before
    assert all(s.state is ALState.OP for s in bus.read_al_status())


def test_non_msgpack_payload_refused(served) -> None:
    bus, client, seg = served
    replies = list(client.get(f"drives/@sim/{seg}/0/fault", payload=b"\xc1", timeout=2))
    assert len(replies) == 1 and replies[0].err is not None
    assert "msgpack" in msgpack.unpackb(replies[0].err.payload.to_bytes())["error"]


def test_handlers_run_off_the_zenoh_thread(sessions) -> None:
    server, client = sessions
    seen: list[str] = []

    def probe(position: int, args: dict) -> str:
        seen.append(threading.current_thread().name)
        return "ok"

    ctl = SimControl(server, "probe", {"probe": probe, "wkc_fault": lambda p, a: "ok"}, n_slaves=1)
    try:
        wait_served(client, "probe")
        assert sim_inject(client, "probe", 0, "probe") == ["ok"]
        assert seen == ["sim-control-probe"]
    finally:
        ctl.close()


def test_no_simulator_answers(sessions) -> None:
    _, client = sessions
    with pytest.raises(SimControlError, match="no simulator answered"):
        sim_inject(client, "nobody", 0, "fault", error_code=1, timeout_s=0.3)


def test_parse_control_key() -> None:
    assert parse_control_key("drives/@sim/s/3/fault", "s") == ("3", "fault")
    with pytest.raises(ValueError):
        parse_control_key("drives/@v1/s/3/fault", "s")
    assert parse_control_key("drives/@sim/*/*/unplug", "s") == ("*", "unplug")
    for bad in ("drives/@sim/s/3", "drives/@sim/s/x/fault", "drives/@sim/s/3/*", "drives/@sim/t/3/fault"):
        with pytest.raises(ValueError):
            parse_control_key(bad, "s")


def test_wildcard_segment_and_action_queries(served) -> None:
    bus, client, seg = served
    replies = list(client.get("drives/@sim/*/1/fault", payload=msgpack.packb({"error_code": 0x1234}), timeout=2))
    assert [msgpack.unpackb(r.ok.payload.to_bytes())["ok"] for r in replies if r.ok is not None] == [True]
    assert bus.model(1).error_code == 0x1234
    replies = list(client.get(f"drives/@sim/{seg}/1/*", timeout=2))
    assert replies and all(r.err is not None for r in replies)  # an action must be named
