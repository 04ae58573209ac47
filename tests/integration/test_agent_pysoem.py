"""The agent cycle over PysoemBus against ``ecat-sim`` on a veth pair (root).

The real path: pysoem frames on a veth end, a separate ecat-sim process on the other.
Waits are on conditions with deadlines; drive states are checked on the drive side through
ecat-sim's control socket (``status``) or by SDO.
"""

from __future__ import annotations

import functools
import struct
import threading
import time

import pytest

from bus_agent.sim import child
from bus_agent.bus.base import ALState, BusError
from bus_agent.bus.pysoem_bus import PysoemBus
from bus_agent.config import AgentConfig, DriveConfig, Identity, PdoMapping
from bus_agent.cycle.cycle import Cycle, IdentityMismatch
from bus_agent.runtime import DriveCommand, Outcome
from bus_agent.sim.drive_model import PROFILES

pytestmark = [pytest.mark.root, pytest.mark.timeout(120)]

GENERIC = PROFILES["generic"]


_wait = functools.partial(child.wait_for, poll_s=0.005)


def _drive_states(control) -> list[str]:
    reply = control.request("status")
    assert reply["ok"], reply
    return [s["drive_state"] if "drive_state" in s else s.get("state") for s in reply["slaves"]]


class Agent:
    """A running cycle over PysoemBus with outcome collection."""

    def __init__(self, ifname: str, n: int, **cfg) -> None:
        self.config = AgentConfig(host="h1", ifname=ifname, **cfg)
        self.bus = PysoemBus(ifname)
        self.cycle = Cycle(self.bus, self.config)
        self.events = []
        self.lock = threading.Lock()
        self.cycle.snapshot_sink = self._sink
        self.outcomes: dict[str, list[Outcome]] = {}
        self.seq = 0

    def _sink(self, snap) -> None:
        if snap.events:
            with self.lock:
                self.events.extend(snap.events)

    def has_event(self, kind: str, axis: str | None = None) -> bool:
        with self.lock:
            return any(e.kind == kind and (axis is None or e.axis == axis) for e in self.events)

    def cmd(self, op: str, *axes: str, timeout_s: float = 5.0, **args) -> str:
        self.seq += 1
        rid = f"r{self.seq}"
        out: list[Outcome] = []
        self.outcomes[rid] = out
        assert self.cycle.submit(DriveCommand(request_id=rid, op=op, axes=axes, args=args, timeout_s=timeout_s,
                                              received_ns=time.monotonic_ns(), on_outcome=out.append))
        return rid

    def wait_outcomes(self, rid: str, n: int, timeout_s: float = 10.0) -> list[Outcome]:
        _wait(lambda: len(self.outcomes[rid]) >= n, timeout_s, f"{n} outcome(s) of {rid}")
        return self.outcomes[rid]


def test_startup_to_op_and_enable_through_the_cycle(ecat_segment):
    ifname, control = ecat_segment(4, "generic")
    agent = Agent(ifname, 4, drives=tuple(DriveConfig(slave=i, identity=Identity(GENERIC.vendor_id, GENERIC.product_code))
                                          for i in range(4)))
    agent.cycle.start()
    try:
        _wait(lambda: agent.cycle.latest is not None and agent.cycle.latest.cycle > 50, 5, "50 cycles")
        snap = agent.cycle.latest
        assert all(d.al_state == "op" and d.state == "switch_on_disabled" for d in snap.drives)
        rid = agent.cmd("enable", "axis0", "axis1", "axis2", "axis3")
        outs = agent.wait_outcomes(rid, 4)
        assert sorted(o.axis for o in outs) == ["axis0", "axis1", "axis2", "axis3"]
        assert all(o.outcome == "done" for o in outs), outs
        states = _drive_states(control)
        assert all(s == "operation_enabled" for s in states), states
        # 3 per slave (LRW read + write); right in (nearly) every cycle: a frame lost to a stalled
        # host is counted, but an exchange that is wrong every cycle fails (generous bound, 5 %)
        assert agent.bus.expected_wkc == 3 * 4
        assert agent.cycle.cycles > 50 and agent.cycle.wkc_errors * 20 <= agent.cycle.cycles, (
            agent.cycle.wkc_errors, agent.cycle.cycles)
    finally:
        agent.cycle.stop()
    # ordered shutdown seen on the drive side, then INIT
    states = _drive_states(control)
    assert all(s == "switch_on_disabled" for s in states), states
    reply = control.request("status")
    assert all(s.get("al_state") in ("init", 1) for s in reply["slaves"]), reply["slaves"]


