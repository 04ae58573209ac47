"""EDS files (bus_agent/devices/eds.py) and canopen-sim nodes built from them (no bus).

The files are the project's own: the EDS ``canopen-sim --write-eds`` writes, and the
hand-written ones in tests/data/eds/, each exercising quirks of vendors' files
(docs/device-files.md, "EDS (CANopen)"; every file's header comment names its quirks).
"""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import pytest
from canopen.sdo import SdoAbortedError

from bus_agent.bus.canopen import pdo
from bus_agent.bus.canopen.nmt import NmtCommand as C, nmt_frame
from bus_agent.bus.canopen.sdo import SdoError
from bus_agent.bus.mapping import MappingError
from bus_agent.bus.pdo import DriveInputs
from bus_agent.bus.pdo import mapping_entry as me
from bus_agent.devices import eds
from bus_agent.sim.canopen import cli as sim_cli
from bus_agent.sim.canopen.dictionary import from_eds
from bus_agent.sim.canopen.node import SimNode
from bus_agent.sim.drive_model import PROFILES

DATA = Path(__file__).resolve().parents[1] / "data" / "eds"
CLASSIC, INTERP, VENDOR = DATA / "classic.eds", DATA / "interpolated.eds", DATA / "vendor.eds"


def _node(path: Path, node_id: int) -> SimNode:
    return SimNode(node_id, dictionary=from_eds(eds.load(path, node_id)), serial=node_id)


def _read(n: SimNode):
    """SDO reads as the agent's client sees them (aborts as SdoError)."""
    def read(i: int, s: int) -> bytes:
        try:
            return n.get_data(i, s)
        except SdoAbortedError as e:
            raise SdoError(n.node_id, "read", i, s, e.code, "abort") from None
    return read


def _abort(fn, *args) -> int:
    with pytest.raises(SdoAbortedError) as e:
        fn(*args)
    return e.value.code


# ---- reading the files ------------------------------------------------------------------------------

def test_classic_quirks_read_as_the_standard_means_them() -> None:
    assert b"\r\n" in CLASSIC.read_bytes()                           # CRLF, as most vendors' files
    d = eds.load(CLASSIC, 5)
    assert (d.vendor_id, d.product_code, d.revision) == (4660, 0x402, 0x00010002)   # decimal vendor number
    assert d.device_type == 0x00420192 and d.cia402                  # 0x42 above the profile: still CiA 402
    rx, tx = d.pdos(False), d.pdos(True)
    assert [(p.cob_id, p.valid) for p in rx] == [(0x205, True), (0x80000305, False), (0x80000405, False),
                                                 (0x80000505, False)]  # "$NODEID + 0x..", "$NodeID", bit 31
    assert rx[0].entries == (me(0x6040, 0, 16),) and rx[3].entries == (me(0x6040, 0, 16), me(0x60FF, 0, 32))
    assert tx[1].cob_id == 0xC0000285 and not tx[1].valid               # bits 31 and 30
    assert d.objects[(0x2000, 0)].default == 5                       # [2000] = $NODEID+0x00
    assert d.objects[(0x1600, 2)].default is None                    # an unused slot without DefaultValue
    access = {k: d.objects[(k, 0)].access for k in (0x6040, 0x6041, 0x6064, 0x607A, 0x1008)}
    assert access == {0x6040: "rw", 0x6041: "ro", 0x6064: "rw", 0x607A: "rw", 0x1008: "ro"}  # rww, RO, rwr, Rw, const
    assert d.name_of(0x1018, 1) == "Identity object: Vendor ID"


def test_other_quirks_identity_from_device_info_and_empty_defaults() -> None:
    d = eds.load(INTERP, 3)
    assert (d.vendor_id, d.product_code, d.revision) == (0xABC0, 0x2C001, 3)   # 0x1018:3 absent: [DeviceInfo]
    assert d.objects[(0x1000, 0)].default is None and not d.cia402   # no default for 0x1000
    assert d.objects[(0x1008, 0)].default is None                    # "DefaultValue=" empty
    assert d.pdos(True)[0].cob_id == 0x40000183 and d.pdos(True)[0].valid     # bit 30 (no RTR): valid
    assert d.pdos(False)[2].entries == () and d.objects[(0x1602, 1)].default == me(0x6040, 0, 16)  # sub 0 = 0
    assert not d.objects[(0x607A, 0)].pdo_mappable
    v = eds.load(VENDOR, 9)
    assert (v.vendor_id, v.product_code, v.revision, v.device_type) == (305419896, 7, 65536, 0x00060192)
    assert v.name_of(0x2101, 0) == "Temperature (°C)"                # Latin-1 text
    assert not any(p.valid for p in v.pdos(False))                   # every RPDO disabled by default


