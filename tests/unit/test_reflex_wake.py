"""A remote group trigger wakes the sleeping cycle and goes out in an express exchange
(``Cycle._express``) without moving the schedule or the DC PI; the cycle thread's eventfd wake
over SimBus. The first tests run the loop (``Cycle._run``) on a fake clock: nothing sleeps."""

from __future__ import annotations

import queue
import threading
import time

from bus_agent.bus.sim_bus import SimBus
from bus_agent.cia402.states import State
from bus_agent.config import AgentConfig
from bus_agent.cycle.cycle import Cycle
from bus_agent.runtime import CycleSnapshot, DriveCommand

from tests.unit.test_cycle import PERIOD_NS, Clock

GROUPS = {"arm": ("h1/axis0", "h2/axis0")}


class CountingDc:
    """Stands in for bus_agent.bus.dc.DcSync: records every PI step (no correction)."""

    def __init__(self) -> None:
        self.steps: list[int] = []   # the lateness each step was given
        self.offset_ns = 0

    def step(self, dc_time_ns: int, late_ns: int = 0, hold: bool = False) -> int:
        self.steps.append(late_ns)
        return 0


def _enabled_cycle(express: bool = True) -> tuple[Cycle, SimBus, Clock, list[CycleSnapshot], list[int]]:
    """A Cycle on a fake clock with axis0 and axis1 enabled (by tick), exchanges time-stamped."""
    clock = Clock()
    bus = SimBus(2, clock=clock.s)
    cyc = Cycle(bus, AgentConfig(host="h1", sim_drives=2, groups=GROUPS), clock_ns=clock,
                sleep=lambda s: None, manage_gc=False, switch_interval_s=None)
    cyc.express_reflex = express
    snaps: list[CycleSnapshot] = []
    cyc.snapshot_sink = snaps.append
    cyc.open()
    done: list = []
    assert cyc.submit(DriveCommand(request_id="e", op="enable", axes=("axis0", "axis1"), on_outcome=done.append))
    for _ in range(200):
        clock.ns += PERIOD_NS
        cyc.tick()
        if len(done) == 2:
            break
    assert [o.outcome for o in done] == ["done", "done"]
    exchanges: list[int] = []
    exchange = bus.exchange

    def stamped() -> int:
        exchanges.append(clock.ns)
        return exchange()

    bus.exchange = stamped  # type: ignore[method-assign]
    snaps.clear()
    return cyc, bus, clock, snaps, exchanges


def _run_cycles(cyc: Cycle, clock: Clock, cycles: int, trigger_in_sleep: int) -> list[int]:
    """Run the loop for ``cycles`` cycles (each takes 100 us); the ``trigger_in_sleep``-th sleep
    is cut short halfway by a remote trigger. Returns the start times of the cycles."""
    starts: list[int] = []
    sleeps = [0]

    def sleep(s: float) -> None:
        sleeps[0] += 1
        if sleeps[0] == trigger_in_sleep:
            clock.ns += int(s * 1e9) // 2
            cyc.trigger_group("arm", "h2/axis0 fault 0x7305")
        else:
            clock.ns += int(s * 1e9)

    def spin_clock() -> int:
        clock.ns += 1_000  # every read of the clock takes 1 us, so the spin ends
        return clock.ns

    orig = cyc.run_cycle

    def timed_cycle(now_ns: int) -> None:
        starts.append(now_ns)
        orig(now_ns)
        clock.ns += 100_000
        if len(starts) >= cycles:
            cyc.begin_stop(True, 0.0)

    cyc.timing.sleep = sleep
    cyc.clock_ns = spin_clock
    cyc.run_cycle = timed_cycle  # type: ignore[method-assign]
    cyc.run()
    return starts


