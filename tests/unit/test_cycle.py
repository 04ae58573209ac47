"""The agent cycle against the in-process SimBus (no root): commands, outcomes, reflexes, loss,
NMT and the ordered shutdown. Time is a fake clock advanced 1 ms per tick; nothing sleeps."""

from __future__ import annotations

import pytest

from bus_agent.bus.base import ALState
from bus_agent.bus.sim_bus import SimBus
from bus_agent.cia402.states import State
from bus_agent.config import AgentConfig, DriveConfig, DrivePolicy, Identity
from bus_agent.cycle.cycle import INBOX_MAX, STATS_EVERY, Cycle, IdentityMismatch
from bus_agent.runtime import AgentCommand, DriveCommand, Outcome

PERIOD_NS = 1_000_000


class Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns

    def s(self) -> float:
        return self.ns / 1e9


class Harness:
    def __init__(self, n: int = 3, groups: dict | None = None, drives: tuple = (), profile: str = "generic",
                 **cfg) -> None:
        self.clock = Clock()
        self.bus = SimBus(n, profile, clock=self.clock.s)
        self.config = AgentConfig(host="h1", sim_drives=n, groups=groups or {}, drives=drives, **cfg)
        self.cycle = Cycle(self.bus, self.config, clock_ns=self.clock, manage_gc=False, switch_interval_s=None)
        self.snaps = []
        self.cycle.snapshot_sink = self.snaps.append
        self.group_triggers: list[tuple[str, str]] = []
        self.cycle.group_sink = lambda g, r: self.group_triggers.append((g, r))
        self.outcomes: dict[str, list[Outcome]] = {}
        self.seq = 0

    def open(self) -> "Harness":
        self.cycle.open()
        self.ticks(5)
        return self

    def tick(self):
        self.clock.ns += PERIOD_NS
        return self.cycle.tick()

    def ticks(self, n: int):
        for _ in range(n):
            snap = self.tick()
        return snap

    def until(self, cond, max_ticks: int = 3000):
        for _ in range(max_ticks):
            snap = self.tick()
            if cond(snap):
                return snap
        raise AssertionError("condition not reached within %d cycles" % max_ticks)

    def cmd(self, op: str, *axes: str, timeout_s: float = 5.0, **args) -> str:
        self.seq += 1
        rid = f"r{self.seq}"
        self.outcomes[rid] = []
        c = DriveCommand(request_id=rid, op=op, axes=axes, args=args, timeout_s=timeout_s,
                         received_ns=self.clock.ns, on_outcome=self.outcomes[rid].append)
        assert self.cycle.submit(c)
        return rid

    def nmt(self, command: str, axis: str | None = None, timeout_s: float = 5.0) -> str:
        self.seq += 1
        rid = f"n{self.seq}"
        self.outcomes[rid] = []
        args = {"command": command} if axis is None else {"command": command, "axis": axis}
        assert self.cycle.submit(AgentCommand(request_id=rid, op="nmt", args=args, timeout_s=timeout_s,
                                              received_ns=self.clock.ns, on_outcome=self.outcomes[rid].append))
        return rid

    def done(self, rid: str, n: int = 1):
        return lambda snap: len(self.outcomes[rid]) >= n

    def state(self, pos: int) -> State:
        return self.bus.model(pos).state

    def snap_drive(self, axis: str):
        return next(d for d in self.cycle.latest.drives if d.axis == axis)


@pytest.fixture
def h():
    hh = Harness().open()
    yield hh
    hh.cycle.stop(timeout_s=1.0)


def test_nothing_enabled_without_a_command(h):
    h.ticks(200)
    assert all(h.state(i) == State.SWITCH_ON_DISABLED for i in range(3))
    assert all(d.goal == "disabled" for d in h.cycle.latest.drives)


def test_enable_reaches_operation_enabled_with_one_outcome_per_axis(h):
    rid = h.cmd("enable", "axis0", "axis1")
    h.until(h.done(rid, 2))
    h.ticks(50)
    outs = h.outcomes[rid]
    assert sorted(o.axis for o in outs) == ["axis0", "axis1"]  # exactly once per axis
    assert all(o.outcome == "done" and o.state == "operation_enabled" and o.cycles > 0 for o in outs)
    assert h.state(0) == h.state(1) == State.OPERATION_ENABLED
    assert h.state(2) == State.SWITCH_ON_DISABLED
    events = [e for s in h.snaps for e in s.events if e.kind == "outcome" and e.request_id == rid]
    assert len(events) == 2