def test_identity_mismatch_names_what_differs() -> None:
    d = eds.load(CLASSIC, 1)
    assert d.identity_mismatch(4660, 0x402, 0x00010002) is None
    assert d.identity_mismatch(0xABC, 0x402001, 1) == ("vendor id 0x00000ABC, the EDS says 0x00001234; product code "
                                                       "0x00402001, the EDS says 0x00000402; revision 0x00000001, "
                                                       "the EDS says 0x00010002")


def test_unusable_files_are_refused_naming_file_and_reason(tmp_path: Path) -> None:
    with pytest.raises(eds.EdsError, match=r"EDS .*nope.eds: cannot read"):
        eds.load(tmp_path / "nope.eds", 1)
    bad = tmp_path / "bad.eds"
    bad.write_text("[1000]\nParameterName=x\nObjectType=0x7\nDataType=0x0007\nAccessType=rx\n")
    with pytest.raises(eds.EdsError, match=r"bad.eds: 0x1000:0 \(x\): AccessType 'rx' is not one of"):
        eds.load(bad, 1)
    bad.write_text("just text\n")
    with pytest.raises(eds.EdsError, match="bad.eds: not a readable EDS"):
        eds.load(bad, 1)
    assert eds.parse_spec("a.eds*3") == ("a.eds", 3) and eds.parse_spec("a.eds") == ("a.eds", 1)
    with pytest.raises(eds.EdsError, match="COUNT 'x' is not a number"):
        eds.parse_spec("a.eds*x")
    with pytest.raises(eds.EdsError, match="not a CiA 402 drive the simulator can run: no 0x6040 and no 0x6041"):
        from_eds(eds.load(_write_nodrive(tmp_path), 1))


def _write_nodrive(tmp_path: Path) -> Path:
    p = tmp_path / "io.eds"
    p.write_text("[1000]\nParameterName=Device type\nObjectType=0x7\nDataType=0x0007\nAccessType=ro\n"
                 "DefaultValue=0x00000191\n")
    return p


# ---- canopen-sim's EDS round trip -------------------------------------------------------------------

def test_written_eds_runs_as_the_builtin_node(tmp_path: Path) -> None:
    path = tmp_path / "sim.eds"
    assert sim_cli.main(["--write-eds", str(path), "--profile", "indy7"]) == 0
    d = eds.load(path, 7)
    p = PROFILES["indy7"]
    assert (d.vendor_id, d.product_code, d.revision, d.product_name) == (p.vendor_id, p.product_code, p.revision,
                                                                         p.device_name)
    builtin, from_file = SimNode(7, p, serial=7), _node(path, 7)
    for key in sorted(set(builtin.dictionary.comm) | set(builtin.dictionary.drive)):
        assert from_file.get_data(*key) == builtin.get_data(*key), key   # every object, the same value
    assert pdo.read_mapping(_read(from_file)) == pdo.default_mapping(7) == pdo.eds_mapping(d)
    assert from_file.model.state == builtin.model.state              # indy7: not ready on power-up, as built in


# ---- a node built from an EDS -----------------------------------------------------------------------

