"""The CANopen backend for real: ``canopen-sim`` (3 nodes) and ``bus-agent`` with a ``[can]``
configuration as separate processes exchanging CAN frames (python-can udp_multicast) in a
namespace of their own (only ``lo``: no frame leaves it). ``drivectl`` runs in the namespace over
TCP; the test's own supervisor (``Fleet``) and fault injection reach in over UNIX sockets.

Covered: the three PDO policies (drive, explicit without the mode objects, default) each carry a
drive to Operation enabled; the SYNC counter (0x1019 = 5) seen by a plain python-can listener and checked by every
node; NMT stop/pre-operational/start/reset communication/reset node as frames on COB-ID
0x000 seen by a plain python-can listener; a node's heartbeat lost and back (lost, the group
reacts; back to operational, never re-enabled); an EMCY to fault with its error text.
"""

from __future__ import annotations

import ast
import time
from typing import Iterator

import pytest
import zenoh

from bus_agent.bus.pdo import mapping_entry as me
from bus_agent.gateway.zenoh_config import make_zenoh_config
from bus_agent.sim.child import free_port, wait_for
from bus_agent.sim.control import sim_inject
from supervisor.fleet import Fleet
from tests.conftest import require_root
from tests.system.canbed import CHANNEL, CanBed

pytestmark = [pytest.mark.root, pytest.mark.slow]

# node 2: its own layout, PDO 1 and 2 regrouped (written by the agent at start-up and after a reset),
# without the mode (0x6060/0x6061): the cycle serves it by SDO, as for an EtherCAT drive
EXPLICIT_RPDO = [[me(0x6040, 0, 16)], [me(0x607A, 0, 32), me(0x60FF, 0, 32)]]
EXPLICIT_TPDO = [[me(0x6041, 0, 16), me(0x603F, 0, 16)], [me(0x6064, 0, 32), me(0x606C, 0, 32)]]
SYNC_COUNTER = 5
AXES = ("c2/axis0", "c2/axis1", "c2/axis2")


def _toml(listen: list[str]) -> str:
    return f"""
host = "c2"
cycle_us = 10000
[zenoh]
listen = {listen!r}
[defaults]
fault_reset_retries = 10
[can]
channel = "{CHANNEL}"
interface = "udp_multicast"
heartbeat_ms = 200
sync_counter = {SYNC_COUNTER}
nodes = [{{ id = 1, pdo = "drive" }},
         {{ id = 2, pdo = "explicit", rpdo = {EXPLICIT_RPDO}, tpdo = {EXPLICIT_TPDO} }},
         {{ id = 3, pdo = "default", sdo = [{{ index = 0x605A, value = 2, size = 2 }}] }}]
[groups]
pair = ["c2/axis0", "c2/axis1"]
""".replace("'", '"')


class Bed:
    def __init__(self, can: CanBed, tcp: str, fleet: Fleet, sim: zenoh.Session) -> None:
        self.can, self.tcp, self.fleet, self.sim = can, tcp, fleet, sim

    def row(self, axis: str):
        st = self.fleet.fetch_status(axis)
        assert len(st) == 1, st
        return next(iter(st.values()))

    def inject(self, position: int, action: str, **args: object) -> list[str]:
        return sim_inject(self.sim, "cansim", position, action, timeout_s=10, **args)

    def counters(self, position: int) -> dict[str, int]:
        """The simulated node's frame counters (its ``status``)."""
        (detail,) = self.inject(position, "status")
        return ast.literal_eval(detail.split(" counters ", 1)[1])


@pytest.fixture(scope="module")
def bed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Bed]:
    require_root()
    b = CanBed("a")
    try:
        sim_ep = b.unix_endpoint("sim")
        b.module("canopen-sim", "bus_agent.sim.canopen.cli", "--channel", CHANNEL, "--interface", "udp_multicast",
                 "--nodes", "3", "--name", "cansim", "--zenoh-listen", sim_ep, ready="canopen-sim ready")
        tcp, unix = f"tcp/127.0.0.1:{free_port()}", b.unix_endpoint("agent")
        cfg = tmp_path_factory.mktemp("can") / "agent.toml"
        cfg.write_text(_toml([tcp, unix]))
        b.module("agent c2", "bus_agent.cli", "--config", str(cfg), ready="bus-agent ready", timeout_s=60)
        sim = zenoh.open(make_zenoh_config("client", (), [sim_ep]))
        with Fleet(connect=[unix], name="cantest") as fleet:
            assert fleet.wait_for_agents(["c2"], 20, drives=3)
            yield Bed(b, tcp, fleet, sim)
        sim.close()
    finally:
        b.close()