def test_a_trigger_during_the_sleep_goes_out_at_once_and_the_schedule_stays() -> None:
    cyc, bus, clock, snaps, exchanges = _enabled_cycle()
    dc = cyc.dc.sync = CountingDc()  # type: ignore[assignment]
    starts = _run_cycles(cyc, clock, cycles=6, trigger_in_sleep=2)
    # one express exchange between the 2nd and 3rd cycle, at the trigger (halfway through the sleep)
    assert cyc.express_exchanges == 1
    assert len(exchanges) == 7
    express_at = exchanges[2]
    assert starts[1] < express_at < starts[2]
    assert starts[2] - express_at > 300_000                 # not at the deadline: hundreds of us before
    # the schedule did not move: every period is the period (the fake clock's 1 us reads aside)
    periods = [b - a for a, b in zip(starts, starts[1:])]
    assert all(abs(p - PERIOD_NS) <= 5_000 for p in periods), periods
    # the PI stepped once per cycle, never for the express frame, and saw no lateness
    assert len(dc.steps) == 6 and all(0 <= late <= 5_000 for late in dc.steps)
    assert cyc.overruns == 0
    # the express snapshot: numbered as the cycle before it, the reflex in it, quick stop sent
    express = [s for s in snaps if any(e.kind == "reflex" for e in s.events)]
    assert len(express) == 1
    assert express[0].cycle == snaps[1].cycle and express[0] is snaps[2]
    d0 = express[0].drives[0]
    assert d0.goal == "quick_stop" and d0.controlword & 0x0087 == 0x0002   # 0x6040 quick stop (transition 11)
    assert express[0].drives[1].goal == "enabled"
    # the drive had the quick stop before the next cycle, which saw it leave operation enabled
    nxt = snaps[3]
    assert nxt.drives[0].state == State.QUICK_STOP_ACTIVE.value
    assert any(e.kind == "transition" and e.axis == "axis0" and e.from_state == "operation_enabled"
               for e in nxt.events)
    assert not any(e.kind == "reflex" for s in snaps[3:] for e in s.events)  # applied once
    assert all(s.drives[1].state == "operation_enabled" for s in snaps)      # not a member


def test_without_express_the_next_cycle_applies_the_trigger() -> None:
    cyc, bus, clock, snaps, exchanges = _enabled_cycle(express=False)
    starts = _run_cycles(cyc, clock, cycles=6, trigger_in_sleep=2)
    assert cyc.express_exchanges == 0 and len(exchanges) == 6 == len(starts)
    reflex = [s for s in snaps if any(e.kind == "reflex" for e in s.events)]
    assert len(reflex) == 1 and reflex[0].cycle == snaps[2].cycle and reflex[0].drives[0].goal == "quick_stop"


def test_a_trigger_for_members_at_rest_sends_no_extra_frame() -> None:
    cyc, bus, clock, snaps, exchanges = _enabled_cycle()
    cyc.groups = type(cyc.groups)("h1", {"other": ("h1/axis9", "h2/axis0")}, ("axis0", "axis1"))
    clock.ns += PERIOD_NS
    cyc.trigger_group("other", "h2/axis0 lost")
    cyc.express(clock.ns)
    assert cyc.express_exchanges == 0 and not exchanges      # no local member: nothing to send
    assert snaps and snaps[-1].events == ()


def test_the_cycle_thread_wakes_for_a_trigger_and_the_member_leaves_operation_enabled() -> None:
    """Real threads and clock: a 200 ms period, the trigger from another thread just after a
    cycle; the reflex is applied long before the next deadline (eventfd wake)."""
    bus = SimBus(2, sm_watchdog_s=1.0)  # the period is longer than the default 100 ms watchdog
    cyc = Cycle(bus, AgentConfig(host="h1", sim_drives=2, groups=GROUPS, cycle_us=200_000))
    snaps: queue.SimpleQueue = queue.SimpleQueue()
    cyc.snapshot_sink = snaps.put
    cyc.start()
    try:
        done: queue.SimpleQueue = queue.SimpleQueue()
        assert cyc.submit(DriveCommand(request_id="e", op="enable", axes=("axis0",), on_outcome=done.put))
        assert done.get(timeout=30).outcome == "done"
        while not snaps.empty():
            snaps.get_nowait()
        before = snaps.get(timeout=5)                          # a cycle just ran: 200 ms until the next
        fired = threading.Event()
        threading.Thread(target=lambda: (cyc.trigger_group("arm", "h2/axis0 fault 0x7305"), fired.set())).start()
        assert fired.wait(5)
        snap = snaps.get(timeout=5)
        assert any(e.kind == "reflex" and e.axis == "axis0" for e in snap.events), snap.events
        assert snap.cycle == before.cycle                      # not waiting for the next cycle
        assert cyc.express_exchanges == 1
        assert int(bus.model(0).read(0x6040, 0)) & 0x0087 == 0x0002  # the drive has the quick stop
        nxt = snaps.get(timeout=5)
        assert nxt.cycle == before.cycle + 1 and nxt.drives[0].state == State.QUICK_STOP_ACTIVE.value
    finally:
        cyc.stop()
    assert cyc.triggers.wake_fd == -1
    cyc.trigger_group("arm", "after stop")  # the closed wake is not written