def test_drives_addressed_together_change_in_the_same_cycle(h):
    rid = h.cmd("enable", "axis0", "axis1", "axis2")
    h.until(h.done(rid, 3))
    first_change = {}
    for s in h.snaps:
        for d in s.drives:
            if d.controlword != 0 and d.axis not in first_change:
                first_change[d.axis] = s.cycle
    assert len(set(first_change.values())) == 1, first_change
    reached = {}
    for s in h.snaps:
        for e in s.events:
            if e.kind == "outcome" and e.request_id == rid:
                reached[e.axis] = s.cycle
    assert len(set(reached.values())) == 1, reached


def test_newer_command_supersedes_pending_one(h):
    r1 = h.cmd("enable", "axis0")
    h.tick()
    r2 = h.cmd("disable", "axis0")
    h.until(h.done(r2))
    assert [o.outcome for o in h.outcomes[r1]] == ["failed"]
    assert h.outcomes[r1][0].reason == f"superseded by {r2}"
    assert [o.outcome for o in h.outcomes[r2]] == ["done"]
    h.ticks(20)
    assert len(h.outcomes[r1]) == 1 and len(h.outcomes[r2]) == 1
    assert h.state(0) == State.SWITCH_ON_DISABLED


def test_command_timeout_withdraws_the_upward_goal(h):
    rid = h.cmd("switch_on", "axis0", timeout_s=0.001)  # due before the drive can get there
    h.ticks(30)
    assert [o.outcome for o in h.outcomes[rid]] == ["timeout"]
    assert h.snap_drive("axis0").goal == "disabled"  # nobody waits for it: not pursued
    assert h.state(0) == State.SWITCH_ON_DISABLED


def test_enable_of_faulted_drive_fails_and_fault_reset_is_explicit(h):
    h.bus.inject_fault(1, 0x2310)
    h.ticks(30)
    assert h.state(1) == State.FAULT
    rid = h.cmd("enable", "axis1")
    h.until(h.done(rid))
    assert h.outcomes[rid][0].outcome == "failed"
    assert h.outcomes[rid][0].error_code == 0x2310
    h.ticks(200)
    assert h.state(1) == State.FAULT  # never reset by itself
    r2 = h.cmd("fault_reset", "axis1")
    h.until(h.done(r2))
    assert h.outcomes[r2][0].outcome == "done"
    h.ticks(10)
    assert h.state(1) == State.SWITCH_ON_DISABLED
    r3 = h.cmd("fault_reset", "axis0")  # not in fault: done, nothing to reset
    h.until(h.done(r3))
    assert h.outcomes[r3][0].outcome == "done" and "not in fault" in h.outcomes[r3][0].reason


def test_disable_of_faulted_drive_is_done_and_says_so_without_resetting(h):
    h.bus.inject_fault(1, 0x2310)
    h.ticks(30)
    assert h.state(1) == State.FAULT
    rid = h.cmd("disable", "axis1")
    h.until(h.done(rid))
    o = h.outcomes[rid][0]
    assert (o.outcome, o.state, o.error_code) == ("done", "fault", 0x2310)
    assert "without torque" in o.reason and "fault" in o.reason
    h.ticks(100)
    assert h.state(1) == State.FAULT  # disable never resets a fault


def test_unknown_axis_and_bad_args_rejected(h):
    rid = h.cmd("enable", "nope")
    h.until(h.done(rid))
    assert h.outcomes[rid][0].outcome == "rejected"
    r2 = h.cmd("set_mode", "axis0", mode=42)
    h.until(h.done(r2))
    assert h.outcomes[r2][0].outcome == "rejected"
    assert h.state(0) == State.SWITCH_ON_DISABLED


def test_set_mode_done_on_echo_and_halt_immediate(h):
    rid = h.cmd("set_mode", "axis0", mode=9)
    h.until(h.done(rid))
    assert h.outcomes[rid][0].outcome == "done"
    assert h.snap_drive("axis0").mode_display == 9
    r2 = h.cmd("halt", "axis0", on=True)
    snap = h.until(h.done(r2))
    assert h.outcomes[r2][0].outcome == "done"
    assert snap.drives[0].halt and snap.drives[0].controlword & 0x0100


