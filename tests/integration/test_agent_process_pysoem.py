"""The whole agent (``bus-agent --ifname``: pysoem, cycle, gateway process) against ``ecat-sim``,
commanded over Zenoh from another process, observed on the drive side through the simulator.

Every drive op, malformed payloads (nothing changes), and SIGTERM's ordered shutdown as the
emulated drives and slaves see it.
"""

from __future__ import annotations

import itertools
import sys

import msgpack
import pytest
import zenoh

from bus_agent.sim.child import ChildProcess, free_port, wait_for
from bus_agent.gateway.zenoh_config import make_zenoh_config
from schemas import keys
from schemas.messages import SCHEMA_VERSION, CommandReply, CommandRequest, decode, encode

pytestmark = [pytest.mark.root, pytest.mark.timeout(120)]

HOST = "pz"
AXES = ("axis0", "axis1")
_ids = itertools.count()


@pytest.fixture
def bed(ecat_segment):
    ifname, control = ecat_segment(len(AXES))
    ep = f"tcp/127.0.0.1:{free_port()}"
    agent = ChildProcess("bus-agent", [sys.executable, "-m", "bus_agent.cli", "--ifname", ifname, "--host", HOST,
                                       "--listen", ep, "--log-level", "INFO"], ready_marker="bus-agent ready")
    session = None
    try:
        agent.expect_ready(40)
        session = zenoh.open(make_zenoh_config("peer", (), (ep,)))
        wait_for(lambda: list(session.liveliness().get(keys.alive(HOST), timeout=1.0)), 10, "the agent's token")
        yield agent, session, control
    finally:
        if session is not None:
            session.close()
        agent.stop(20)
        agent.kill()


def command(session, op: str, axis: str = "*", args: dict | None = None, payload: bytes | None = None,
            timeout_s: float = 5.0) -> tuple[list[CommandReply], list[str]]:
    """One query; returns (decoded replies, error texts)."""
    if payload is None:
        payload = encode(CommandRequest(request_id=f"t{next(_ids)}", op=op, args=args or {}, timeout_s=timeout_s))
    replies, errors = [], []
    for r in session.get(keys.drive_cmd(HOST, axis, op), payload=payload, target=zenoh.QueryTarget.ALL,
                         consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s + 2):
        if r.ok is not None:
            replies.append(decode(r.ok.payload.to_bytes(), CommandReply))
        else:
            errors.append(r.err.payload.to_string())
    return replies, errors


def drive_side(control) -> list[dict]:
    reply = control.request("status")
    assert reply["ok"], reply
    return reply["slaves"]


def states(control) -> list[str]:
    return [s["drive_state"] for s in drive_side(control)]


@pytest.mark.parametrize("op, args, reached", [
    ("shutdown", {}, "ready_to_switch_on"),
    ("switch_on", {}, "switched_on"),
    ("enable", {}, "operation_enabled"),
    ("quick_stop", {}, "quick_stop_active"),
    ("disable", {}, "switch_on_disabled"),
])
def test_goal_ops_reach_the_drives(bed, op, args, reached):
    _agent, session, control = bed
    if op == "quick_stop":  # from operation enabled (transition 11)
        replies, _ = command(session, "enable")
        assert {r.outcome for r in replies} == {"done"}
    replies, errors = command(session, op, args=args)
    assert not errors
    assert sorted(r.axis for r in replies) == list(AXES)  # one terminal reply per addressed drive
    assert {r.outcome for r in replies} == {"done"}, replies
    if op == "quick_stop":  # generic drive: 0x605A = 2, quick stop ramp then switch on disabled
        assert all(s in ("quick_stop_active", "switch_on_disabled") for s in states(control))
    else:
        assert states(control) == [reached] * len(AXES)


def test_halt_mode_and_fault_reset(bed):
    _agent, session, control = bed
    replies, _ = command(session, "enable", axis="axis0")
    assert [r.outcome for r in replies] == ["done"]
    replies, _ = command(session, "halt", axis="axis0", args={"on": True})
    assert [r.outcome for r in replies] == ["done"]
    wait_for(lambda: drive_side(control)[0]["controlword"] & 0x0100, 2, "halt bit 8 at the drive")
    replies, _ = command(session, "halt", axis="axis0", args={"on": False})
    replies, _ = command(session, "set_mode", axis="axis1", args={"mode": 9})
    assert [(r.axis, r.outcome) for r in replies] == [("axis1", "done")]
    wait_for(lambda: drive_side(control)[1]["mode_display"] == 9, 2, "0x6061 echo 9")
    assert control.request("fault", slave=1, error_code=0x2310)["ok"]
    wait_for(lambda: states(control)[1] == "fault", 3, "fault on axis1")
    assert states(control)[0] == "operation_enabled"  # not grouped: the other drive is unaffected
    replies, _ = command(session, "fault_reset", axis="axis1")
    assert [r.outcome for r in replies] == ["done"]
    assert states(control)[1] == "switch_on_disabled" and drive_side(control)[1]["error_code"] == 0


def raw(**fields) -> bytes:
    """A command request as msgpack, bypassing the encoder's validation (bad input on purpose)."""
    body = {"v": SCHEMA_VERSION, "type": "command_request", "request_id": "bad", "op": "enable", "args": {},
            "timeout_s": 5.0, **fields}
    return msgpack.packb(body)


@pytest.mark.parametrize("op, payload, match", [
    ("enable", b"\x00\xffnot msgpack", "msgpack"),
    ("enable", encode(CommandRequest(request_id="m1", op="enable"))[:-3], "msgpack"),
    ("set_mode", raw(op="set_mode", args={"mode": 99}), "mode"),
    ("enable", raw(v=SCHEMA_VERSION + 1), "version"),
    ("enable", raw(timeout_s="soon"), "timeout_s"),
    ("enable", raw(op="disable"), "op"),
    ("frobnicate", raw(op="enable"), "frobnicate"),
])
def test_malformed_commands_get_an_error_and_change_nothing(bed, op, payload, match):
    _agent, session, control = bed
    before = [(s["drive_state"], s["controlword"]) for s in drive_side(control)]
    replies, errors = command(session, op, payload=payload)
    assert not replies and errors and all(match in e for e in errors), (replies, errors)
    assert [(s["drive_state"], s["controlword"]) for s in drive_side(control)] == before


def test_sigterm_runs_the_ordered_shutdown_seen_by_the_drives(bed):
    agent, session, control = bed
    replies, _ = command(session, "enable")
    assert {r.outcome for r in replies} == {"done"}
    assert agent.stop(20) == 0, agent.output()
    assert not agent.stop_timed_out
    side = drive_side(control)
    # The seed's order ended in switch on disabled, not a watchdog fault; then the slaves went to INIT.
    assert [s["drive_state"] for s in side] == ["switch_on_disabled"] * len(AXES), side
    assert all(s["error_code"] == 0 for s in side), side
    assert all(s["al_state"] == "init" for s in side), side
    log = "\n".join(agent.lines)
    assert "ordered shutdown" in log