def test_ecat_sim_steps_its_drives_after_every_frame_of_a_1ms_cycle() -> None:
    """ecat-sim's frame loop calls step_some right after answering each frame; with frames every
    1 ms (a few us of jitter either way) every frame is followed by one round of model steps, so
    a drive answers a new controlword in the next frame (it was about 60 % of the frames)."""
    from bus_agent.sim.ecat.segment import Segment

    import time

    seg = Segment(2)
    t0 = time.monotonic() + 1.0
    rounds = 0
    for k in range(1000):
        now = t0 + k * 1e-3 + 30e-6 + (8e-6 if k % 3 == 0 else -8e-6)
        before = seg.escs[0].last_step
        assert not seg.step_some(now, 1e-3, 8)   # one call steps both (budget 8)
        rounds += seg.escs[0].last_step != before
    assert rounds >= 999
    # far behind (an idle segment at 10 ms, then 1 ms frames): no burst of catch-up rounds
    later = t0 + 5.0
    steps = [seg.step_some(later + i * 1e-4, 1e-3, 8) or seg.escs[0].last_step for i in range(5)]
    assert len(set(steps)) == 1


def test_the_gateway_publishes_a_new_fault_at_once_on_the_callers_thread() -> None:
    """``publish_bad_now`` (the gateway process's bridge reader calls it per snapshot): the
    status of a drive newly in fault goes out from the caller's thread, without the publish
    thread (its heartbeat an hour away, never woken here); once per change."""
    import time

    import zenoh

    from bus_agent import runtime as rt
    from bus_agent.gateway.zenoh_config import make_zenoh_config
    from schemas import keys
    from schemas import messages as m
    from tests.unit.test_gateway import HOST, FakeCycle, free_port, make_gateway, wait_for

    port = free_port()
    agent_s = zenoh.open(make_zenoh_config("peer", [f"tcp/127.0.0.1:{port}"], []))
    client = zenoh.open(make_zenoh_config("peer", [], [f"tcp/127.0.0.1:{port}"]))
    cycle = FakeCycle()
    gateway = make_gateway(agent_s, cycle, heartbeat_s=3600.0)
    got: list = []
    sub = client.declare_subscriber(keys.drive_status(HOST, "x2"), lambda s: got.append(m.decode(s.payload)))
    try:
        wait_for(lambda: gateway.publisher.status_pubs["x2"].matching_status.matching, what="the subscriber matched")

        def snap() -> rt.CycleSnapshot:
            return rt.CycleSnapshot(cycle.cycle, time.time_ns(), tuple(cycle.drives.values()), (), rt.CycleStats())

        gateway.publisher.publish_bad_now(snap())                  # nothing bad: nothing published
        n = len(got)
        cycle.set("x2", state="fault", error_code=0x7305)
        gateway.publisher.publish_bad_now(snap())
        gateway.publisher.publish_bad_now(snap())                  # unchanged: not again
        wait_for(lambda: any(s.state == "fault" for s in got[n:]), what="the fault status")
        assert [(s.axis, s.state, s.error_code) for s in got[n:]] == [("x2", "fault", 0x7305)]
    finally:
        sub.undeclare()
        gateway.close()
        client.close()
        agent_s.close()


def test_the_drive_models_rest_path_equals_the_general_path() -> None:
    """DriveModel.rest_fast_path (the idle demo's sim cost): random controlwords, modes, targets,
    faults and resets; every object and the state equal to a model on the general path."""
    import random

    from bus_agent.bus.pdo import DriveOutputs
    from bus_agent.sim.drive_model import DriveModel

    rng = random.Random(13)
    fast, full = DriveModel(serial=1), DriveModel(serial=1)
    full.rest_fast_path = False
    fast.home_switch_position = full.home_switch_position = 500
    words = (0x0000, 0x0002, 0x0006, 0x0007, 0x000F, 0x010F, 0x0080, 0x000B)
    for step in range(6000):
        if step % 40 == 0:
            out = DriveOutputs(controlword=rng.choice(words), target_position=rng.randint(-2000, 2000),
                               target_velocity=rng.randint(-5000, 5000), target_torque=rng.randint(-100, 100),
                               modes_of_operation=rng.choice((8, 9, 10, 1, 3)))
            fast.apply_outputs(out)
            full.apply_outputs(out)
        if step % 997 == 500:
            fast.inject_fault(0x7305)
            full.inject_fault(0x7305)
        dt = rng.choice((0.001, 0.0005, 0.002))
        fast.step(dt)
        full.step(dt)
        assert fast.state == full.state and fast._values == full._values, step
        assert (fast.position, fast.velocity) == (full.position, full.velocity), step


