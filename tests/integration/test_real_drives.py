"""Drives that map PDOs like real ones, over pysoem and ``ecat-sim`` on a veth pair (root).

The agent with no configuration reads each drive's own mapping in PRE-OP and builds its codec;
objects the drive does not map are served by SDO; mapping policies and start-up SDOs are
written in PRE-OP, and their refusals name the object, the abort code and what to do.
"""

from __future__ import annotations

import functools
import struct
import threading
import time

import pytest

from bus_agent.bus.base import BusError
from bus_agent.bus.mapping import MappingPolicy, StartupSdo
from bus_agent.bus.pysoem_bus import PysoemBus
from bus_agent.config import AgentConfig, DriveConfig
from bus_agent.cycle import management
from bus_agent.cycle.cycle import Cycle
from bus_agent.runtime import DriveCommand, Outcome
from bus_agent.sim import child

pytestmark = [pytest.mark.root, pytest.mark.timeout(180)]

_wait = functools.partial(child.wait_for, poll_s=0.005)
OMRON_POSITION = 100_000  # the omron1s profile's absolute encoder: 100000 * serial at power-on


class Agent:
    def __init__(self, ifname: str, **cfg) -> None:
        self.bus = PysoemBus(ifname)
        self.cycle = Cycle(self.bus, AgentConfig(host="h1", ifname=ifname, **cfg))
        self.events: list = []
        self.lock = threading.Lock()
        self.cycle.snapshot_sink = self._sink
        self.seq = 0

    def _sink(self, snap) -> None:
        if snap.events:
            with self.lock:
                self.events.extend(snap.events)

    def cmd(self, op: str, *axes: str, timeout_s: float = 5.0, **args) -> list[Outcome]:
        self.seq += 1
        out: list[Outcome] = []
        assert self.cycle.submit(DriveCommand(request_id=f"r{self.seq}", op=op, axes=axes, args=args,
                                              timeout_s=timeout_s, received_ns=time.monotonic_ns(),
                                              on_outcome=out.append))
        _wait(lambda: len(out) >= len(axes), timeout_s + 5, f"{len(axes)} outcome(s) of {op}")
        return out

    def drive(self, axis: str):
        snap = self.cycle.latest
        assert snap is not None
        return next(d for d in snap.drives if d.axis == axis)


def _slaves(control) -> list[dict]:
    reply = control.request("status")
    assert reply["ok"], reply
    return reply["slaves"]


def test_predefined_drives_with_no_configuration(ecat_segment):
    """Omron-like drives: own mapping read, OP, SDO mode change, enable without a jump."""
    ifname, control = ecat_segment(3, "omron1s")
    agent = Agent(ifname)
    agent.cycle.start()
    try:
        _wait(lambda: agent.cycle.latest is not None and all(d.mode_display == 8 for d in agent.cycle.latest.drives),
              10, "0x6061 = 8 echoed by SDO on every drive")
        for k, d in enumerate(agent.cycle.latest.drives):
            assert d.al_state == "op" and d.state == "switch_on_disabled"
            assert d.absent == ("velocity",)  # 0x606C is not in 0x1B01
            objs = dict(zip(d.object_names, d.objects))
            assert set(objs) == {"following_error_actual_value", "touch_probe_status", "touch_probe_1_positive_edge",
                                 "touch_probe_2_positive_edge", "digital_inputs"}
            # each drive decoded at its own offsets: its serial in bits 16..31, the home switch
            # (bit 2, active at and above 5000 increments) on at the omron1s power-on position
            assert objs["digital_inputs"] == (k + 1) << 16 | 0x4
            assert d.position == OMRON_POSITION * (k + 1)
        assert [s["mode_display"] for s in _slaves(control)] == [8, 8, 8]
        outs = agent.cmd("enable", "axis0", "axis1", "axis2")
        assert all(o.outcome == "done" for o in outs), outs
        # no jump: 0x607A was held at 0x6064 (a stale 0 would be a 100000+ following error, 0x8611)
        for k in range(3):
            (target,) = struct.unpack("<i", agent.bus.sdo_read(k, 0x607A, 0, 4))
            assert target == OMRON_POSITION * (k + 1)
        assert all(s["drive_state"] == "operation_enabled" and s["error_code"] == 0 for s in _slaves(control))
        # a mode change through SDO (0x6060 is not mapped): done when 0x6061 (read by SDO) echoes it
        outs = agent.cmd("set_mode", "axis1", mode=9)
        assert [o.outcome for o in outs] == ["done"], outs
        assert _slaves(control)[1]["mode_display"] == 9
        # a fault: 0x603F is mapped in 0x1B01
        assert control.request("fault", slave=2, error_code=0x7500)["ok"]
        _wait(lambda: agent.drive("axis2").state == "fault" and agent.drive("axis2").error_code == 0x7500, 5,
              "axis2 in fault with 0x7500")
    finally:
        agent.cycle.stop()
    assert all(s["drive_state"] in ("switch_on_disabled", "fault") for s in _slaves(control))


