"""A mixed fleet: an EtherCAT agent (pysoem over a veth pair to ``ecat-sim``) and a CAN agent
(``bus-agent --can ... --nodes 1,2`` to ``canopen-sim``) enabled and disabled together by one
supervisor; and ``bus-agent scan --can`` listing the CAN nodes (identity, PDO mappings) first.
All processes live in one namespace of the test's own (CAN frames and EtherCAT frames stay in it);
the agents are Zenoh peers (c1 connects to e1) and the supervisor reaches them over a UNIX socket."""

from __future__ import annotations

import json
import os
import sys
from typing import Iterator

import pytest

from bus_agent.sim.netns import pair_names, veth_down, veth_up
from supervisor.fleet import Fleet
from tests.conftest import require_root
from tests.system.canbed import CHANNEL, CanBed

pytestmark = [pytest.mark.root, pytest.mark.slow]


@pytest.fixture(scope="module")
def bed() -> Iterator[CanBed]:
    require_root()
    b = CanBed("m")
    master, sim = pair_names(f"zcm{os.getpid() % 10000}", 0)
    try:
        veth_up(master, sim, master_netns=b.netns, sim_netns=b.netns)
        # SCHED_FIFO: on a loaded host a normal-priority ecat-sim answers too late for start-up
        b.module("ecat-sim", "bus_agent.sim.cli", "--ifname", sim, "--drives", "2", "--rt-priority", "20",
                 ready="ecat-sim ready")
        b.module("canopen-sim", "bus_agent.sim.canopen.cli", "--channel", CHANNEL, "--interface", "udp_multicast",
                 "--nodes", "2", ready="canopen-sim ready")
        b.ecat_master = master  # type: ignore[attr-defined]
        yield b
    finally:
        b.close()
        veth_down(master, b.netns)


def test_scan_lists_the_nodes_with_identity_and_mappings(bed: CanBed) -> None:
    r = bed.run(sys.executable, "-m", "bus_agent.cli", "scan", "--can", CHANNEL, "--can-interface", "udp_multicast",
                "--json")
    assert r.returncode == 0, r.stdout + r.stderr
    nodes = {n["node_id"]: n for n in json.loads(r.stdout)["nodes"]}
    assert sorted(nodes) == [1, 2]
    n2 = nodes[2]
    assert (n2["vendor_id"], n2["product_code"], n2["serial"], n2["device_type"]) == (0xABC, 0x00402001, 2, 0x00020192)
    assert n2["name"] == "SimDrive402" and n2["error"] == ""
    assert [p["cob_id"] for p in n2["tpdo"]] == [0x182, 0x282]
    assert n2["tpdo"][0]["entries"] == ["0x6041:0/16", "0x6064:0/32", "0x6061:0/8"]
    r = bed.run(sys.executable, "-m", "bus_agent.cli", "scan", "--can", CHANNEL, "--can-interface", "udp_multicast",
                "--nodes", "5")
    assert r.returncode == 1 and "no CANopen node answered" in r.stdout


def test_mixed_fleet_enabled_together(bed: CanBed) -> None:
    ecat_ep, can_ep = bed.unix_endpoint("e1"), bed.unix_endpoint("c1")
    bed.module("agent e1", "bus_agent.cli", "--host", "e1", "--ifname", bed.ecat_master,  # type: ignore[attr-defined]
               "--listen", ecat_ep, ready="bus-agent ready", timeout_s=60)
    bed.module("agent c1", "bus_agent.cli", "--host", "c1", "--can", CHANNEL, "--can-interface", "udp_multicast",
               "--nodes", "1,2", "--cycle-us", "10000", "--listen", can_ep, "--connect", ecat_ep,
               ready="bus-agent ready", timeout_s=60)
    with Fleet(connect=[can_ep], name="mixed") as fleet:  # one supervisor, both agents through c1's peer link
        assert fleet.wait_for_agents(["e1", "c1"], 20, drives=4)
        assert fleet.wait_until(lambda f: all(a.status is not None for a in f.agents().values()), 10)
        backends = {h: a.status.backend for h, a in fleet.agents().items() if a.status is not None}
        assert backends == {"e1": "pysoem", "c1": "canopen"}, backends
        report = fleet.enable("**", timeout_s=20)
        assert report.ok and len(report.final) == 4, report.failures
        st = fleet.fetch_status("**")
        assert {str(r) for r in st} == {"e1/axis0", "e1/axis1", "c1/axis0", "c1/axis1"}
        assert all(s.state == "operation_enabled" for s in st.values()), st
        report = fleet.disable("**", timeout_s=20)
        assert report.ok, report.failures
        assert all(s.state == "switch_on_disabled" for s in fleet.fetch_status("**").values())