def test_inbox_is_bounded(h):
    accepted = sum(h.cycle.submit(DriveCommand(request_id=f"x{i}", op="halt", axes=("axis0",), args={"on": False}))
                   for i in range(INBOX_MAX + 10))
    assert accepted == INBOX_MAX


def test_group_reflex_in_the_same_cycle():
    hh = Harness(n=3, groups={"arm": ("h1/axis0", "h1/axis1", "h2/axis9")}).open()
    try:
        rid = hh.cmd("enable", "axis0", "axis1", "axis2")
        hh.until(hh.done(rid, 3))
        hh.bus.inject_fault(0, 0x7500)
        snap = hh.until(lambda s: any(e.kind == "reflex" for e in s.events), 50)
        # the fault was seen in this cycle, and axis1 got its quick stop in this same cycle
        assert snap.drives[0].state in ("fault_reaction_active", "fault")
        assert snap.drives[1].goal == "quick_stop"
        assert snap.drives[1].controlword & 0x0087 == 0x0002
        assert snap.drives[2].goal == "enabled"  # not in the group
        # ... and it went out in an express exchange right after that cycle, not with the next frame
        assert hh.cycle.express_exchanges == 1 and int(hh.bus.model(1).read(0x6040, 0)) & 0x0087 == 0x0002
        assert hh.group_triggers and hh.group_triggers[0][0] == "arm"
        hh.until(lambda s: hh.state(1) in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED), 3000)
        assert hh.state(2) == State.OPERATION_ENABLED
    finally:
        hh.cycle.stop(timeout_s=1.0)


def test_remote_group_trigger_reacts_next_cycle():
    hh = Harness(n=2, groups={"arm": ("h1/axis0", "h2/axis0")}).open()
    try:
        rid = hh.cmd("enable", "axis0", "axis1")
        hh.until(hh.done(rid, 2))
        hh.cycle.trigger_group("arm", "h2/axis0 fault 0x7500")
        snap = hh.tick()
        assert snap.drives[0].goal == "quick_stop" and snap.drives[1].goal == "enabled"
        assert any(e.kind == "reflex" and e.axis == "axis0" for e in snap.events)
        assert not hh.group_triggers  # a remote trigger is not sent back out
    finally:
        hh.cycle.stop(timeout_s=1.0)


def test_lost_slave_reacts_and_returns_disabled():
    hh = Harness(n=2, groups={"arm": ("h1/axis0", "h1/axis1")}).open()
    try:
        rid = hh.cmd("enable", "axis0", "axis1")
        hh.until(hh.done(rid, 2))
        hh.bus.unplug(1)
        snap = hh.until(lambda s: any(e.kind == "lost" for e in s.events), 20)
        assert snap.drives[1].lost
        assert snap.drives[0].goal == "quick_stop"  # its group reacted in the same cycle
        assert any(e.kind == "reflex" and e.axis == "axis0" for e in snap.events)
        # the unplugged slave's missing working counter is counted, and reaches the published stats
        assert hh.cycle.wkc_errors >= 1
        hh.until(lambda s: s.stats.wkc_errors >= 1, 2 * STATS_EVERY)
        r2 = hh.cmd("enable", "axis1")
        hh.until(hh.done(r2))
        assert hh.outcomes[r2][0].outcome == "rejected"
        hh.bus.plug(1)
        snap = hh.until(lambda s: any(e.kind == "found" for e in s.events), 200)
        assert not snap.drives[1].lost and snap.drives[1].goal == "disabled"
        hh.ticks(300)
        assert hh.state(1) == State.SWITCH_ON_DISABLED  # never re-enabled without a new command
        r3 = hh.cmd("enable", "axis1")
        hh.until(hh.done(r3))
        assert hh.outcomes[r3][0].outcome == "done"
    finally:
        hh.cycle.stop(timeout_s=1.0)