def test_bridge_out_is_woken_only_when_there_is_something_to_forward() -> None:
    """GatewayProcess.on_snapshot: a cycle at rest hands on the very tuple of drive snapshots;
    then nothing wakes bridge-out (its periodic wake-up forwards the statistics). A changed
    drive, an event, an outcome or a new agent state wakes it."""
    from bus_agent import runtime as rt
    from bus_agent.gateway.bridge import GatewayProcess

    gp = GatewayProcess(object(), {"host": "h1"}, None)
    drives = (rt.DriveSnapshot("x", 0, "switch_on_disabled", 0x0250, 0, "disabled", False, 8, 8, 0, 0, 0, 0, "",
                               "op", False),)

    def snap(drives: tuple, events: tuple = (), state: str = "running") -> rt.CycleSnapshot:
        return rt.CycleSnapshot(1, 0, drives, events, rt.CycleStats(), agent_state=state)

    def woken(s: rt.CycleSnapshot) -> bool:
        gp._wake.clear()
        gp.on_snapshot(s)
        return gp._wake.is_set()

    assert woken(snap(drives))                      # the first
    assert not woken(snap(drives))                  # at rest: the same tuple
    assert woken(snap((drives[0],)))                # a new tuple: something changed
    assert not woken(snap(gp._latest.drives))  # type: ignore[union-attr]
    assert woken(snap(gp._latest.drives, events=(rt.CycleEvent("x", "fault"),)))  # type: ignore[union-attr]
    gp._on_outcome(1, rt.Outcome("x", "done"))
    assert woken(snap(gp._latest.drives))           # type: ignore[union-attr]
    gp._outcomes.clear()
    assert woken(snap(gp._latest.drives, state="stopping"))  # type: ignore[union-attr]


def test_the_spin_adapts_by_default_unless_the_cycle_thread_is_real_time() -> None:
    from bus_agent.cycle.cycle import SPIN_NS

    cfg = AgentConfig(host="h1", sim_drives=1)
    assert Cycle(SimBus(1), cfg).spin_ns is None                      # the demo, a laptop: CPU first
    assert Cycle(SimBus(1), cfg, rt_priority=10).spin_ns == SPIN_NS   # SCHED_FIFO: jitter first


def test_express_reflex_is_a_cycle_setting_on_by_default() -> None:
    import pytest

    from bus_agent.config import ConfigError, config_from_dict

    assert config_from_dict({"host": "h1", "sim_drives": 1}).express_reflex is True
    assert config_from_dict({"host": "h1", "sim_drives": 1, "cycle": {"express_reflex": False}}).express_reflex is False
    with pytest.raises(ConfigError, match="express_reflex"):
        config_from_dict({"host": "h1", "sim_drives": 1, "cycle": {"express_reflex": "yes"}})


def test_no_express_frame_while_another_drive_follows_a_trajectory() -> None:
    """The express frame would hand a moving drive its next target a period early (then again):
    while any non-reacting drive has a plan, the reflex is applied at once but goes out with the
    next frame."""
    cyc, bus, clock, snaps, exchanges = _enabled_cycle()
    moved: list = []
    assert cyc.submit(DriveCommand(request_id="m", op="move", axes=("axis1",), args={"by": 200_000},
                                   on_outcome=moved.append))
    for _ in range(20):
        clock.ns += PERIOD_NS
        cyc.tick()
    d1 = next(d for d in cyc.drives if d.axis == "axis1")
    assert d1.motion.plan is not None and not moved          # axis1 is moving
    n = len(exchanges)
    clock.ns += PERIOD_NS // 2
    cyc.trigger_group("arm", "h2/axis0 fault 0x7305")
    cyc.express(clock.ns)
    assert cyc.express_exchanges == 0 and len(exchanges) == n   # no extra frame
    assert snaps[-1].drives[0].goal == "quick_stop"             # but the reflex is applied now
    assert any(e.kind == "reflex" for e in snaps[-1].events)
    clock.ns += PERIOD_NS // 2
    cyc.tick()                                                  # and goes out with the next frame
    clock.ns += PERIOD_NS
    snap = cyc.tick()
    assert snap.drives[0].state == "quick_stop_active" and snap.drives[1].state == "operation_enabled"


