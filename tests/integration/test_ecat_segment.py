"""Unmodified pysoem against ``ecat-sim``: discovery, mapping, AL states, CoE, faults.

Plain pysoem only (no project master code): what any SOEM-based master sees on this segment.
"""

from __future__ import annotations

import contextlib
import struct
import time
from typing import Iterator

import pysoem  # a dependency: a broken import fails the run, never skips it
import pytest
import zenoh

from bus_agent.bus.pdo import RX_STRUCT, TX_STRUCT
from bus_agent.sim.drive_model import PROFILES

pytestmark = [pytest.mark.root, pytest.mark.timeout(60)]

GENERIC = PROFILES["generic"]
OUT_BYTES, IN_BYTES = RX_STRUCT.size, TX_STRUCT.size  # 13, 15


@contextlib.contextmanager
def _opened(ifname: str, n: int) -> Iterator[pysoem.Master]:
    """A pysoem master on ``ifname`` that found ``n`` slaves; closed on exit."""
    m = pysoem.Master()
    m.open(ifname)
    try:
        assert m.config_init() == n
        yield m
    finally:
        m.close()


def _wait(predicate, timeout: float, what: str, poll=None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if poll:
            poll()
        if predicate():
            return
        time.sleep(0.001)
    raise AssertionError(f"timed out waiting for {what}")


def _to_op(m, map_first: bool = True) -> None:
    if map_first:
        m.config_map()
    assert m.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
    m.send_processdata()
    m.receive_processdata(2000)
    m.state = pysoem.OP_STATE
    m.write_state()
    deadline = time.monotonic() + 5
    while m.state_check(pysoem.OP_STATE, 5000) != pysoem.OP_STATE:
        assert time.monotonic() < deadline, "slaves did not reach OP"
        m.send_processdata()
        m.receive_processdata(2000)


def _set_controlword(m, cw: int) -> None:
    for s in m.slaves:
        s.output = RX_STRUCT.pack(cw, 0, 0, 0, 8)


def _statuswords(m) -> list[int]:
    return [TX_STRUCT.unpack(bytes(s.input))[0] for s in m.slaves]


def _cycle(m, lost_frames: bool = False) -> int:
    """One process-data exchange; its working counter. A frame that does not come back within
    SOEM's 2 ms (-1, a stall of the shared machine) is sent again, up to 3 times in all, unless
    the caller looks for lost frames."""
    for _ in range(1 if lost_frames else 3):
        m.send_processdata()
        wkc = m.receive_processdata(2000)
        if wkc != -1:
            break
    return wkc


def _enable(m) -> None:
    """Shutdown, switch on, enable operation (CiA 402 transitions 2, 3, 4) over the PDOs."""
    for cw, pattern in ((0x0006, 0x0021), (0x0007, 0x0023), (0x000F, 0x0027)):
        _set_controlword(m, cw)
        _wait(lambda: all(sw & 0x006F == pattern for sw in _statuswords(m)), 3.0,
              f"statusword pattern 0x{pattern:04X}", poll=lambda: _cycle(m))


def _abort_code(excinfo) -> int:
    return excinfo.value.abort_code & 0xFFFFFFFF


@pytest.mark.parametrize("n", [1, 16])
def test_discovery_identity_and_mapping(ecat_segment, n):
    ifname, _control = ecat_segment(n)
    with _opened(ifname, n) as m:
        for s in m.slaves:
            assert (s.name, s.man, s.id, s.rev) == (GENERIC.device_name, GENERIC.vendor_id,
                                                   GENERIC.product_code, GENERIC.revision)
        assert m.state_check(pysoem.PREOP_STATE, 2_000_000) == pysoem.PREOP_STATE
        assert m.config_map() == n * (OUT_BYTES + IN_BYTES)
        assert m.expected_wkc == 3 * n
        assert all((len(s.output), len(s.input)) == (OUT_BYTES, IN_BYTES) for s in m.slaves)
        _to_op(m, map_first=False)
        for _ in range(50):
            assert _cycle(m) == 3 * n
        serials = [struct.unpack("<I", s.sdo_read(0x1018, 4))[0] for s in m.slaves]
        assert serials == list(range(1, n + 1))


def test_sdo_transfers(ecat_segment):
    ifname, _ = ecat_segment(1)
    with _opened(ifname, 1) as m:
        s = m.slaves[0]
        assert m.state_check(pysoem.PREOP_STATE, 2_000_000) == pysoem.PREOP_STATE
        assert struct.unpack("<I", s.sdo_read(0x1018, 1))[0] == GENERIC.vendor_id  # expedited
        assert s.sdo_read(0x1008, 0).decode() == GENERIC.device_name  # normal upload
        s.sdo_write(0x6081, 0, struct.pack("<I", 12345))
        assert struct.unpack("<I", s.sdo_read(0x6081, 0))[0] == 12345
        blob = bytes(range(256)) + bytes(range(44))  # 300 bytes: segmented both ways
        s.sdo_write(0x2FFF, 0, blob)
        assert s.sdo_read(0x2FFF, 0, 512) == blob
        assert s.sdo_read(0x1C00, 0) == b"\x04"
        assert struct.unpack("<H", s.sdo_read(0x1C12, 1))[0] == 0x1600


ABORTS = [
    ("read", 0x2000, 0, None, 0x06020000),  # no object
    ("read", 0x1018, 9, None, 0x06090011),  # no subindex
    ("write", 0x6041, 0, b"\0\0", 0x06010002),  # read only
    ("write", 0x6040, 0, b"\0\0\0\0", 0x06070010),  # length mismatch
    ("write", 0x6060, 0, b"\x63", 0x06090030),  # value range (mode 99)
    ("write", 0x1600, 1, struct.pack("<I", 0x60650020), 0x06040041),  # not mappable (after sub0 = 0)
]


def test_sdo_aborts(ecat_segment):
    ifname, _ = ecat_segment(1)
    with _opened(ifname, 1) as m:
        s = m.slaves[0]
        assert m.state_check(pysoem.PREOP_STATE, 2_000_000) == pysoem.PREOP_STATE
        s.sdo_write(0x1600, 0, b"\x00")
        for kind, index, sub, data, code in ABORTS:
            with pytest.raises(pysoem.SdoError) as excinfo:
                s.sdo_read(index, sub) if kind == "read" else s.sdo_write(index, sub, data)
            assert _abort_code(excinfo) == code, f"{kind} 0x{index:04X}:{sub}"
        s.sdo_write(0x1600, 0, b"\x05")  # restore the default mapping count
        m.config_map()
        assert m.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
        with pytest.raises(pysoem.SdoError) as excinfo:
            s.sdo_write(0x1C12, 0, b"\x00")
        assert _abort_code(excinfo) == 0x08000022  # wrong state: PDO assignment outside PRE-OP


def _remap(slave) -> None:
    """0x1600 = controlword + target position, 0x1A00 = statusword + position (6 + 6 bytes)."""
    rx = [0x60400010, 0x607A0020]
    tx = [0x60410010, 0x60640020]
    for assign, pdo, entries in ((0x1C12, 0x1600, rx), (0x1C13, 0x1A00, tx)):
        slave.sdo_write(assign, 0, b"\x00")
        slave.sdo_write(pdo, 0, b"\x00")
        for k, e in enumerate(entries, start=1):
            slave.sdo_write(pdo, k, struct.pack("<I", e))
        slave.sdo_write(pdo, 0, bytes([len(entries)]))
        slave.sdo_write(assign, 1, struct.pack("<H", pdo))
        slave.sdo_write(assign, 0, b"\x01")


def test_remap_in_preop_then_refused(ecat_segment):
    ifname, _ = ecat_segment(2)
    with _opened(ifname, 2) as m:
        for s in m.slaves:
            s.config_func = (lambda pos, s=s: _remap(s))  # runs in PRE-OP inside config_map
        assert m.config_map() == 2 * (6 + 6)
        assert all((len(s.output), len(s.input)) == (6, 6) for s in m.slaves)
        _to_op(m, map_first=False)
        for s in m.slaves:
            s.output = struct.pack("<Hi", 0x0006, 0)
        _wait(lambda: all(struct.unpack("<Hi", bytes(s.input))[0] & 0x6F == 0x21 for s in m.slaves), 3.0,
              "ready to switch on through the remapped PDO", poll=lambda: _cycle(m))
        assert _cycle(m) == 6
        with pytest.raises(pysoem.SdoError) as excinfo:
            m.slaves[0].sdo_write(0x1600, 0, b"\x00")
        assert _abort_code(excinfo) == 0x08000022


def test_enable_fault_emcy(ecat_segment):
    ifname, control = ecat_segment(2)
    with _opened(ifname, 2) as m:
        _to_op(m)
        _enable(m)
        emergencies = []
        m.slaves[1].add_emergency_callback(emergencies.append)
        assert control.request("fault", slave=1, error_code=0x5530)["ok"]
        _wait(lambda: _statuswords(m)[1] & 0x004F == 0x0008, 3.0, "Fault on slave 1", poll=lambda: _cycle(m))
        assert TX_STRUCT.unpack(bytes(m.slaves[1].input))[5] == 0x5530  # 0x603F in the TxPDO
        assert _statuswords(m)[0] & 0x006F == 0x0027  # the other drive stays enabled
        assert struct.unpack("<H", m.slaves[1].sdo_read(0x603F, 0))[0] == 0x5530
        _wait(lambda: any(e.error_code == 0x5530 for e in emergencies), 2.0, "EMCY 0x5530",
              poll=lambda: m.slaves[1].mbx_receive())
        assert not control.request("fault", slave=7, error_code=1)["ok"]  # bad input: refused


def test_sm_watchdog_trips(ecat_segment):
    ifname, control = ecat_segment(2)
    with _opened(ifname, 2) as m:
        _to_op(m)
        _enable(m)
        emergencies = []
        for s in m.slaves:
            s.add_emergency_callback(emergencies.append)
        # stop process data: after 100 ms (0x0400/0x0420 defaults) SAFE-OP + error 0x001B
        _wait(lambda: m.read_state() == pysoem.SAFEOP_STATE and all(
            s.state == (pysoem.SAFEOP_STATE | pysoem.STATE_ERROR) and s.al_status == 0x001B for s in m.slaves),
            3.0, "SM watchdog")
        for s in m.slaves:  # the drives left Operation enabled: fault 0x8130 (communication lost)
            assert struct.unpack("<H", s.sdo_read(0x6041, 0))[0] & 0x006F != 0x0027
            assert struct.unpack("<H", s.sdo_read(0x603F, 0))[0] == 0x8130
        _wait(lambda: {e.slave_pos for e in emergencies if e.error_code == 0x8130} == {1, 2}, 2.0,
              "EMCY 0x8130 from both drives", poll=lambda: [s.mbx_receive() for s in m.slaves])
        status = control.request("status")["slaves"]
        assert [x["al_status_code"] for x in status] == [0x001B, 0x001B]
        # in SAFE-OP the inputs still flow (+1 each) but the outputs are not taken (no +2)
        assert _cycle(m) == 2


def test_al_error_codes(ecat_segment):
    ifname, _ = ecat_segment(1)
    with _opened(ifname, 1) as m:
        s = m.slaves[0]
        assert m.state_check(pysoem.PREOP_STATE, 2_000_000) == pysoem.PREOP_STATE
        s.state = pysoem.OP_STATE  # PRE-OP -> OP skips SAFE-OP
        s.write_state()
        s.state_check(pysoem.OP_STATE, 100_000)
        assert s.state == pysoem.PREOP_STATE | pysoem.STATE_ERROR and s.al_status == 0x0011
        s.state = pysoem.PREOP_STATE | pysoem.STATE_ACK
        s.write_state()
        assert s.state_check(pysoem.PREOP_STATE, 100_000) == pysoem.PREOP_STATE
        m.config_map()
        assert m.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
        s.state = pysoem.PREOP_STATE
        s.write_state()
        assert s.state_check(pysoem.PREOP_STATE, 100_000) == pysoem.PREOP_STATE
        s._fpwr(0x0812, struct.pack("<H", 5))  # SM2 length 5 instead of 13
        s.state = pysoem.SAFEOP_STATE
        s.write_state()
        s.state_check(pysoem.SAFEOP_STATE, 100_000)
        assert s.state == pysoem.PREOP_STATE | pysoem.STATE_ERROR and s.al_status == 0x001D
        s._fpwr(0x0812, struct.pack("<H", OUT_BYTES))
        s._fpwr(0x081A, struct.pack("<H", 3))  # SM3 length wrong
        s.state = pysoem.SAFEOP_STATE | pysoem.STATE_ACK
        s.write_state()
        s.state_check(pysoem.SAFEOP_STATE, 100_000)
        assert s.state == pysoem.PREOP_STATE | pysoem.STATE_ERROR and s.al_status == 0x001E
        s.state = pysoem.INIT_STATE  # INIT clears the error; a bad mailbox SM refuses PRE-OP
        s.write_state()
        assert s.state_check(pysoem.INIT_STATE, 100_000) == pysoem.INIT_STATE
        s._fpwr(0x0802, struct.pack("<H", 64))
        s.state = pysoem.PREOP_STATE
        s.write_state()
        s.state_check(pysoem.PREOP_STATE, 100_000)
        assert s.state == pysoem.INIT_STATE | pysoem.STATE_ERROR and s.al_status == 0x0016


def test_unplug_plug_wkc_fault_and_frame_faults(ecat_segment):
    ifname, control = ecat_segment(3)
    with _opened(ifname, 3) as m:
        _to_op(m)
        assert _cycle(m) == 9
        assert control.request("wkc_fault", slave=2, on=True)["ok"]
        assert _cycle(m) == 6
        assert control.request("wkc_fault", slave=2, on=False)["ok"]
        assert control.request("unplug", slave=1)["ok"]
        assert _cycle(m) == 6
        with pytest.raises(pysoem.WkcError):
            m.slaves[1].sdo_read(0x1018, 1)
        assert control.request("plug", slave=1)["ok"]
        assert _cycle(m) == 6  # back, but reset: INIT, no FMMUs
        s = m.slaves[1]
        assert s.recover(20_000) > 0  # same identity: station address restored
        assert s.reconfig(20_000) == pysoem.SAFEOP_STATE
        s.state = pysoem.OP_STATE
        s.write_state()
        _wait(lambda: _cycle(m) == 9 and s.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE, 3.0,
              "slave 1 back in OP")
        assert control.request("drop_frames", count=2)["ok"]
        assert [_cycle(m, lost_frames=True) for _ in range(3)] == [-1, -1, 9]
        # 50 ms: long after SOEM gave up (2 ms), short of the 100 ms SM watchdog (which would
        # take the slaves to SAFE-OP, where outputs no longer count in the working counter)
        assert control.request("delay_frames", count=1, delay_ms=50)["ok"]
        assert _cycle(m, lost_frames=True) == -1  # answered long after SOEM gave up: ignored
        time.sleep(0.06)
        _wait(lambda: _cycle(m) == 9, 1.0, "cycles after the late answer")
        assert not control.request("drop_frames", ratio=3)["ok"]


def test_64_drives_multi_frame(ecat_segment):
    ifname, _ = ecat_segment(64)
    with _opened(ifname, 64) as m:
        assert m.config_map() == 64 * (OUT_BYTES + IN_BYTES)  # beyond one frame: two LRWs
        assert m.expected_wkc == 192
        _to_op(m, map_first=False)
        for _ in range(20):
            assert _cycle(m) == 192


def test_fault_injection_over_zenoh(ecat_segment):
    import socket

    from bus_agent.sim.control import SimControlError, sim_inject

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    ifname, control = ecat_segment(2, "generic", "--zenoh-listen", f"tcp/127.0.0.1:{port}")
    segment = control.request("ping")["segment"]
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    session = zenoh.open(conf)
    try:
        deadline = time.monotonic() + 10
        while True:  # the route to the simulator's queryable takes a moment to appear
            try:
                details = sim_inject(session, segment, 1, "fault", error_code=0x2310, timeout_s=1.0)
                break
            except SimControlError:
                assert time.monotonic() < deadline, "simulator never answered over Zenoh"
        assert len(details) == 1
        status = control.request("status")["slaves"]
        assert status[1]["error_code"] == 0x2310 and status[0]["error_code"] == 0
        with pytest.raises(SimControlError):
            sim_inject(session, segment, 1, "fault", error_code="bad", timeout_s=2.0)
    finally:
        session.close()


def test_drives_without_sync0_run_on_the_sm2_event(ecat_segment):
    """Without SYNC0 a simulated drive is SM-synchronous (0x1C32:01 = 1): the frame that writes
    its outputs starts its application cycle, so the master's next frame, however soon, reads
    the answer to a new controlword. The free-run timer is set to 200 ms here: a drive stepped by
    the timer would answer within the 20 ms allowed below fewer than one time in ten (a host
    stall of a few ms does not fail the test)."""
    ifname, _control = ecat_segment(2, "generic", "--step-us", "200000")
    with _opened(ifname, 2) as m:
        assert [struct.unpack("<H", s.sdo_read(0x1C32, 1))[0] for s in m.slaves] == [1, 1]
        _to_op(m)
        for cw, pattern in ((0x0006, 0x0021), (0x0007, 0x0023), (0x000F, 0x0027), (0x0006, 0x0021)):
            _set_controlword(m, cw)
            sent = time.monotonic()
            _cycle(m)  # the SM2 event
            seen = None
            while seen is None and time.monotonic() - sent < 0.020:
                time.sleep(0.002)
                _cycle(m)
                if all(sw & 0x006F == pattern for sw in _statuswords(m)):
                    seen = time.monotonic() - sent
            assert seen is not None, f"controlword 0x{cw:04X}: statusword {_statuswords(m)} not 0x{pattern:04X} in 20 ms"