def test_ordered_shutdown_order_on_the_drive():
    hh = Harness(n=2).open()
    rid = hh.cmd("enable", "axis0", "axis1")
    hh.until(hh.done(rid, 2))
    seen: list[list[int]] = [[], []]
    for pos in range(2):
        model = hh.bus.model(pos)
        orig = model.apply_outputs

        def spy(out, orig=orig, pos=pos):
            if not seen[pos] or seen[pos][-1] != out.controlword:
                seen[pos].append(out.controlword)
            orig(out)
        model.apply_outputs = spy
    hh.cycle.stop(timeout_s=2.0)
    for pos in range(2):
        assert seen[pos][:4] == [0x000F, 0x0007, 0x0006, 0x0000], seen[pos]
        assert hh.state(pos) == State.SWITCH_ON_DISABLED
    assert hh.bus.read_al_status()[0].state == ALState.INIT
    assert hh.cycle.state == "stopped"
    hh.cycle.stop()  # idempotent
    assert not hh.cycle.submit(DriveCommand(request_id="late", op="enable", axes=("axis0",)))


def test_nmt_stop_brings_drives_down_first_then_start_returns_disabled(h):
    rid = h.cmd("enable", "axis0")
    h.until(h.done(rid))
    n1 = h.nmt("stop", axis="axis0")
    h.until(h.done(n1))
    assert h.outcomes[n1][0].outcome == "done", h.outcomes[n1]
    assert h.outcomes[n1][0].axis == ""
    st = h.bus.read_al_status()
    assert st[0].state == ALState.SAFEOP and st[1].state == ALState.OP
    assert h.state(0) == State.SWITCH_ON_DISABLED  # taken down before leaving OP
    assert not h.snap_drive("axis0").lost
    r2 = h.cmd("enable", "axis0")
    h.until(h.done(r2))
    assert h.outcomes[r2][0].outcome == "rejected"
    n2 = h.nmt("start")
    h.until(h.done(n2))
    assert h.outcomes[n2][0].outcome == "done"
    assert all(s.state == ALState.OP for s in h.bus.read_al_status())
    h.ticks(50)
    assert h.state(0) == State.SWITCH_ON_DISABLED


@pytest.mark.parametrize("command,al", [("preop", ALState.PREOP), ("reset_comm", ALState.PREOP),
                                        ("reset_node", ALState.OP)])
def test_nmt_ops(h, command, al):
    n = h.nmt(command)
    h.until(h.done(n))
    assert h.outcomes[n][0].outcome == "done", h.outcomes[n]
    assert all(s.state == al for s in h.bus.read_al_status())
    assert not any(d.lost for d in h.cycle.latest.drives)


def test_nmt_bad_command_rejected(h):
    n = h.nmt("explode")
    h.until(h.done(n))
    assert h.outcomes[n][0].outcome == "rejected"
    assert all(s.state == ALState.OP for s in h.bus.read_al_status())


def test_identity_mismatch_stops_startup():
    clock = Clock()
    bus = SimBus(2, clock=clock.s)
    cfg = AgentConfig(host="h1", sim_drives=2,
                      drives=(DriveConfig(slave=0, identity=Identity(0xDEAD, 0xBEEF)), DriveConfig(slave=1)))
    cyc = Cycle(bus, cfg, clock_ns=clock, manage_gc=False, switch_interval_s=None)
    with pytest.raises(IdentityMismatch, match=r"slave 0 .*0x0000DEAD"):
        cyc.open()
    assert cyc.state == "error"


def test_configured_drives_axis_names_and_policy():
    hh = Harness(n=2, drives=(DriveConfig(slave=1, axis="lift", policy=DrivePolicy(transition_timeout_s=0.05)),))
    hh.open()
    try:
        assert hh.cycle.axes == ("lift",)
        assert [d.axis for d in hh.cycle.latest.drives] == ["lift"]
        # the configured 0.05 s transition timeout (default 5 s) decides the outcome of a goal the
        # drive never reaches: this drive ignores its controlword
        model = hh.bus.model(1)
        model._transition = lambda cw, reset_edge: None
        rid = hh.cmd("enable", "lift", timeout_s=10.0)
        hh.until(hh.done(rid), 200)
        (out,) = hh.outcomes[rid]
        assert out.outcome == "timeout" and "within 0.05 s" in out.reason
        assert 45 <= out.cycles <= 60  # 1 ms per fake tick
        hh.ticks(1)
        assert hh.cycle.latest.drives[0].goal == "disabled"  # withdrawn: the status says so
        del model._transition  # the drive answers again: told "timeout", it must not become enabled
        hh.ticks(300)
        assert hh.state(1) == State.SWITCH_ON_DISABLED
    finally:
        hh.cycle.stop(timeout_s=1.0)


