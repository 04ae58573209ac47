"""The cycle in its own thread (real monotonic clock) over SimBus: commands from another thread,
snapshots through the sink, ordered stop. Waits are on events with deadlines."""

from __future__ import annotations

import gc
import queue
import threading
import time

from bus_agent.bus.base import ALState
from bus_agent.bus.sim_bus import SimBus
from bus_agent.cia402.states import State
from bus_agent.config import AgentConfig
from bus_agent.cycle.cycle import Cycle
from bus_agent.runtime import AgentCommand, DriveCommand


def test_threaded_enable_snapshots_and_ordered_stop():
    bus = SimBus(4)
    cyc = Cycle(bus, AgentConfig(host="h1", sim_drives=4))
    snaps: queue.SimpleQueue = queue.SimpleQueue()
    cyc.snapshot_sink = snaps.put
    cyc.start()
    try:
        assert not gc.isenabled()  # no cyclic GC pauses while the loop runs
        outcomes: queue.SimpleQueue = queue.SimpleQueue()
        assert cyc.submit(DriveCommand(request_id="e1", op="enable", axes=("axis0", "axis1", "axis2", "axis3"),
                                       on_outcome=outcomes.put))
        got = [outcomes.get(timeout=10) for _ in range(4)]
        assert sorted(o.axis for o in got) == ["axis0", "axis1", "axis2", "axis3"]
        assert all(o.outcome == "done" for o in got)
        assert all(bus.model(i).state == State.OPERATION_ENABLED for i in range(4))
        first = snaps.get(timeout=1)
        later = snaps.get(timeout=1)
        assert later.cycle > first.cycle
        assert cyc.latest is not None and cyc.latest.cycle >= later.cycle
        done = threading.Event()
        assert cyc.submit(AgentCommand(request_id="n1", op="nmt", args={"command": "explode"},
                                       on_outcome=lambda o: done.set()))
        assert done.wait(5)
    finally:
        cyc.stop()
    assert gc.isenabled()
    assert cyc.state == "stopped"
    assert all(bus.model(i).state == State.SWITCH_ON_DISABLED for i in range(4))
    cyc.stop()  # idempotent


class SlowRecoverBus(SimBus):
    """recover() blocks like a slave that does not respond to AL state changes (SOEM's
    statecheck waits up to 2 s per state): here 0.3 s per call, outside the bus lock."""

    def __init__(self, *a, **kw) -> None:
        super().__init__(*a, **kw)
        self.recover_calls = 0
        self.recover_thread: set[str] = set()

    def recover(self, position: int) -> bool:
        self.recover_calls += 1
        self.recover_thread.add(threading.current_thread().name)
        time.sleep(0.3)
        return super().recover(position)


def test_blocking_recovery_does_not_stall_the_other_drives():
    # SM watchdog 250 ms: below one blocking recover call (300 ms), so a recover on the cycle
    # thread still trips it; above a host's scheduling stall (a CI run once lost 100 ms here)
    bus = SlowRecoverBus(3, sm_watchdog_s=0.25)
    cyc = Cycle(bus, AgentConfig(host="h1", sim_drives=3, groups={"g": ("h1/axis1", "h1/axis2")}))
    events: list = []
    lock = threading.Lock()

    def sink(snap) -> None:
        if snap.events:
            with lock:
                events.extend(snap.events)

    def seen(kind: str, axis: str) -> bool:
        with lock:
            return any(e.kind == kind and e.axis == axis for e in events)

    def wait(pred, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not pred():
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            time.sleep(0.005)

    cyc.snapshot_sink = sink
    cyc.start()
    try:
        outcomes: queue.SimpleQueue = queue.SimpleQueue()
        assert cyc.submit(DriveCommand(request_id="e1", op="enable", axes=("axis0", "axis1", "axis2"),
                                       on_outcome=outcomes.put))
        assert all(outcomes.get(timeout=10).outcome == "done" for _ in range(3))
        bus.unplug(2)
        wait(lambda: seen("lost", "axis2"), 5, "axis2 lost")
        wait(lambda: seen("reflex", "axis1"), 1, "group reflex on axis1")
        # several blocking recover calls while the slave is away: the cycle keeps exchanging
        wait(lambda: bus.recover_calls >= 3, 5, "3 recover calls")
        assert "cycle-h1" not in bus.recover_thread  # never on the cycle thread
        c0 = cyc.latest.cycle
        wait(lambda: cyc.latest.cycle > c0 + 100, 2, "100 more cycles")
        st = bus.read_al_status()
        assert st[0].state == ALState.OP and not st[0].error, st[0]  # no SM watchdog (0x001B)
        assert bus.model(0).state == State.OPERATION_ENABLED
        assert not seen("lost", "axis0") and not seen("reflex", "axis0")
        bus.plug(2)
        wait(lambda: seen("found", "axis2"), 5, "axis2 found")
        d2 = next(d for d in cyc.latest.drives if d.axis == "axis2")
        assert d2.goal == "disabled" and bus.model(2).state != State.OPERATION_ENABLED
        assert bus.model(0).state == State.OPERATION_ENABLED
        assert bus.read_al_status()[0].state == ALState.OP
    finally:
        cyc.stop()
    assert cyc.state == "stopped"
