"""The CANopen backend for real: ``canopen-sim`` and ``bus-agent --can`` as separate processes
exchanging CAN frames (python-can udp_multicast) in a namespace of their own, ``drivectl`` over
Zenoh, and a plain python-can listener checking the NMT frames on the bus (COB-ID 0x000)."""

from __future__ import annotations

import json
import sys
from typing import Iterator

import pytest

from bus_agent.sim.child import free_port, wait_for
from tests.conftest import require_root
from tests.system.canbed import CHANNEL, CanBed

pytestmark = [pytest.mark.root, pytest.mark.slow]


@pytest.fixture(scope="module")
def bed() -> Iterator[tuple[CanBed, str]]:
    require_root()
    b = CanBed("a")
    try:
        b.module("canopen-sim", "bus_agent.sim.canopen.cli", "--channel", CHANNEL, "--interface", "udp_multicast",
                 "--nodes", "2", ready="canopen-sim ready")
        ep = f"tcp/127.0.0.1:{free_port()}"
        b.module("agent c1", "bus_agent.cli", "--host", "c1", "--can", CHANNEL, "--can-interface", "udp_multicast",
                 "--nodes", "1,2", "--cycle-us", "4000", "--listen", ep, ready="bus-agent ready", timeout_s=60)
        yield b, ep
    finally:
        b.close()


def drivectl(bed: CanBed, ep: str, *args: str) -> tuple[int, str]:
    r = bed.run(sys.executable, "-m", "supervisor.cli", "--connect", ep, *args)
    return r.returncode, r.stdout + r.stderr


def states(bed: CanBed, ep: str) -> dict[str, dict]:
    rc, out = drivectl(bed, ep, "--json", "status")
    assert rc == 0, out
    doc = json.loads(out)
    rows = doc["drives"] if isinstance(doc, dict) else doc
    return {f"{r['host']}/{r['axis']}": r for r in rows}


def test_enable_and_disable_through_drivectl(bed: tuple[CanBed, str]) -> None:
    b, ep = bed
    before = states(b, ep)
    assert set(before) == {"c1/axis0", "c1/axis1"}
    assert all(r["state"] == "switch_on_disabled" for r in before.values()), before
    rc, out = drivectl(b, ep, "enable", "c1/*")
    assert rc == 0, out
    assert all(r["state"] == "operation_enabled" and r["al_state"] == "op" for r in states(b, ep).values())
    rc, out = drivectl(b, ep, "disable", "**")
    assert rc == 0, out
    assert all(r["state"] == "switch_on_disabled" for r in states(b, ep).values())


def test_nmt_frames_on_the_bus(bed: tuple[CanBed, str]) -> None:
    b, ep = bed
    log = b.listener()
    # (drivectl nmt command, NMT command specifier, AL state reported afterwards)
    for command, specifier, al in (("stop", 0x02, "safeop"), ("preop", 0x80, "preop"), ("start", 0x01, "op"),
                                   ("reset_comm", 0x82, "preop")):
        mark = len(log.frames())
        rc, out = drivectl(b, ep, "nmt", command)
        assert rc == 0, f"nmt {command}: {out}"
        for node in (1, 2):
            log.wait_frame(0x000, bytes((specifier, node)), after=mark)
        if command == "reset_comm":  # the node reboots its communication: boot-up message
            for node in (1, 2):
                log.wait_frame(0x700 + node, b"\x00", after=mark)
        wait_for(lambda: all(r["al_state"] == al for r in states(b, ep).values()), 15, f"al_state {al} after {command}")
    rc, out = drivectl(b, ep, "nmt", "start")
    assert rc == 0, out
    # back in operational: SYNC and TPDOs flow again, and a drive enables
    mark = len(log.frames())
    log.wait_frame(0x080, b"", after=mark)
    rc, out = drivectl(b, ep, "enable", "c1/axis1")
    assert rc == 0, out
    assert drivectl(b, ep, "disable", "**")[0] == 0
