"""One agent per host name in every session mode (issue 23 #5), with real ``bus-agent`` processes
and routers.

``bus-agent --host h1 --connect EP`` (no ``--listen``: the README's deployment shape) is a zenoh
peer that listens nowhere, and a router does not forward between two peers: a second such agent
saw neither the first one's liveliness token nor its status and ran under the same name. The
claim now goes through a client session the router routes for. While two agents share a name,
each refuses every command that raises power, clears a fault, changes the mode or moves, naming
the conflict, for as long as the other keeps publishing.
"""

from __future__ import annotations

import sys
import time
from typing import Iterator

import pytest
import zenoh

from bus_agent.sim.child import ChildProcess, free_port
from schemas import keys
from schemas import messages as m
from supervisor.session import zenoh_config
from supervisor.testbed import Proc, start_router

pytestmark = pytest.mark.timeout(240)


def agent(router: str, host: str, *extra: str) -> Proc:
    return ChildProcess(f"bus-agent {host}", [sys.executable, "-m", "bus_agent.cli", "--sim", "1", "--host", host,
                                              "--connect", router, *extra], ready_marker="bus-agent ready")


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    r, ep = start_router()
    try:
        yield ep
    finally:
        r.stop()


@pytest.mark.parametrize("mode", [(), ("--mode", "client"), ("--listen", "tcp/127.0.0.1:{port}")],
                         ids=["peer-connect-only", "client", "peer-listening"])
def test_second_agent_under_a_taken_name_exits_3_in_every_session_mode(router: str, mode: tuple[str, ...]) -> None:
    first = agent(router, "k1")  # the README's shape: peer, --connect only
    second = None
    try:
        first.expect_ready(60)
        second = agent(router, "k1", *(a.format(port=free_port()) for a in mode))
        try:
            code = second.popen.wait(30)
        except Exception:
            code = None
        assert code == 3, f"second k1 ({' '.join(mode) or 'peer, --connect only'}) exit {code}:\n{second.output()}"
        assert "host name 'k1' is taken" in second.output()
    finally:
        if second is not None:
            second.stop()  # an agent that wrongly started must not outlive the test
        first.stop()


def _statuses(s: zenoh.Session, host: str) -> list[m.AgentStatus]:
    out = []
    for reply in s.get(keys.agent_status(host), target=zenoh.QueryTarget.ALL,
                       consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0):
        if reply.ok is not None:
            out.append(m.decode(reply.ok.payload.to_bytes(), m.AgentStatus))
    return out


def _command(s: zenoh.Session, host: str, op: str, args: dict) -> list[m.CommandReply]:
    """A plain client's command (the README's contract): every agent's reply."""
    req = m.CommandRequest(f"claim-test-{op}-{time.monotonic_ns()}", op, args, 3.0, "claim-test")
    out = []
    for reply in s.get(keys.drive_cmd(host, "axis0", op), payload=m.encode(req), target=zenoh.QueryTarget.ALL,
                       consolidation=zenoh.ConsolidationMode.NONE, timeout=6.0):
        if reply.ok is not None:
            out.append(m.decode(reply.ok.payload.to_bytes(), m.CommandReply))
    return out


def test_agents_in_conflict_refuse_commands_while_it_lasts(router: str) -> None:
    """Two connect-only agents that meet after starting (the second one's router comes up later
    and links to the first's): both see the conflict through their claim sessions and refuse
    enable and motion, naming it, as long as both run; then it ends."""
    far = f"tcp/127.0.0.1:{free_port()}"
    first = agent(router, "k2")
    late = agent(far, "k2")  # its router is not there yet: nothing to see at its start
    bridge: Proc | None = None
    try:
        first.expect_ready(60)
        late.expect_ready(60)
        bridge = ChildProcess("bridge-router", [sys.executable, "-m", "bus_agent.router", "--listen", far,
                                                "--connect", router], ready_marker="drives-router ready")
        bridge.expect_ready(20)
        with zenoh.open(zenoh_config("client", [router])) as s:
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                sts = _statuses(s, "k2")
                if len(sts) == 2 and all(st.conflict for st in sts):
                    break
                time.sleep(0.3)
            assert len(sts) == 2 and all("also used by agent instance" in st.conflict for st in sts), sts
            for _ in range(2):  # and still, after longer than the conflict's hold (3 status periods)
                for op, args in (("enable", {}), ("move", {"by": 100.0}), ("jog", {"velocity": 10.0, "for_s": 0.1})):
                    replies = _command(s, "k2", op, args)
                    assert len(replies) == 2, (op, replies)  # both agents answer: both refuse
                    assert all(r.outcome == "rejected" and "host name k2 is also used by" in r.reason
                               for r in replies), (op, replies)
                time.sleep(3.5)
            late.stop()
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and any(st.conflict for st in _statuses(s, "k2")):
                time.sleep(0.3)
            assert [st.conflict for st in _statuses(s, "k2")] == [""]
            assert [r.outcome for r in _command(s, "k2", "enable", {})] == ["done"]
            assert [r.outcome for r in _command(s, "k2", "disable", {})] == ["done"]
    finally:
        if bridge is not None:
            bridge.stop()
        late.stop()
        first.stop()