def test_identity_mismatch_is_a_clear_startup_error(ecat_segment):
    ifname, _control = ecat_segment(2, "generic")
    agent = Agent(ifname, 2, drives=(DriveConfig(slave=0), DriveConfig(slave=1, identity=Identity(0x1234, 0x5678))))
    with pytest.raises(IdentityMismatch, match=r"slave 1 .* 0x00001234"):
        agent.cycle.open()
    assert agent.cycle.state == "error"


def test_pdo_mapping_override_and_sdo(ecat_segment):
    ifname, _control = ecat_segment(2, "generic")
    agent = Agent(ifname, 2, drives=(DriveConfig(slave=0, pdo=PdoMapping()), DriveConfig(slave=1)))
    agent.cycle.open()
    try:
        assert agent.bus.expected_wkc == 6
        (sw,) = struct.unpack("<H", agent.bus.sdo_read(0, 0x6041, 0, 2))
        assert sw & 0x004F == 0x0040
        with pytest.raises(BusError, match="0x6FFF"):
            agent.bus.sdo_read(0, 0x6FFF, 0, 2)
    finally:
        agent.cycle.stop()


def test_lost_and_returning_slave_is_not_re_enabled(ecat_segment):
    ifname, control = ecat_segment(3, "generic")
    agent = Agent(ifname, 3, groups={"arm": ("h1/axis0", "h1/axis2")})
    agent.cycle.start()
    try:
        rid = agent.cmd("enable", "axis0", "axis1", "axis2")
        assert all(o.outcome == "done" for o in agent.wait_outcomes(rid, 3))
        assert control.request("unplug", slave=2)["ok"]
        _wait(lambda: agent.has_event("lost", "axis2"), 5, "lost event")
        _wait(lambda: agent.has_event("reflex", "axis0"), 1, "group reflex on axis0")
        snap = agent.cycle.latest
        assert next(d for d in snap.drives if d.axis == "axis2").lost
        _wait(lambda: _drive_states(control)[0] in ("quick_stop_active", "switch_on_disabled"), 5,
              "axis0 quick stop on the drive")
        assert _drive_states(control)[1] == "operation_enabled"  # not in the group
        assert control.request("plug", slave=2)["ok"]
        _wait(lambda: agent.has_event("found", "axis2"), 10, "found event")
        time.sleep(0.3)  # let a re-enable show if there were one
        d2 = next(d for d in agent.cycle.latest.drives if d.axis == "axis2")
        assert not d2.lost and d2.goal == "disabled" and d2.al_state == "op"
        assert _drive_states(control)[2] != "operation_enabled"
        r2 = agent.cmd("enable", "axis2")
        assert agent.wait_outcomes(r2, 1)[0].outcome == "done"
    finally:
        agent.cycle.stop()


def test_sm_watchdog_when_the_master_stops(ecat_segment):
    ifname, control = ecat_segment(2, "generic")
    agent = Agent(ifname, 2)
    agent.cycle.open()
    try:
        rid = agent.cmd("enable", "axis0", "axis1")
        deadline = time.monotonic() + 10
        while len(agent.outcomes[rid]) < 2 and time.monotonic() < deadline:
            agent.cycle.tick()
            time.sleep(0.001)
        assert [o.outcome for o in agent.outcomes[rid]] == ["done", "done"]
        # the master stops exchanging: the slaves' SM watchdog ends OP and the drives stop
        statuses = _wait(lambda: (lambda st: st if all(s.state == ALState.SAFEOP and s.error for s in st) else None)(
            agent.bus.read_al_status()), 5, "SAFE-OP + error on every slave")
        assert all(s.status_code == 0x001B for s in statuses)
        assert all(s != "operation_enabled" for s in _drive_states(control))
        # the cycle resumes: both lost, then recovered to OP with goals disabled
        deadline = time.monotonic() + 10
        while not (agent.has_event("found", "axis0") and agent.has_event("found", "axis1")):
            assert time.monotonic() < deadline, (agent.events[-10:], agent.cycle.latest.drives)
            agent.cycle.tick()
            time.sleep(0.001)
        assert agent.has_event("lost", "axis0") and agent.has_event("lost", "axis1")
        for _ in range(100):
            agent.cycle.tick()
            time.sleep(0.001)
        assert all(d.goal == "disabled" and not d.lost and d.al_state == "op" for d in agent.cycle.latest.drives)
        # the drives' communication-loss reaction stands; nothing re-enables or resets them
        assert all(s in ("switch_on_disabled", "fault") for s in _drive_states(control)), _drive_states(control)
    finally:
        agent.cycle.stop()