def test_no_express_frame_on_a_bus_without_express_exchange() -> None:
    """CANopen: an exchange sends a SYNC, a cycle for every node; the reflex waits for the next."""
    cyc, bus, clock, snaps, exchanges = _enabled_cycle()
    bus.express_exchange = False  # type: ignore[misc]
    clock.ns += PERIOD_NS // 2
    cyc.trigger_group("arm", "h2/axis0 fault 0x7305")
    cyc.express(clock.ns)
    assert cyc.express_exchanges == 0 and not exchanges and snaps[-1].drives[0].goal == "quick_stop"
    from bus_agent.bus.canopen.bus import CanopenBus
    assert CanopenBus.express_exchange is False


def test_triggers_as_datagrams_wake_the_cycle_thread_itself() -> None:
    """Cycle.trigger_socket (the gateway process's triggers): the cycle thread's sleep waits on
    the socket and reads ``group NUL reason`` itself; a datagram that comes while the cycle runs
    (here: sent from the snapshot sink, at the cycle's end) wakes the sleep after it at once, so
    it goes out in an express exchange well before the next deadline. Real threads and clock, a
    200 ms period."""
    import socket

    bus = SimBus(2, sm_watchdog_s=1.0)
    cyc = Cycle(bus, AgentConfig(host="h1", sim_drives=2, groups=GROUPS, cycle_us=200_000))
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    cyc.trigger_socket(ours)
    snaps: queue.SimpleQueue = queue.SimpleQueue()
    cyc.snapshot_sink = snaps.put
    cyc.start()
    try:
        done: queue.SimpleQueue = queue.SimpleQueue()
        assert cyc.submit(DriveCommand(request_id="e", op="enable", axes=("axis0",), on_outcome=done.put))
        assert done.get(timeout=30).outcome == "done"
        while not snaps.empty():
            snaps.get_nowait()
        before = snaps.get(timeout=5)
        theirs.send("arm\0h2/axis0 fault 0x7305 (é)".encode())
        snap = snaps.get(timeout=5)
        ev = [e for e in snap.events if e.kind == "reflex"]
        assert ev and ev[0].axis == "axis0" and "h2/axis0 fault 0x7305 (é)" in ev[0].detail
        assert snap.cycle == before.cycle and cyc.express_exchanges == 1
        # a datagram during the cycle's work: the sleep after it wakes at once
        sent: list[int] = []

        def send_in_cycle(s) -> None:
            snaps.put(s)
            if not sent and not any(e.kind == "reflex" for e in s.events):
                sent.append(time.monotonic_ns())
                theirs.send(b"arm\0h2/axis0 lost")

        while not snaps.empty():
            snaps.get_nowait()
        cyc.snapshot_sink = send_in_cycle
        snap = snaps.get(timeout=5)
        while not any(e.kind == "reflex" for e in snap.events):
            snap = snaps.get(timeout=5)
        assert time.monotonic_ns() - sent[0] < 100_000_000  # not the next deadline, 200 ms on
        assert "h2/axis0 lost" in [e.detail for e in snap.events if e.kind == "reflex"][0]
    finally:
        cyc.stop()
        theirs.close()
    assert ours.fileno() == -1  # closed with the bus


def test_a_trigger_taken_by_the_cycle_goes_out_right_after_it() -> None:
    """A trigger that came during the spin or the cycle's work is taken by the cycle; its reflex
    goes out in an express exchange right after that cycle, not with the next scheduled frame:
    the drive has the quick stop before the next deadline. Without express it waits for it."""
    for express in (True, False):
        cyc, bus, clock, snaps, exchanges = _enabled_cycle(express)
        clock.ns += PERIOD_NS
        cyc.trigger_group("arm", "h2/axis0 fault 0x7305")  # queued before the cycle ran (the spin)
        cyc.tick()
        assert cyc.express_exchanges == int(express) and len(exchanges) == 1 + int(express)
        assert any(e.kind == "reflex" for e in snaps[-1].events)
        # the drive model already holds the quick stop (0x6040 bits 0x0087 == 0x0002) only with express
        has_it = int(bus.model(0).read(0x6040, 0)) & 0x0087 == 0x0002
        assert has_it == express
        clock.ns += PERIOD_NS
        cyc.tick()
        assert cyc.express_exchanges == int(express)  # one extra frame, once
        if express:
            assert snaps[-1].drives[0].state == State.QUICK_STOP_ACTIVE.value
        assert snaps[-1].drives[1].state == "operation_enabled"  # not a member