class TickingClock(Clock):
    """Advances 1 us per read, so the spin-wait ends."""

    def __call__(self) -> int:
        self.ns += 1000
        return self.ns


def test_overruns_counted_with_injected_clock():
    clock = TickingClock()
    bus = SimBus(1, clock=clock.s)
    cfg = AgentConfig(host="h1", sim_drives=1)
    schedule = iter([0, 0, 3_500_000, 0, 0, 0, 2_500_000] + [0] * 100)

    def fake_sleep(s: float) -> None:
        clock.ns += int(s * 1e9)

    cyc = Cycle(bus, cfg, clock_ns=clock, sleep=fake_sleep, manage_gc=False, switch_interval_s=None)
    cyc.open()
    orig = cyc.run_cycle
    count = [0]

    def slow_cycle(now_ns: int) -> None:
        orig(now_ns)
        clock.ns += 100_000 + next(schedule)  # each cycle takes 100 us, two take much longer
        count[0] += 1
        if count[0] >= 20:
            cyc.begin_stop(True, 0.0)

    cyc.run_cycle = slow_cycle  # type: ignore[method-assign]
    cyc.run()
    assert cyc.overruns == 2
    periods = sorted(cyc.statistics.periods[i] for i in range(1, 20))
    # drift-free: back on the 1 ms grid after each overrun (within the fake clock's 1 us reads)
    assert abs(periods[len(periods) // 2] - 1_000_000) <= 5_000
    cyc.stop()


def test_auto_reset_is_off_by_default_and_bounded_when_configured():
    from bus_agent.config import AutoReset

    policy = DrivePolicy(auto_reset=AutoReset(enabled=True, max_attempts=2, backoff_s=0.02, backoff_max_s=0.05))
    hh = Harness(n=2, drives=(DriveConfig(slave=0, policy=policy), DriveConfig(slave=1))).open()

    def warnings() -> list:
        return [e for s in hh.snaps for e in s.events if e.kind == "warning" and e.axis == "axis0"]

    def fault_then_reset_ms() -> float:
        """Inject a fault on axis0; fake ms from its Fault state to the next auto reset."""
        hh.bus.inject_fault(0, 0x2310)
        hh.until(lambda s: hh.state(0) == State.FAULT, 100)
        t0, n = hh.clock.ns, len(warnings())
        hh.until(lambda s: len(warnings()) > n, 500)
        return (hh.clock.ns - t0) / 1e6

    try:
        hh.bus.inject_fault(1, 0x2310)
        # attempt 1 after backoff_s, attempt 2 after 2 x backoff_s (exponential backoff)
        assert 19 <= fault_then_reset_ms() <= 25
        assert "auto fault reset attempt 1/2" in warnings()[-1].detail
        hh.until(lambda s: hh.state(0) == State.SWITCH_ON_DISABLED, 100)
        assert hh.snap_drive("axis0").goal == "disabled"  # reset, not re-enabled
        assert 39 <= fault_then_reset_ms() <= 45
        assert "auto fault reset attempt 2/2" in warnings()[-1].detail
        hh.until(lambda s: hh.state(0) == State.SWITCH_ON_DISABLED, 100)
        # attempts exhausted: reported once, then the drive waits in Fault for a command
        hh.bus.inject_fault(0, 0x2310)
        hh.until(lambda s: any("exhausted" in w.detail for w in warnings()), 500)
        hh.ticks(500)
        assert hh.state(0) == State.FAULT
        assert sum("exhausted" in w.detail for w in warnings()) == 1
        assert hh.state(1) == State.FAULT  # not configured: never reset without a command
        rid = hh.cmd("fault_reset", "axis0")
        hh.until(hh.done(rid), 500)
        assert hh.outcomes[rid][0].outcome == "done" and hh.state(0) == State.SWITCH_ON_DISABLED
    finally:
        hh.cycle.stop(timeout_s=1.0)