def test_node_serves_what_the_eds_lists_and_aborts_the_rest() -> None:
    n = _node(CLASSIC, 5)
    assert n.get_data(0x1018, 1) == struct.pack("<I", 4660)
    assert n.get_data(0x1018, 4) == struct.pack("<I", 5)               # serial: per node
    assert n.get_data(0x1000, 0) == struct.pack("<I", 0x00420192)
    assert n.get_data(0x2000, 0) == b"\x05"                          # $NODEID default
    assert n.get_data(0x1401, 1) == struct.pack("<I", 0x80000305)
    assert n.get_data(0x605A, 0) == struct.pack("<h", 6)              # EDS default in the drive model
    assert n.model.read(0x605A, 0) == 6
    assert _abort(n.get_data, 0x6071, 0) == 0x06020000               # the model has it, the EDS does not
    assert _abort(n.get_data, 0x6502, 0) == 0x06020000
    assert _abort(n.get_data, 0x1018, 5) == 0x06090011
    assert _abort(n.set_data, 0x1018, 1, b"\0\0\0\0") == 0x06010002
    assert _abort(n.set_data, 0x6064, 0, b"\0\0\0\0") == 0x06010002  # rwr in the EDS, read-only in the model
    n.set_data(0x2000, 0, b"\x09")
    assert n.get_data(0x2000, 0) == b"\x09"
    assert _abort(n.set_data, 0x2000, 0, b"\x09\x00") == 0x06070010
    n.on_frame(0x000, nmt_frame(C.RESET_NODE, 5), 0.0)
    assert n.get_data(0x2000, 0) == b"\x05"                          # power-on default again


def test_node_runs_the_default_pdos_of_its_eds() -> None:
    n = _node(VENDOR, 2)
    read = _read(n)
    assert _abort(n.set_data, 0x2100, 0, struct.pack("<H", 1001)) == 0x06090030   # HighLimit
    n.on_frame(0x000, nmt_frame(C.START, 2), 0.0)
    frames = n.on_frame(0x080, b"", 0.01)
    tpdo = [f for f in frames if f[0] == 0x182]
    assert tpdo == [(0x182, struct.pack("<Hh", n.model.statusword, 25))]   # 6041 + vendor temperature
    assert n.on_frame(0x202, struct.pack("<HH", 6, 300), 0.02) == []  # RPDO1 disabled by default: ignored
    assert n.get_data(0x2100, 0) == struct.pack("<H", 250)
    m = pdo.read_mapping(read)
    assert m.rx_pdos == () and m.tx_pdos == (0x1A00,)


def test_node_applies_rpdos_with_vendor_objects_and_refuses_unmappable_ones() -> None:
    n = _node(INTERP, 4)
    write = lambda i, s, d: n.set_data(i, s, d)  # noqa: E731
    write(0x1602, 0, b"\x00")
    assert _abort(write, 0x1602, 2, struct.pack("<I", me(0x607A, 0, 32))) == 0x06040041  # PDOMapping=0
    assert _abort(write, 0x1602, 1, struct.pack("<I", me(0x6071, 0, 16))) == 0x06040041  # not in the EDS
    n.on_frame(0x000, nmt_frame(C.START, 4), 0.0)
    n.on_frame(0x204, struct.pack("<Hi", 0x0006, -1234), 0.01)       # RPDO1: 6040 + 60C1:01
    n.on_frame(0x080, b"", 0.02)
    assert n.get_data(0x60C1, 1) == struct.pack("<i", -1234)
    assert n.model.read(0x6040, 0) == 0x0006
    assert n.get_data(0x6060, 0) == b"\x07"                          # power-on mode from the EDS
    assert n.get_data(0x1008, 0) == b"Interp402"                     # empty default: the product name


# ---- the agent's side: names, types and the eds policy --------------------------------------------

def test_agent_names_and_types_vendor_objects_from_the_eds() -> None:
    d = eds.load(VENDOR, 2)
    m = pdo.eds_mapping(d)
    assert m.rx_pdos == () and m.tx_pdos == (0x1A00,) and dict(m.cob_ids) == {0x1A00: 0x182}
    with pytest.raises(MappingError, match=r"node 2: PDO policy 'eds': 0x6040 \(controlword\) is not in the outputs"):
        pdo.mapping_for("eds", 2, _read(_node(VENDOR, 2)), lambda *a: None, m)   # every RPDO disabled
    usable = pdo.pdos_mapping(2, [[me(0x6040, 0, 16)]], [list(d.pdos(True)[0].entries)])
    frames = pdo.PdoFrames(usable, pdo.eds_dictionary(d))
    assert frames.codec.extra_names == ("Temperature (°C)",)         # the EDS's name for a vendor object
    inputs = DriveInputs()
    assert frames.store_tpdo(0x182, struct.pack("<Hh", 0x0237, -5))
    frames.decode_into(inputs)
    assert inputs.statusword == 0x0237 and inputs.extra == (-5,)     # INTEGER16 in the EDS: signed
    plain = pdo.PdoFrames(usable)
    plain.store_tpdo(0x182, struct.pack("<Hh", 0x0237, -5))
    plain.decode_into(inputs)
    assert plain.codec.extra_names == ("0x2101:00",) and inputs.extra == (0xFFFB,)   # without the EDS


