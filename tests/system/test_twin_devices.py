"""drives-twin running the drives its fleet file names by their device files.

EDS hosts (no root): ``canopen-sim --eds`` and the agent's CANopen backend on an interface-local
IPv6 multicast group of the host's own, next to a host of built-in simulated drives, one group
across both; faults through canopen-sim's Zenoh control. ESI hosts (root, ecat backend):
``ecat-sim --esi`` with the ESI ``ecat-sim --write-esi`` writes, pysoem on the other end.
The files are the project's own (tests/data/eds, and what the simulators write).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from bus_agent.sim.child import wait_for
from tests.conftest import require_root
from twin import Twin, TwinError

pytestmark = [pytest.mark.timeout(240)]

CLASSIC = Path(__file__).resolve().parents[1] / "data" / "eds" / "classic.eds"


def test_twin_runs_eds_drives_next_to_builtin_ones(tmp_path: Path) -> None:
    sim_eds = tmp_path / "sim.eds"
    subprocess.run([sys.executable, "-m", "bus_agent.sim.canopen.cli", "--write-eds", str(sim_eds)], check=True)
    (tmp_path / "fleet.toml").write_text(
        f'[hosts.can1]\naxes = ["a", "b"]\ndevices = ["{CLASSIC}", "sim.eds"]\n'
        '[hosts.s1]\naxes = ["x"]\n[groups]\ng = ["can1/a", "can1/b", "s1/x"]\n')
    exits: list[str] = []
    with Twin(tmp_path / "fleet.toml", on_unexpected_exit=exits.append) as twin:
        f = twin.fleet
        assert {h: a.status.backend for h, a in f.agents().items() if a.status} == {"can1": "canopen", "s1": "sim"}
        assert f.host_axes() == {"can1": ["a", "b"], "s1": ["x"]}
        nodes = twin.plans["can1"].agent_toml["can"]["nodes"]
        assert [(n["id"], n["eds"], n["pdo"]) for n in nodes] == [(1, str(CLASSIC), "eds"), (2, str(sim_eds), "eds")]
        assert f.enable("@g").ok
        for ref in ("can1/a", "can1/b", "s1/x"):
            twin.wait_state(ref, "operation_enabled", 10)
        assert twin.fault("can1/b", 0x2310)                             # canopen-sim's control, segment can1
        assert twin.wait_state("can1/b", "fault", 10).error_code == 0x2310
        twin.wait_state("s1/x", "switch_on_disabled", 10)               # the group reacts on the other host
        twin.unplug("can1/a")
        assert wait_for(lambda: (st := f.status("can1/a")) is not None and st.lost, 10, "can1/a lost")
        twin.plug("can1/a")
        assert wait_for(lambda: (st := f.status("can1/a")) is not None and not st.lost, 20, "can1/a back")
        assert twin.wait_state("can1/a", "switch_on_disabled", 10)     # back, never re-enabled
        assert exits == []


def test_twin_names_why_an_eds_drive_cannot_run() -> None:
    vendor = CLASSIC.parent / "vendor.eds"   # every RPDO disabled, no 0x607A: the project's layout cannot be mapped
    with pytest.raises(TwinError, match=r"bus-agent v did not become ready \(exit 3\):\n.*PDO policy 'default': "
                                        r"node 1: SDO write 0x1600:2 aborted with 0x06040041"):
        Twin({"hosts": {"v": {"axes": ["a"], "device": str(vendor)}}}, ready_timeout_s=30).start()


def test_ecat_twin_runs_esi_drives(tmp_path: Path) -> None:
    require_root()
    esi = tmp_path / "sim.xml"
    subprocess.run([sys.executable, "-m", "bus_agent.sim.cli", "--write-esi", str(esi)], check=True)
    fleet = {"hosts": {"e1": {"axes": ["p", "q"], "device": str(esi)}}}
    with Twin(fleet, backend="ecat") as twin:
        assert "--esi" in twin.sims["e1"].popen.args and f"{esi}*2" in twin.sims["e1"].popen.args
        f = twin.fleet
        assert f.host_axes() == {"e1": ["p", "q"]}
        assert f.enable("e1/*").ok
        for ref in ("e1/p", "e1/q"):
            twin.wait_state(ref, "operation_enabled", 10)
        assert twin.fault("e1/q", 0x2310)
        assert twin.wait_state("e1/q", "fault", 10).error_code == 0x2310
