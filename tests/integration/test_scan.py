"""``bus-agent scan`` against ``ecat-sim`` profiles over a veth pair (root): never beyond PRE-OP."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from bus_agent.bus.scan import render_text, scan_segment
from bus_agent.config import config_from_dict
from tests.integration.test_real_drives import _slaves

pytestmark = [pytest.mark.root, pytest.mark.timeout(120)]
ROOT = Path(__file__).resolve().parents[2]
ALL_MODES = (1, 3, 4, 6, 8, 9, 10)


def test_scan_reports_each_profile(ecat_segment):
    ifname, control = ecat_segment(3, "generic,omron1s:dc,roassign")
    scans = scan_segment(ifname)
    assert [s.position for s in scans] == [0, 1, 2]
    assert [s.dc for s in scans] == [False, True, False]
    assert all(s.mailbox == ("CoE",) and s.modes == ALL_MODES and not s.errors for s in scans)
    assert [s.product_code for s in scans] == [0x00402001, 0x00402101, 0x00402102]
    assert [s.serial for s in scans] == [1, 2, 3]
    g, o, r = (s.mapping for s in scans)
    assert g.rx_pdos == (0x1600,) and g.tx_pdos == (0x1A00,) and (g.out_bytes, g.in_bytes) == (13, 15)
    assert o.rx_pdos == (0x1701,) and o.tx_pdos == (0x1B01,) and (o.out_bytes, o.in_bytes) == (12, 28)
    assert [(e.index, e.subindex, e.bit_offset, e.bits) for e in o.rx] == [
        (0x6040, 0, 0, 16), (0x607A, 0, 16, 32), (0x60B8, 0, 48, 16), (0x60FE, 1, 64, 32)]
    assert [(e.name, e.bit_offset) for e in o.tx][-1] == ("digital_inputs", 192)
    assert r.rx_pdos == (0x1600,)
    text = render_text(scans)
    assert "slave 1 'SimPredefined1S'" in text and "bit  192 +32 0x60FD:00 digital_inputs" in text
    assert all(s["al_state"] == "preop" for s in _slaves(control))  # never beyond PRE-OP

    # the CLI: --json, and --toml blocks the agent's configuration accepts as they are
    out = subprocess.run([sys.executable, "-m", "bus_agent.cli", "scan", "--ifname", ifname, "--json"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert [s["tx_pdos"] for s in doc["slaves"]] == [[0x1A00], [0x1B01], [0x1A00]]
    out = subprocess.run([sys.executable, "-m", "bus_agent.cli", "scan", "--ifname", ifname, "--toml"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    cfg = config_from_dict({"host": "h1", "ifname": ifname, **tomllib.loads(out.stdout)})
    assert [(d.slave, d.mode, d.identity.product_code) for d in cfg.drives] == [
        (0, 8, 0x00402001), (1, 8, 0x00402101), (2, 8, 0x00402102)]


def test_scan_of_an_unreadable_segment_is_a_clear_error(ecat_segment):
    out = subprocess.run([sys.executable, "-m", "bus_agent.cli", "scan", "--ifname", "zdnosuchif0"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 3 and "zdnosuchif0: cannot open the interface" in out.stderr, out.stderr


def test_an_upload_without_answer_is_named_and_the_rest_still_read(ecat_segment):
    """0x6502 of slave 1 gets no answer: the scan says which upload and why, and reads the
    identity and the mapping of every slave all the same."""
    ifname, control = ecat_segment(2)
    assert control.request("mute_sdo", slave=1, index=0x6502, subindex=0, skip=0, count=1)["ok"]
    scans = scan_segment(ifname)
    assert not scans[0].errors and scans[0].modes == ALL_MODES
    assert scans[1].errors == ("0x6502 supported drive modes: SDO upload 0x6502:00: WkcError: no answer from "
                               "the slave's mailbox",)
    assert [s.serial for s in scans] == [1, 2] and all((s.mapping.out_bytes, s.mapping.in_bytes) == (13, 15)
                                                      for s in scans)