def test_eds_policy_writes_the_default_mapping_and_refuses_what_the_cycle_cannot_run() -> None:
    n = _node(CLASSIC, 3)
    read = _read(n)
    m = pdo.eds_mapping(eds.load(CLASSIC, 3))
    assert pdo.mapping_for("eds", 3, read, lambda i, s, d: n.set_data(i, s, d), m) == m
    assert pdo.read_mapping(read) == m and read(0x1400, 2) == b"\x01"  # written synchronous (EDS: 255)
    interp = eds.load(INTERP, 3)
    with pytest.raises(MappingError, match="0x6040:00 is mapped twice in the RPDOs"):
        pdo.mapping_for("eds", 3, read, lambda *a: None, pdo.eds_mapping(interp))


def test_canopen_sim_refuses_bad_eds_arguments_naming_why(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    for argv, needle in ((["--eds", str(CLASSIC), "--nodes", "2"], "--nodes and --eds exclude each other"),
                         (["--eds", f"{CLASSIC}*x"], "COUNT 'x' is not a number"),
                         (["--eds", f"{CLASSIC}*100", "--eds", f"{VENDOR}*30"], "node ids 1..130 outside 1..127"),
                         (["--eds", str(tmp_path / "none.eds")], "none.eds: cannot read"),
                         (["--eds", str(_write_nodrive(tmp_path))], "not a CiA 402 drive the simulator can run")):
        assert sim_cli.main(["--channel", "ff11::7a64:99", *argv]) == 2
        assert needle in capsys.readouterr().err, argv
    specs = [(str(CLASSIC), 2), (str(VENDOR), 1)]
    dicts = sim_cli.eds_dictionaries(specs, [4, 5, 6])
    assert [d.profile.product_code for d in dicts] == [0x402, 0x402, 7]
    assert [d.comm_defaults[(0x1400, 1)] for d in dicts] == [0x204, 0x205, 0x80000206]   # $NODEID per node


def test_scan_matches_each_node_to_its_eds_and_lists_where_its_mapping_differs(tmp_path: Path) -> None:
    from bus_agent.bus.canopen import scan

    assert scan.eds_files(str(DATA)) == [str(CLASSIC), str(INTERP), str(VENDOR)]
    with pytest.raises(eds.EdsError, match="no \\*.eds file"):
        scan.eds_files(str(tmp_path))
    n = _node(VENDOR, 4)
    report = scan.NodeReport(4, 305419896, 7, 65536, 0, 0x60192, "Vendor402", 0, mapping=pdo.read_mapping(_read(n)))
    matched = scan.match_eds(report, scan.eds_files(str(DATA)))
    assert (matched.eds, matched.device, matched.differences) == (str(VENDOR), "Vendor402", ())
    n.set_data(0x1400, 1, struct.pack("<I", 0x204))                 # RPDO1 enabled: not the EDS default
    changed = scan.match_eds(dataclasses.replace(report, mapping=pdo.read_mapping(_read(n))), [str(CLASSIC), str(VENDOR)])
    assert changed.differences == ("RPDO1: node 0x204 [6040 2100], EDS not valid",)
    text = scan.format_table([changed])
    assert f"  EDS: {VENDOR} (Vendor402): mapping differs from its default\n    RPDO1: node 0x204" in text
    unknown = scan.match_eds(dataclasses.replace(report, vendor_id=1), [str(CLASSIC), str(VENDOR)])
    assert unknown.eds == "" and "EDS: none of 2 file(s) has its identity" in scan.format_table([unknown])


def test_decimal_with_leading_zeros_and_bare_cr_lines(tmp_path: Path) -> None:
    p = tmp_path / "zeros.eds"
    p.write_bytes(b"[DeviceInfo]\rVendorNumber=0123\rProductName=007 Drive\r[1000]\rParameterName=007 type\r"
                  b"ObjectType=0x7\rDataType=0007\rAccessType=ro\rDefaultValue=0x00000192\r")
    d = eds.load(p, 1)
    assert (d.vendor_id, d.product_name, d.name_of(0x1000, 0), d.device_type) == (123, "007 Drive", "007 type", 0x192)