def test_mixed_segment_and_policies(ecat_segment):
    """Flexible + predefined + read-only assignment, each with a policy that fits it; one drive
    without 0x603F/0x6061 in its PDOs (read by SDO); start-up SDOs survive a power cycle."""
    ifname, control = ecat_segment(4, "generic,omron1s,roassign,generic")
    drives = (
        DriveConfig(slave=0, mapping=MappingPolicy("explicit", rx_entries=((0x6040, 0, 16), (0x607A, 0, 32), (0x6060, 0, 8)),
                                                   tx_entries=((0x6041, 0, 16), (0x6064, 0, 32), (0x60FD, 0, 32))),
                    sdos=(StartupSdo(0x6065, 0, "u32", 12345),)),
        DriveConfig(slave=1, mapping=MappingPolicy("predefined", rx=(0x1702,), tx=(0x1B02,))),
        DriveConfig(slave=2),  # policy drive: its read-only 0x1C12 holds the default layout
        DriveConfig(slave=3, mapping=MappingPolicy("default")),
    )
    agent = Agent(ifname, drives=drives)
    agent.cycle.start()
    try:
        _wait(lambda: agent.cycle.latest is not None and agent.cycle.latest.cycle > 50, 10, "50 cycles")
        d0 = agent.drive("axis0")
        assert d0.absent == ("velocity", "torque") and d0.object_names == ("digital_inputs",)
        assert d0.objects == (1 << 16,)
        assert agent.drive("axis1").absent == ("velocity",)
        assert agent.drive("axis2").absent == () and agent.drive("axis3").absent == ()
        assert struct.unpack("<I", agent.bus.sdo_read(0, 0x6065, 0, 4))[0] == 12345
        outs = agent.cmd("enable", "axis0", "axis1", "axis2", "axis3")
        assert all(o.outcome == "done" for o in outs), [(o.axis, o.outcome, o.reason) for o in outs] + [(d.axis, d.mode, d.mode_display, d.statusword) for d in agent.cycle.latest.drives]
        assert [s["drive_state"] for s in _slaves(control)] == ["operation_enabled"] * 4
        # 0x603F not mapped on axis0: read by SDO once the fault shows
        assert control.request("fault", slave=0, error_code=0x5530)["ok"]
        _wait(lambda: agent.drive("axis0").error_code == 0x5530, 5, "0x603F read by SDO")
        with agent.lock:
            assert any(e.kind == "fault" and e.error_code == 0x5530 and "SDO" in e.detail for e in agent.events)
        outs = agent.cmd("fault_reset", "axis0")
        assert [o.outcome for o in outs] == ["done"], outs
        assert outs[0].error_code == 0, outs  # the reply does not carry the reset fault's code
        _wait(lambda: agent.drive("axis0").error_code == 0, 5, "error code cleared after the reset")
        # power cycle: mapping and start-up SDOs re-applied before it is back in OP
        assert control.request("unplug", slave=0)["ok"]
        _wait(lambda: agent.drive("axis0").lost, 10, "axis0 lost")
        assert control.request("plug", slave=0)["ok"]
        _wait(lambda: not agent.drive("axis0").lost, 20, "axis0 found")
        assert struct.unpack("<I", agent.bus.sdo_read(0, 0x6065, 0, 4))[0] == 12345
        assert agent.drive("axis0").state == "switch_on_disabled"  # never re-enabled by itself
    finally:
        agent.cycle.stop()


