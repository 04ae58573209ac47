"""Plain pysoem against ``ecat-sim --esi`` (root): the simulator is what the ESI file says.

Files are the project's own: the ESI ``ecat-sim --write-esi`` writes for the built-in profiles
(round trip: pysoem configures the ESI slaves exactly as the built-in ones) and the
hand-written tests/esi/quirks.xml (docs/device-files.md). No project master code here.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import time
from pathlib import Path

import pysoem
import pytest

from bus_agent.devices.esi import load_esi
from bus_agent.sim.ecat.profiles import PROFILES

pytestmark = [pytest.mark.root, pytest.mark.timeout(90)]

ROOT = Path(__file__).resolve().parents[2]
QUIRKS = ROOT / "tests" / "esi" / "quirks.xml"


def _abort_code(slave, index: int, sub: int, data: bytes | None = None) -> int:
    try:
        if data is None:
            slave.sdo_read(index, sub)
        else:
            slave.sdo_write(index, sub, data)
    except pysoem.SdoError as exc:
        return exc.abort_code
    raise AssertionError(f"0x{index:04X}:{sub} was not refused")


def _configure(ifname: str, n: int, map_: bool = True):
    m = pysoem.Master()
    m.open(ifname)
    assert m.config_init() == n
    if map_:
        m.config_map()
    return m


def _picture(m) -> list[tuple]:
    """What a master learns while configuring: identity, SII name, image sizes, mapping by SDO."""
    out = []
    for s in m.slaves:
        mapping = []
        for assign in (0x1C12, 0x1C13):
            n = s.sdo_read(assign, 0)[0]
            for k in range(1, n + 1):
                pdo = struct.unpack("<H", s.sdo_read(assign, k))[0]
                count = s.sdo_read(pdo, 0)[0]
                mapping.append((pdo, [struct.unpack("<I", s.sdo_read(pdo, j))[0] for j in range(1, count + 1)]))
        out.append((s.man, s.id, s.rev, s.name, len(s.output), len(s.input), mapping,
                    struct.unpack("<I", s.sdo_read(0x1000, 0))[0], s.sdo_read(0x1008, 0)))
    return out


def test_write_esi_round_trip_configures_like_the_built_in_profiles(ecat_segment, tmp_path):
    path = tmp_path / "builtin.xml"
    subprocess.run([sys.executable, "-m", "bus_agent.sim.cli", "--write-esi", str(path)], check=True, cwd=ROOT,
                   capture_output=True)
    devices = load_esi(path)
    assert [d.product_code for d in devices] == [p.drive.product_code for p in PROFILES.values()]
    specs = tuple(f"{path}@#x{p.drive.product_code:08X}" for p in PROFILES.values())
    built_in, _ = ecat_segment(len(PROFILES), ",".join(PROFILES))
    from_esi, _ = ecat_segment(len(PROFILES), esi=specs)
    pictures = []
    for ifname in (built_in, from_esi):
        m = _configure(ifname, len(PROFILES))
        try:
            pictures.append(_picture(m))
        finally:
            m.close()
    assert pictures[0] == pictures[1]
    assert [p[3] for p in pictures[1]] == [p.drive.device_name for p in PROFILES.values()]


def test_quirk_file_slave_as_its_esi_says(ecat_segment):
    ifname, control = ecat_segment(2, esi=(f"{QUIRKS}*2",))  # default: the first device with CiA 402
    m = _configure(ifname, 2, map_=False)
    try:
        s = m.slaves[0]
        # in PRE-OP: the assignment is writable, <Exclude> refuses a clash (the file's PDO
        # 0x1600 has no entries: the user's to map)
        s.sdo_write(0x1C12, 0, b"\0")
        s.sdo_write(0x1C12, 1, struct.pack("<H", 0x1702))
        assert _abort_code(s, 0x1C12, 2, struct.pack("<H", 0x1600)) == 0x06040043
        s.sdo_write(0x1C12, 1, struct.pack("<H", 0x1701))
        s.sdo_write(0x1C12, 0, b"\1")
        m.config_map()
        assert (s.man, s.id, s.rev) == (0xABC, 0x00402201, 0x00020000)
        assert s.name == "Quirk servo (predefined)"
        # 0x1701: 32 + 1 + 7 padding + 16 bits; 0x1B01: 16 + 32 + 1 + 7 + 8 + 32 + 16 bits
        assert (len(s.output), len(s.input)) == (7, 14)
        assert struct.unpack("<H", s.sdo_read(0x2001, 0))[0] == 250  # DefaultData in decimal
        assert struct.unpack("<H", s.sdo_read(0x1C12, 1))[0] == 0x1701  # DefaultData byte-swapped
        assert struct.unpack("<I", s.sdo_read(0x6065, 0))[0] == 100_000  # DefaultValue #x
        assert struct.unpack("<I", s.sdo_read(0x1000, 0))[0] == 0x00060192
        assert _abort_code(s, 0x603F, 0) == 0x06020000  # not in this dictionary
        assert s.sdo_read(0x1C00, 0) == b"\x04"  # omitted by the file, served as every CoE slave does
        assert _abort_code(s, 0x1701, 0, b"\0") == 0x06010002  # Fixed: read-only mapping
        assert _abort_code(s, 0x1C13, 0, b"\0") == 0x06010002  # the dictionary makes 0x1C13 ro
        # only a DC op mode offered: OP without SYNC0 is refused with AL 0x0030
        assert m.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
        m.send_processdata()
        m.receive_processdata(2000)
        m.state = pysoem.OP_STATE
        m.write_state()
        deadline = time.monotonic() + 2
        while time.monotonic() < deadline:
            m.send_processdata()
            m.receive_processdata(2000)
            m.read_state()
            if s.state & 0x10 and s.al_status == 0x0030:
                break
            time.sleep(0.005)
        assert s.state & 0x10 and s.al_status == 0x0030, (s.state, hex(s.al_status))
    finally:
        m.close()


def test_configurable_file_sdo_information_complete_access_and_remapping(ecat_segment):
    path = ROOT / "tests" / "esi" / "configurable.xml"
    ifname, _control = ecat_segment(1, esi=(f"{path}@4203265:3",))
    m = _configure(ifname, 1, map_=False)
    try:
        s = m.slaves[0]
        assert (s.man, s.id, s.rev, s.name) == (0xABC, 4203265, 3, "Configurable drive")
        assert struct.unpack("<h", s.sdo_read(0x2101, 0))[0] == -12
        assert struct.unpack("<I", s.sdo_read(0x6502, 0))[0] == 0  # as the file says
        # complete access (CompleteAccess="true"): subindex 0 as 16 bits, then the entries
        assert s.sdo_read(0x1A00, 0, ca=True) == struct.pack("<BxIIIII", 5, 0x60410010, 0x60640020, 0x606C0020,
                                                                  0x60610008, 0x21010010)
        # SDO information (SdoInfo="true"): the file's dictionary, names included; with its
        # 48-byte mailbox the object list comes in fragments, which SOEM puts together
        od = {obj.index: obj for obj in s.od}
        assert od[0x2100].name in ("Current limit", b"Current limit")
        assert od[0x2101].data_type == 0x0003  # INT
        assert [e.name for e in od[0x1A00].entries][:2] in (["Number of entries", "Entry 1"], [b"Number of entries", b"Entry 1"])
        assert 0x603F in od and 0x6098 not in od  # the model's own objects stay internal
        # Fixed="0": the TxPDO is the master's to map (here: the vendor object moved up)
        s.sdo_write(0x1A00, 0, b"\0")
        s.sdo_write(0x1A00, 4, struct.pack("<I", 0x21010010))
        s.sdo_write(0x1A00, 5, struct.pack("<I", 0x60610008))
        s.sdo_write(0x1A00, 0, b"\5")
        m.config_map()
        assert (len(s.output), len(s.input)) == (7, 13)
        assert m.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
        m.send_processdata()
        m.receive_processdata(2000)
        assert struct.unpack_from("<h", s.input, 10)[0] == -12  # the vendor object in the image
    finally:
        m.close()


def test_a_file_without_coe_maps_from_the_sii(ecat_segment):
    """An `ethercat xml`-style file (no CoE, no dictionary): the slave answers no CoE, so SOEM
    sizes the process data from the SII's PDO categories (ETG.2010), 1-bit and padding entries
    included; the image carries the drive model's statusword."""
    ifname, _control = ecat_segment(1, esi=(str(ROOT / "tests" / "esi" / "no_coe.xml"),))
    m = _configure(ifname, 1)
    try:
        s = m.slaves[0]
        assert (s.man, s.id, s.name) == (0xABC, 0x00402401, "NoCoeDrive")
        assert (len(s.output), len(s.input)) == (3, 7)  # 16 + 8 bits out; 16 + 16 + 1 + 7 + 8 + 8 bits in
        with pytest.raises(pysoem.MailboxError, match="mailbox protocol is not supported"):
            s.sdo_read(0x1018, 1)  # no CoE
        assert m.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
        m.send_processdata()
        m.receive_processdata(2000)
        error_code, statusword = struct.unpack_from("<HH", s.input)  # the error code comes first
        assert error_code == 0 and statusword & 0x004F in (0x0040, 0x0000)  # switch on disabled / not ready
    finally:
        m.close()
