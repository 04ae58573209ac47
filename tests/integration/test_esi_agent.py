"""The agent with the slaves' ESI files (root): ``ecat-sim --esi`` slaves from the project's
hand-written files, the agent given the same files (``[esi]``/``--esi``): each slave matched by
identity, its InitCmds made (the TOML's SDO for the same object wins), vendor objects named and
typed from the ESI, SYNC0 where the file offers only DC, enabled without a jump; an identity
that matches no device stops start-up with the reason."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from bus_agent.bus.esi_setup import EsiMatchError
from bus_agent.bus.mapping import StartupSdo
from bus_agent.config import DriveConfig, EsiConfig
from tests.integration.test_real_drives import Agent, _slaves, _wait

pytestmark = [pytest.mark.root, pytest.mark.timeout(90)]

ESI_DIR = Path(__file__).resolve().parents[1] / "esi"


def test_agent_matches_esi_devices_makes_init_cmds_and_names_vendor_objects(ecat_segment):
    ifname, control = ecat_segment(2, esi=(f"{ESI_DIR / 'quirks.xml'}", f"{ESI_DIR / 'configurable.xml'}"))
    drives = (DriveConfig(slave=0), DriveConfig(slave=1, sdos=(StartupSdo(0x2100, 0, "u16", 1000),)))
    agent = Agent(ifname, esi=EsiConfig(str(ESI_DIR)), drives=drives)
    agent.cycle.start()
    try:
        _wait(lambda: agent.cycle.latest is not None and all(d.mode_display == 8 for d in agent.cycle.latest.drives),
              20, "both drives in OP with mode 8")
        slaves = _slaves(control)
        assert [s["al_state"] for s in slaves] == ["op", "op"]
        assert slaves[0]["dc"]["sync0"]  # the quirk file offers only the DC op mode
        # InitCmds: quirk PS 0x2001 = 300; configurable's 0x2100 InitCmd yields to the TOML's 1000
        assert struct.unpack("<H", agent.bus.sdo_read(0, 0x2001, 0, 2))[0] == 300
        assert struct.unpack("<H", agent.bus.sdo_read(1, 0x2100, 0, 2))[0] == 1000
        assert agent.bus.sdo_read(1, 0x2102, 0, 1) == b"\x02"  # the SO InitCmd, made in SAFE-OP
        d1 = agent.drive("axis1")
        assert dict(zip(d1.object_names, d1.objects)) == {"Motor temperature": -12}  # ESI name, INT decoded
        before = [d.position for d in agent.cycle.latest.drives]
        outs = agent.cmd("enable", "axis0", "axis1")
        assert all(o.outcome == "done" for o in outs), outs
        after = [d.position for d in agent.cycle.latest.drives]
        assert after == before  # no jump
        # a power cycle forgets the InitCmds' values: made again before the slave returns to OP
        assert control.request("unplug", slave=1)["ok"]
        _wait(lambda: agent.drive("axis1").lost, 10, "axis1 lost")
        assert control.request("plug", slave=1)["ok"]
        _wait(lambda: not agent.drive("axis1").lost and agent.drive("axis1").al_state == "op", 30, "axis1 back in OP")
        assert agent.bus.sdo_read(1, 0x2102, 0, 1) == b"\x02"  # SO
        assert struct.unpack("<H", agent.bus.sdo_read(1, 0x2100, 0, 2))[0] == 1000  # the TOML's, not the InitCmd
    finally:
        agent.cycle.stop()


def test_an_identity_matching_no_esi_device_stops_start_up(ecat_segment):
    ifname, _control = ecat_segment(1, "generic")
    agent = Agent(ifname, esi=EsiConfig(str(ESI_DIR / "quirks.xml")))
    with pytest.raises(EsiMatchError, match=r"slave 0 \('SimDrive402'\): identity vendor 0x00000ABC product "
                                            r"0x00402001 revision 0x00010000 matches no device in the ESI"):
        agent.cycle.open()


def test_scan_names_the_esi_device_and_where_the_mapping_differs(ecat_segment):
    import json
    import subprocess
    import sys

    import pysoem

    ifname, _control = ecat_segment(3, esi=(f"{ESI_DIR / 'quirks.xml'}", f"{ESI_DIR / 'configurable.xml'}",
                                             f"{ESI_DIR / 'quirks.xml'}@0x00402200"))  # the boot loader
    m = pysoem.Master()
    m.open(ifname)
    try:
        assert m.config_init() == 3
        m.slaves[1].sdo_write(0x1A00, 0, b"\4")  # the vendor object left out of the TxPDO
    finally:
        m.close()
    out = subprocess.run([sys.executable, "-m", "bus_agent.cli", "scan", "--ifname", ifname, "--json",
                          "--esi", str(ESI_DIR)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    slaves = json.loads(out.stdout)["slaves"]
    assert [s["esi_device"] for s in slaves] == ["Quirk servo (predefined)", "Configurable drive", "Quirk boot loader"]
    assert slaves[0]["esi_differences"] == []
    assert [e["name"] for e in slaves[0]["rx"]][:3] == ["target_position", "Brake release", "padding"]  # ESI names
    assert slaves[2]["mailbox"] == ["FoE"] and slaves[2]["errors"] == []  # no CoE in its ESI: none simulated
    assert slaves[1]["esi_differences"] == [
        "TxPDO (0x1C13) 0x1A00 maps [6041:00/16 6064:00/32 606C:00/32 6061:00/8]; the ESI default is "
        "[6041:00/16 6064:00/32 606C:00/32 6061:00/8 2101:00/16]"]
    out = subprocess.run([sys.executable, "-m", "bus_agent.cli", "scan", "--ifname", ifname,
                          "--esi", str(ESI_DIR / "configurable.xml")], capture_output=True, text=True, timeout=60)
    assert out.returncode == 4
    assert "slave 0 ('Quirk servo (predefined)'): identity vendor 0x00000ABC product 0x00402201 revision " \
           "0x00020000 matches no device in the ESI" in out.stderr