def test_a_drive_without_0x603F_reports_the_fault_of_its_emergency(ecat_segment):
    """0x603F neither mapped nor readable (the upload aborted 0x06020000, object does not exist):
    the fault's error code and text come from the drive's CoE emergency; the refused upload is
    made once, not tried again (a definite answer); the fault reset's reply says 0."""
    ifname, control = ecat_segment(1, "generic")
    assert control.request("refuse_sdo", slave=0, index=0x603F, subindex=0, abort=0x06020000)["ok"]
    drives = (DriveConfig(slave=0, mapping=MappingPolicy(
        "explicit", rx_entries=((0x6040, 0, 16), (0x607A, 0, 32), (0x6060, 0, 8)),
        tx_entries=((0x6041, 0, 16), (0x6064, 0, 32), (0x6061, 0, 8)))),)
    agent = Agent(ifname, drives=drives)
    uploads = []
    sdo_read = agent.bus.sdo_read

    def counting(position, index, subindex, size):
        if index == 0x603F:
            uploads.append(time.monotonic())
        return sdo_read(position, index, subindex, size)
    agent.bus.sdo_read = counting
    agent.cycle.start()
    try:
        assert [o.outcome for o in agent.cmd("enable", "axis0")] == ["done"]
        assert control.request("fault", slave=0, error_code=0x2310)["ok"]
        _wait(lambda: agent.drive("axis0").error_code == 0x2310, 5, "the EMCY's error code")
        d = agent.drive("axis0")
        assert d.state == "fault" and d.error_text == "continuous over-current", d
        time.sleep(0.3)  # the management thread's retries would have run by now
        assert len(uploads) == 1, f"0x603F uploaded {len(uploads)} times"
        outs = agent.cmd("fault_reset", "axis0")
        assert [(o.outcome, o.error_code) for o in outs] == [("done", 0)], outs
        # a second fault: no more uploads of the refused object, the EMCY's code again
        assert control.request("fault", slave=0, error_code=0x7500)["ok"]
        _wait(lambda: agent.drive("axis0").error_code == 0x7500, 5, "the second EMCY's error code")
        assert len(uploads) == 1
    finally:
        agent.cycle.stop()


@pytest.mark.parametrize("profile, drive, match", [
    ("roassign", DriveConfig(slave=0, mapping=MappingPolicy("explicit", rx_entries=((0x6040, 0, 16),),
                                                            tx_entries=((0x6041, 0, 16),))),
     r"slave 0 .*policy 'explicit': SDO write 0x1C12:00 = 0x0 aborted 0x06010002 .*use policy 'drive'"),
    ("omron1s", DriveConfig(slave=0, mapping=MappingPolicy("predefined", rx=(0x1705,), tx=(0x1B01,))),
     r"0x1C12:01 = 0x1705 aborted 0x06090030 .*bus-agent scan"),
    ("generic", DriveConfig(slave=0, mapping=MappingPolicy("explicit", rx_entries=((0x6040, 0, 16),),
                                                           tx_entries=((0x6064, 0, 32),))),
     r"slave 0 .*0x6041 \(statusword\) is not in the inputs"),
    ("generic", DriveConfig(slave=0, sdos=(StartupSdo(0x6041, 0, "u16", 1),)),
     r"slave 0 .*start-up SDO 0x6041:00 \(u16\) = 1 aborted 0x06010002"),
])
def test_refusals_name_object_abort_and_policy(ecat_segment, profile, drive, match):
    ifname, control = ecat_segment(1, profile)
    agent = Agent(ifname, drives=(drive,))
    with pytest.raises(BusError, match=match):
        agent.cycle.open()
    assert agent.cycle.state == "error"
    assert _slaves(control)[0]["al_state"] in ("init", "preop")  # never beyond PRE-OP


def test_a_mapping_answer_lost_to_soem_starts_again_from_init(ecat_segment, caplog):
    """SOEM sizes process data from its own SDO uploads of the mapping and counts an entry that
    got no answer as 0 bits (here 0x606C, 32 bits). Slave 1 answers this master's upload of 0x1A00:03 (the PO2SO hook)
    and not SOEM's next one: the sizes disagree, start() goes back to INIT and tries again, and
    the segment reaches OP with the whole mapping. An upload of this master's own that gets no
    answer is tried again (0x1A00:04 of slave 0)."""
    ifname, control = ecat_segment(2)
    for slave, sub, skip in ((1, 3, 1), (0, 4, 0)):
        reply = control.request("mute_sdo", slave=slave, index=0x1A00, subindex=sub, skip=skip, count=1)
        assert reply["ok"], reply
    bad = control.request("mute_sdo", slave=2, index=0x1A00, subindex=3, skip=0, count=1)
    assert not bad["ok"] and "slave must be an integer in 0..1" in bad["error"]
    bus = PysoemBus(ifname)
    try:
        bus.open()
        with caplog.at_level("WARNING", logger="bus_agent.bus.pysoem_bus"):
            wkc = bus.start()
        text = caplog.text
        assert "SDO upload 0x1A00:04" in text and "no answer from the slave's mailbox (attempt 1 of 3)" in text
        assert "slave 1" in text and "process data is 13 bytes out / 11 in" in text and "from INIT again" in text
        for pos in (0, 1):
            assert (bus.codec(pos).out_size, bus.codec(pos).in_size) == (13, 15)
        assert wkc == 6 and bus.exchange() == wkc  # LRW: 3 per slave
        assert [s["al_state"] for s in _slaves(control)] == ["op", "op"]
    finally:
        bus.close()