def test_pdo_policies_and_drivectl_enable_disable(bed: Bed) -> None:
    agent = next(c for c in bed.can.children if c.name == "agent c2")
    text = agent.output(300)
    assert ("node 1: configured, PDO policy drive: RxPDO 0x1600@0x201 [6040 607A 6060] 0x1601@0x301 [60FF 6071], "
            "TxPDO 0x1A00@0x181 [6041 6064 6061] 0x1A01@0x281 [606C 6077 603F]") in text
    assert ("node 2: configured, PDO policy explicit: RxPDO 0x1600@0x202 [6040] 0x1601@0x302 [607A 60FF], "
            "TxPDO 0x1A00@0x182 [6041 603F] 0x1A01@0x282 [6064 606C]") in text
    assert "axis axis1 (slave 1): not mapped, served by SDO: 0x6060, 0x6061" in text
    assert "node 3: configured, PDO policy default" in text
    assert all(bed.row(a).state == "switch_on_disabled" for a in AXES)   # nobody asked: nothing enabled
    rc, out = bed.can.drivectl(bed.tcp, "enable", "c2/*")
    assert rc == 0, out
    assert all(bed.row(a).state == "operation_enabled" and bed.row(a).al_state == "op" for a in AXES)
    assert all(bed.row(a).mode_display == 8 for a in AXES)          # node 2's by SDO (0x6061)
    rc, out = bed.can.drivectl(bed.tcp, "disable", "c2/*")
    assert rc == 0, out
    assert all(bed.row(a).state == "switch_on_disabled" for a in AXES)


def test_sync_counter_on_the_bus_and_checked_by_the_nodes(bed: Bed) -> None:
    before = [bed.counters(p) for p in range(3)]
    log = bed.can.listener()
    wait_for(lambda: len([f for f in log.frames() if f[0] == 0x080]) >= 3 * SYNC_COUNTER, 20, "SYNC frames")
    counters = [data for cob, data in log.frames() if cob == 0x080]
    assert all(len(d) == 1 for d in counters), counters[:10]         # one byte: the counter
    values = [d[0] for d in counters]
    assert set(values) == set(range(1, SYNC_COUNTER + 1))
    # each the one after the previous, N back to 1 (a listener on a loaded host may miss a frame: the
    # datagrams are its only record, so allow a gap but never a wrong step where none was missed)
    steps = [(b - a) % SYNC_COUNTER for a, b in zip(values, values[1:])]
    assert steps.count(1) >= len(steps) - 2, values
    after = [bed.counters(p) for p in range(3)]
    for b, a in zip(before, after):
        assert a["sync"] > b["sync"]
        assert (a["sync_counter_errors"], a["sync_length_errors"]) == (b["sync_counter_errors"], b["sync_length_errors"])


def test_nmt_frames_on_the_bus(bed: Bed) -> None:
    log = bed.can.listener()
    # (nmt command, NMT command specifier on 0x000, AL state reported afterwards)
    for command, specifier, al in (("stop", 0x02, "safeop"), ("preop", 0x80, "preop"), ("start", 0x01, "op"),
                                   ("reset_comm", 0x82, "preop"), ("reset_node", 0x81, "op")):
        mark = len(log.frames())
        result = bed.fleet.nmt(command, ["c2"], timeout_s=20)
        assert result.ok, f"nmt {command}: {result.failures}"
        for node in (1, 2, 3):
            log.wait_frame(0x000, bytes((specifier, node)), after=mark)
            if command.startswith("reset"):  # the node reboots (its communication): boot-up message
                log.wait_frame(0x700 + node, b"\x00", after=mark)
        wait_for(lambda: all(bed.row(a).al_state == al for a in AXES), 20, f"al_state {al} after nmt {command}")
    assert bed.fleet.nmt("start", ["c2"], timeout_s=20).ok
    mark = len(log.frames())
    log.wait_frame(0x080, None, after=mark)           # SYNC flows again
    log.wait_frame(0x182, None, after=mark)           # and node 2's TPDO, mapped again after its reset
    assert bed.fleet.enable("c2/axis1", timeout_s=20).ok
    assert bed.fleet.disable("c2/*", timeout_s=20).ok


def test_heartbeat_loss_and_return(bed: Bed) -> None:
    assert bed.fleet.enable("c2/axis0", "c2/axis1", timeout_s=20).ok
    bed.inject(1, "unplug")                           # node 2 falls silent: no heartbeat, no TPDO
    wait_for(lambda: bed.row("c2/axis1").lost, 20, "axis1 lost")
    assert bed.row("c2/axis1").al_state == "none"
    # its group partner is taken out of Operation enabled by the reflex (quick stop)
    wait_for(lambda: bed.row("c2/axis0").state in ("switch_on_disabled", "quick_stop_active"), 20,
             "axis0 stopped by the group reflex")
    bed.inject(1, "plug")                             # boots again (boot-up), pre-operational
    wait_for(lambda: not bed.row("c2/axis1").lost and bed.row("c2/axis1").al_state == "op", 30,
             "axis1 back in operational")
    deadline = time.monotonic() + 1.5
    while time.monotonic() < deadline:                # never re-enabled without a command
        assert bed.row("c2/axis1").state != "operation_enabled"
    assert bed.fleet.enable("c2/axis1", timeout_s=20).ok  # a new command enables it again
    assert bed.fleet.disable("c2/*", timeout_s=20).ok


def test_emcy_to_fault_with_error_text(bed: Bed) -> None:
    assert bed.fleet.enable("c2/axis2", timeout_s=20).ok
    bed.inject(2, "fault", error_code=0x2310)
    wait_for(lambda: bed.row("c2/axis2").state == "fault", 20, "axis2 in fault")
    row = bed.row("c2/axis2")
    assert row.error_code == 0x2310 and row.error_text == "continuous over-current"
    assert bed.fleet.fault_reset("c2/axis2", timeout_s=20).ok
    assert bed.row("c2/axis2").state == "switch_on_disabled"
