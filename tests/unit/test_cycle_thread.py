"""The cycle in its own thread (real monotonic clock) over SimBus: commands from another thread,
snapshots through the sink, ordered stop. Waits are on events with deadlines."""

from __future__ import annotations

import gc
import queue
import threading

from bus_agent.bus.sim_bus import SimBus
from bus_agent.cia402.states import State
from bus_agent.config import AgentConfig
from bus_agent.cycle import Cycle
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