def test_coe_emergencies_reach_the_log_and_do_not_fail_sdo_transfers(ecat_segment):
    """A drive's CoE emergency (EMCY in its mailbox) is taken by the SDO transfer that finds it,
    which still succeeds (pysoem fails it without an emergency callback), or by poll_mailbox;
    either way it reaches take_emergencies() and error_texts with its error code and text."""
    ifname, control = ecat_segment(2)
    bus = PysoemBus(ifname)
    try:
        bus.open()
        bus.start()
        assert bus.take_emergencies() == []
        assert control.request("fault", slave=1, error_code=0x2310)["ok"]
        _wait(lambda: bus.exchange() and _slaves(control)[1]["drive_state"] == "fault", 3, "slave 1 in fault")
        assert struct.unpack("<H", bus.sdo_read(1, 0x603F, 0, 2))[0] == 0x2310  # the EMCY came first
        assert bus.take_emergencies() == [(1, 0x2310, 0x03, "continuous over-current")]
        assert bus.error_texts == {1: (0x2310, "continuous over-current")}
        assert control.request("fault", slave=0, error_code=0x7500)["ok"]
        _wait(lambda: bus.exchange() and _slaves(control)[0]["drive_state"] == "fault", 3, "slave 0 in fault")
        bus.poll_mailbox(0)
        assert bus.take_emergencies() == [(0, 0x7500, 0x21, "communication")]
        bus.poll_mailbox(None)  # the next slave in turn; nothing waits there
        bus.poll_mailbox(None)
        assert bus.take_emergencies() == []
    finally:
        bus.close()


def test_the_cycle_reports_a_coe_emergency_as_an_event(ecat_segment, monkeypatch):
    """The cycle reads the mailbox of a drive that enters Fault: its EMCY becomes an ``emcy``
    event with the code, its text and the error register; the status's error_text is the EMCY's.
    The slow poll of every mailbox in turn is put off here, so only that read can find it."""
    monkeypatch.setattr(management, "MAILBOX_POLL_NS", 3600 * 10**9)
    ifname, control = ecat_segment(2)
    agent = Agent(ifname)
    agent.cycle.start()
    try:
        _wait(lambda: agent.cycle.latest is not None, 10, "the first snapshot")
        assert control.request("fault", slave=1, error_code=0x2310)["ok"]

        def emcy():
            with agent.lock:
                return [e for e in agent.events if e.kind == "emcy"]
        _wait(lambda: emcy(), 3, "an emcy event")
        (ev,) = emcy()
        assert ev.axis == "axis1" and ev.error_code == 0x2310
        assert ev.detail == "EMCY 0x2310 continuous over-current (error register 0x03)"
        _wait(lambda: agent.drive("axis1").error_text == "continuous over-current", 3, "the EMCY's text in the status")
        assert agent.drive("axis0").error_code == 0 and agent.drive("axis0").state == "switch_on_disabled"
    finally:
        agent.cycle.stop()


def test_mailbox_reads_never_take_an_sdo_transfers_answer(ecat_segment):
    """poll_mailbox on one thread while SDO uploads run on another (the management thread and a
    caller of bus.sdo_read): the mailbox lock keeps the poll from taking an upload's answer."""
    ifname, _control = ecat_segment(1)
    bus = PysoemBus(ifname)
    try:
        bus.open()
        bus.start()
        stop = threading.Event()
        polls = [0]

        def poll() -> None:
            while not stop.is_set():
                bus.poll_mailbox(0)
                polls[0] += 1

        t = threading.Thread(target=poll)
        t.start()
        try:
            values = {struct.unpack("<I", bus.sdo_read(0, 0x1018, 1, 4))[0] for _ in range(200)}
        finally:
            stop.set()
            t.join()
        assert len(values) == 1 and polls[0] > 200
    finally:
        bus.close()