def test_nmt_commands_over_pysoem(ecat_segment):
    from bus_agent.runtime import AgentCommand

    ifname, control = ecat_segment(2, "generic")
    agent = Agent(ifname, 2)
    agent.cycle.start()

    def nmt(command: str, axis: str | None = None) -> Outcome:
        got: list[Outcome] = []
        args = {"command": command} if axis is None else {"command": command, "axis": axis}
        assert agent.cycle.submit(AgentCommand(request_id=f"n-{command}", op="nmt", args=args, timeout_s=10,
                                               received_ns=time.monotonic_ns(), on_outcome=got.append))
        _wait(lambda: got, 15, f"nmt {command}")
        return got[0]

    def al_states() -> list[str]:
        return [s["al_state"] for s in control.request("status")["slaves"]]

    try:
        rid = agent.cmd("enable", "axis1")
        assert agent.wait_outcomes(rid, 1)[0].outcome == "done"
        o = nmt("stop", "axis1")
        assert o.outcome == "done", o
        assert al_states() == ["op", "safeop"]
        assert _drive_states(control)[1] == "switch_on_disabled"  # taken down before leaving OP
        assert not agent.has_event("lost", "axis1")
        o = nmt("start")
        assert o.outcome == "done", o
        assert al_states() == ["op", "op"]
        o = nmt("reset_comm", "axis0")
        assert o.outcome == "done", o
        assert al_states() == ["preop", "op"]
        o = nmt("reset_node")
        assert o.outcome == "done", o
        assert al_states() == ["op", "op"]
        time.sleep(0.2)
        assert all(d.goal == "disabled" and not d.lost for d in agent.cycle.latest.drives)
        rid = agent.cmd("enable", "axis0", "axis1")
        assert [o.outcome for o in agent.wait_outcomes(rid, 2)] == ["done", "done"]
    finally:
        agent.cycle.stop()


def _slave_status(control) -> list[dict]:
    reply = control.request("status")
    assert reply["ok"], reply
    return reply["slaves"]


def _assert_running(status: list[dict], slaves) -> None:
    """These slaves are in OP without an AL error (no SM watchdog 0x001B) and their drives are
    still in operation enabled (a watchdog trip would have faulted them: 0x8130)."""
    for i in slaves:
        s = status[i]
        assert s["al_state"] == "op" and not s["al_error"] and s["al_status_code"] != 0x001B, s
        assert s["drive_state"] == "operation_enabled", s


def test_unplugged_slave_never_stalls_the_others(ecat_segment):
    ifname, control = ecat_segment(4, "generic")
    agent = Agent(ifname, 4, groups={"arm": ("h1/axis2", "h1/axis3")})
    agent.cycle.start()
    try:
        rid = agent.cmd("enable", "axis0", "axis1", "axis2", "axis3")
        assert all(o.outcome == "done" for o in agent.wait_outcomes(rid, 4))
        assert control.request("unplug", slave=2)["ok"]
        _wait(lambda: agent.has_event("lost", "axis2"), 5, "lost event")
        _wait(lambda: agent.has_event("reflex", "axis3"), 1, "group reflex on axis3")
        assert next(d for d in agent.cycle.latest.drives if d.axis == "axis2").lost
        # Away for a while (the management thread keeps trying to recover it meanwhile): the
        # others get process data every cycle the whole time.
        c0 = agent.cycle.latest.cycle
        away_until = time.monotonic() + 1.0
        while time.monotonic() < away_until:
            st = _slave_status(control)
            _assert_running(st, (0, 1))
            assert st[3]["al_state"] == "op" and not st[3]["al_error"], st[3]  # stopped by its group, in OP
            time.sleep(0.02)
        assert agent.cycle.latest.cycle > c0 + 500
        assert _drive_states(control)[3] in ("quick_stop_active", "switch_on_disabled")
        assert control.request("plug", slave=2)["ok"]
        _wait(lambda: agent.has_event("found", "axis2"), 10, "found event")
        st = _slave_status(control)
        assert st[2]["al_state"] == "op" and not st[2]["al_error"], st[2]
        assert st[2]["drive_state"] != "operation_enabled"  # not re-enabled
        d2 = next(d for d in agent.cycle.latest.drives if d.axis == "axis2")
        assert not d2.lost and d2.goal == "disabled" and d2.al_state == "op"
        _assert_running(st, (0, 1))
        assert not any(agent.has_event(k, a) for k in ("lost", "reflex", "al_state") for a in ("axis0", "axis1"))
        r2 = agent.cmd("enable", "axis2")
        assert agent.wait_outcomes(r2, 1)[0].outcome == "done"
    finally:
        agent.cycle.stop()


