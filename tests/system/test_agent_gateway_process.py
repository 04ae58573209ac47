"""The gateway in its own process (the default): what happens when either process dies.

- SIGKILL the gateway child: the agent runs the ordered shutdown of every drive (logged, since
  nobody can watch it over Zenoh any more), its liveliness token is gone, and it exits 1.
- SIGKILL the agent process alone: the gateway child reads EOF and exits too.
"""

from __future__ import annotations

import os
import re
import signal
import threading
import time
import uuid

import pytest
import zenoh

from bus_agent.sim.child import wait_for
from schemas import keys
from schemas import messages as m

pytestmark = pytest.mark.timeout(120)



def command(session, host, axis, op, timeout_s=8.0):
    req = m.CommandRequest(request_id=uuid.uuid4().hex, op=op, args={}, timeout_s=5.0)
    out = {}
    for r in session.get(keys.drive_cmd(host, axis, op), payload=m.encode(req), target=zenoh.QueryTarget.ALL,
                         consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
        if r.ok is not None:
            rep = m.decode(r.ok.payload, m.CommandReply)
            out[rep.axis] = rep.outcome
    return out


def statuses(session, host):
    return {st.axis: st for st in (m.decode(r.ok.payload, m.DriveStatus)
                                   for r in session.get(keys.drive_status(host, "*"), timeout=3.0) if r.ok is not None)}


def gateway_child(pid: int) -> int:
    """The agent's one child once it runs: ``python -m bus_agent.gateway.bridge`` (the start-up
    guard, a second child during start-up, leaves when start-up is over: waited for, 5 s)."""
    deadline = time.monotonic() + 5.0
    while True:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            children = [int(c) for c in f.read().split()]
        if len(children) == 1 or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert len(children) == 1, children
    with open(f"/proc/{children[0]}/cmdline", "rb") as f:
        assert b"bus_agent.gateway.bridge" in f.read()
    return children[0]


def gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")   # exited (maybe not yet reaped)
    except FileNotFoundError:
        return True


def test_gateway_killed_runs_the_ordered_shutdown_and_exits_1(start_agent, zenoh_session):
    a = start_agent("gwk", sim=2)
    s = zenoh_session(connect=[a.endpoint])
    wait_for(lambda: len(statuses(s, "gwk")) == 2, what="agent reachable")
    token_gone = threading.Event()
    sub = s.liveliness().declare_subscriber(
        keys.alive("gwk"), lambda smp: token_gone.set() if smp.kind == zenoh.SampleKind.DELETE else None)
    try:
        assert command(s, "gwk", "*", "enable") == {"axis0": "done", "axis1": "done"}
        child = gateway_child(a.pid)
        os.kill(child, signal.SIGKILL)
        code = a.popen.wait(30)
        a._reader.join(5)
        out = a.output(200)
        assert code == 1, out
        assert re.search(r"gateway process \d+ lost .*killed by SIGKILL.*ordered shutdown", out), out
        for axis in ("axis0", "axis1"):
            path = re.findall(rf"drive gwk/{axis} \(no gateway\): transition .* -> (\w+)", out)
            assert path == ["switched_on", "ready_to_switch_on", "switch_on_disabled"], (axis, out)
        assert "drives at stop: axis0=switch_on_disabled, axis1=switch_on_disabled" in out
        assert token_gone.wait(10)
    finally:
        sub.undeclare()


def test_agent_killed_alone_takes_the_gateway_process_with_it(start_agent):
    a = start_agent("gwa", sim=1)
    child = gateway_child(a.pid)
    a.popen.send_signal(signal.SIGKILL)     # the agent only, not its process group
    a.popen.wait(10)
    wait_for(lambda: gone(child), timeout_s=15.0, what="the gateway process to exit")
