"""SIGTERM during the agent's start-up ends it within 2 s, in order, in the step Python waits in
(the gateway process getting ready: a wait the agent checks from its own thread), with the
simulated backend (no root). The pysoem steps and the guard: tests/integration/test_startup_deadlines.py."""

from __future__ import annotations

import signal
import sys
import time

from bus_agent.sim.child import ChildProcess, free_port, wait_for


def test_sigterm_while_the_gateway_process_starts_ends_start_up_in_order():
    agent = ChildProcess("bus-agent", [sys.executable, "-m", "bus_agent.cli", "--sim", "2", "--host", "early",
                                       "--listen", f"tcp/127.0.0.1:{free_port()}", "--log-level", "DEBUG"],
                         ready_marker="bus-agent ready")
    try:
        wait_for(lambda: any("start-up step 'gateway process" in line for line in agent.lines), 30,
                 "the gateway step")
        agent.popen.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        agent.popen.wait(10)
        assert time.monotonic() - t0 < 2.0, agent.output()
        agent._reader.join(5)
        assert agent.popen.returncode == 0, agent.output()
        out = agent.output(400)
        assert "bus-agent: agent early: stop signal during start-up step 'gateway process" in out, out
        assert "bus-agent ready" not in out and "ended by its start-up guard" not in out, out
    finally:
        agent.kill()