def test_dropped_and_late_frames_neither_stall_nor_lose_slaves(ecat_segment):
    ifname, control = ecat_segment(3, "generic")
    agent = Agent(ifname, 3)
    agent.cycle.start()
    try:
        rid = agent.cmd("enable", "axis0", "axis1", "axis2")
        assert all(o.outcome == "done" for o in agent.wait_outcomes(rid, 3))

        def counter(name: str) -> int:
            return control.request("status")["counters"][name]

        dropped, delayed = counter("dropped"), counter("delayed")
        assert control.request("drop_frames", count=5)["ok"]
        _wait(lambda: counter("dropped") >= dropped + 5, 5, "5 frames dropped")
        assert control.request("delay_frames", count=5, delay_ms=3)["ok"]
        _wait(lambda: counter("delayed") >= delayed + 5, 5, "5 frames delayed")
        assert control.request("drop_frames", count=3)["ok"]
        assert control.request("delay_frames", count=3, delay_ms=2)["ok"]
        c1 = agent.cycle.latest.cycle
        _wait(lambda: agent.cycle.latest.cycle > c1 + 200, 5, "200 more cycles")
        _assert_running(_slave_status(control), (0, 1, 2))
        assert agent.cycle.wkc_errors > 0  # the faults were seen
        assert not agent.has_event("lost")
        assert all(d.state == "operation_enabled" and not d.lost for d in agent.cycle.latest.drives)
    finally:
        agent.cycle.stop()


def test_drives_at_rest_are_skipped_and_their_outputs_stay_on_the_wire(ecat_segment):
    """The fast path on the real path: drives at rest are not stepped, their outputs are not
    written again, and the drives still get them every frame (SOEM sends the IO map as it is):
    they stay in Operation enabled with controlword 0x000F. A fault is seen at once and reaches the
    group; a command to one drive is carried out."""
    ifname, control = ecat_segment(4, "generic")
    agent = Agent(ifname, 4, groups={"pair": ("h1/axis1", "h1/axis2")})
    agent.cycle.start()
    try:
        rid = agent.cmd("enable", "axis0", "axis1", "axis2", "axis3")
        assert all(o.outcome == "done" for o in agent.wait_outcomes(rid, 4))
        cyc = agent.cycle
        _wait(lambda: not cyc.controllers.busy, 5, "every drive at rest")
        c0, s0 = cyc.cycles, cyc.drives_stepped
        _wait(lambda: cyc.cycles >= c0 + 500, 10, "500 cycles")
        c1, s1 = cyc.cycles, cyc.drives_stepped
        # at rest nothing is stepped; a working counter error on a loaded host steps all in one cycle
        assert s1 - s0 <= (c1 - c0) * 4 // 10, (s1 - s0, c1 - c0)
        reply = control.request("status")
        assert [(s["drive_state"], s["controlword"]) for s in reply["slaves"]] == [("operation_enabled", 0x000F)] * 4
        assert control.request("fault", slave=1, error_code=0x2310)["ok"]
        _wait(lambda: agent.has_event("fault", "axis1"), 5, "fault event of axis1")
        _wait(lambda: agent.has_event("reflex", "axis2"), 1, "group reflex on axis2")
        _wait(lambda: _drive_states(control)[2] != "operation_enabled", 5, "axis2 leaving operation enabled")
        rid = agent.cmd("move", "axis3", by=2000)
        assert [o.outcome for o in agent.wait_outcomes(rid, 1)] == ["done"]
        snap = cyc.latest
        assert snap is not None
        axis3 = next(d for d in snap.drives if d.axis == "axis3")
        assert axis3.position == axis3.target_position and axis3.axis_state == "standstill"
        states = _drive_states(control)
        assert states[0] == states[3] == "operation_enabled" and states[1] in ("fault", "fault_reaction_active")
    finally:
        agent.cycle.stop()
