"""The bus agent as a separate process (simulated drives) driven over Zenoh on loopback:
every op, fan-out, malformed payloads, request ids, status and events, liveliness, leases,
ordered shutdown on SIGTERM, and a group reflex across two agent processes."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading
import uuid
from pathlib import Path

import msgpack
import pytest
import zenoh

from bus_agent.sim.child import wait_for
from bus_agent.sim.control import sim_inject
from schemas import keys
from schemas import messages as m

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[2]

HOST = "sa1"
N = 3
AXES = tuple(f"axis{i}" for i in range(N))
OPS_TIMEOUT_S = 8.0



def send(session, key, payload, timeout_s=OPS_TIMEOUT_S):
    """(ok replies as (key, CommandReply), error texts) of one command query."""
    oks, errs = [], []
    for r in session.get(key, payload=payload, target=zenoh.QueryTarget.ALL,
                         consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
        if r.ok is not None:
            oks.append((str(r.ok.key_expr), m.decode(r.ok.payload, m.CommandReply)))
        else:
            errs.append(r.err.payload.to_bytes().decode("utf-8", "replace"))
    return oks, errs


def command(session, axis, op, args=None, rid=None, supervisor="", host=HOST, timeout_s=5.0):
    req = m.CommandRequest(request_id=rid or uuid.uuid4().hex, op=op, args=args or {}, timeout_s=timeout_s,
                           supervisor=supervisor)
    return send(session, keys.drive_cmd(host, axis, op), m.encode(req))


def outcomes(oks):
    return {r.axis: r.outcome for _, r in oks}


def statuses(session, host=HOST, axis="*"):
    out = {}
    for r in session.get(keys.drive_status(host, axis), timeout=3.0):
        if r.ok is not None:
            st = m.decode(r.ok.payload, m.DriveStatus)
            out[st.axis] = st
    return out


class Recorder:
    """Collects decoded samples of a key expression (status or events). Returns once the
    subscription is live: a status sample of ``host`` came through a subscriber declared after
    it (declarations travel in order; status has a heartbeat)."""

    def __init__(self, session, key, host=HOST, live_timeout_s=10.0):
        self.items: list = []
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)
        seen = threading.Event()
        probe = session.declare_subscriber(keys.drive_status(host, "*"), lambda s: seen.set())
        try:
            assert seen.wait(live_timeout_s), f"no status from {host}: subscription not live"
        finally:
            probe.undeclare()

    def _on(self, sample):
        try:
            msg = m.decode(sample.payload)
        except m.SchemaError:
            return
        with self.lock:
            self.items.append(msg)

    def snapshot(self):
        with self.lock:
            return list(self.items)

    def close(self):
        self.sub.undeclare()


@pytest.fixture(scope="module")
def agent(module_start_agent):
    return module_start_agent(HOST, sim=N)


@pytest.fixture(scope="module")
def session(agent, module_zenoh_session):
    s = module_zenoh_session(connect=[agent.endpoint])
    wait_for(lambda: len(statuses(s)) == N, what="agent reachable")
    return s


@pytest.fixture
def clean(session):
    """Every test starts from fault-free, disabled, unleased drives."""
    st = statuses(session)
    faulted = [a for a, s in st.items() if s.state in ("fault", "fault_reaction_active")]
    for a in faulted:
        command(session, a, "fault_reset")
    for a, s in st.items():
        if s.lease_holder:
            command(session, a, "release", args={"holder": s.lease_holder}, supervisor=s.lease_holder)
    oks, errs = command(session, "*", "disable")
    assert set(outcomes(oks).values()) == {"done"}, (oks, errs)
    return session


def test_readiness_line_names_host_drives_and_endpoint(agent):
    line = next(ln for ln in agent.lines if ln.startswith("bus-agent ready"))
    assert f"host={HOST}" in line and f"drives={','.join(AXES)}" in line and agent.endpoint in line


@pytest.mark.parametrize("op, args, state", [
    ("switch_on", None, "switched_on"),
    ("shutdown", None, "ready_to_switch_on"),
    ("enable", None, "operation_enabled"),
])
def test_goal_ops_reach_their_state(clean, op, args, state):
    oks, errs = command(clean, "axis1", op, args)
    assert errs == [] and len(oks) == 1
    key, reply = oks[0]
    assert key == keys.drive_cmd(HOST, "axis1", op)
    assert (reply.outcome, reply.state, reply.axis, reply.host, reply.op) == ("done", state, "axis1", HOST, op)
    assert statuses(clean, axis="axis1")["axis1"].state == state


def test_disable_from_enabled_follows_the_ordered_sequence(clean):
    events = Recorder(clean, keys.drive_event(HOST, "axis0"))
    try:
        assert outcomes(command(clean, "axis0", "enable")[0]) == {"axis0": "done"}
        oks, _ = command(clean, "axis0", "disable")
        assert [(r.outcome, r.state) for _, r in oks] == [("done", "switch_on_disabled")]
        wait_for(lambda: any(e.kind == "outcome" and "disable" in e.detail for e in events.snapshot()),
                 what="disable outcome event")
        path = [e.to_state for e in events.snapshot() if e.kind == "transition"]
        i = path.index("operation_enabled")
        assert path[i + 1:] == ["switched_on", "ready_to_switch_on", "switch_on_disabled"]  # 5, 6, 7
        seqs = [e.seq for e in events.snapshot()]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    finally:
        events.close()


def test_quick_stop_and_halt(clean):
    assert outcomes(command(clean, "axis2", "enable")[0]) == {"axis2": "done"}
    oks, _ = command(clean, "axis2", "halt", {"on": True})
    assert outcomes(oks) == {"axis2": "done"}
    wait_for(lambda: statuses(clean, axis="axis2")["axis2"].halt, what="halt bit in status")
    assert statuses(clean, axis="axis2")["axis2"].state == "operation_enabled"   # halt is not a stop
    assert outcomes(command(clean, "axis2", "halt", {"on": False})[0]) == {"axis2": "done"}
    oks, _ = command(clean, "axis2", "quick_stop")
    assert outcomes(oks) == {"axis2": "done"}
    assert oks[0][1].state in ("quick_stop_active", "switch_on_disabled")
    assert statuses(clean, axis="axis2")["axis2"].goal == "quick_stop"


def test_set_mode_waits_for_the_echo(clean):
    oks, _ = command(clean, "axis0", "set_mode", {"mode": 9})
    assert outcomes(oks) == {"axis0": "done"}
    st = statuses(clean, axis="axis0")["axis0"]
    assert (st.mode, st.mode_display) == (9, 9)
    assert outcomes(command(clean, "axis0", "set_mode", {"mode": 8})[0]) == {"axis0": "done"}


def test_fault_reset_after_an_injected_fault(clean):
    assert outcomes(command(clean, "axis1", "enable")[0]) == {"axis1": "done"}
    sim_inject(clean, HOST, 1, "fault", error_code=0x7500)
    wait_for(lambda: statuses(clean, axis="axis1")["axis1"].state == "fault", what="fault state")
    assert statuses(clean, axis="axis1")["axis1"].error_code == 0x7500
    oks, _ = command(clean, "axis1", "enable")   # a fault is never reset by enable
    (reply,) = [r for _, r in oks]
    # failed at once, naming the fault; a hang (timeout) would not pass
    assert (reply.outcome, reply.state, reply.error_code) == ("failed", "fault", 0x7500), reply
    assert statuses(clean, axis="axis1")["axis1"].state == "fault"
    oks, _ = command(clean, "axis1", "fault_reset")
    assert [(r.outcome, r.state) for _, r in oks] == [("done", "switch_on_disabled")]


def test_fan_out_one_reply_per_drive_same_cycle(clean):
    recs = Recorder(clean, keys.drive_status(HOST, "*"))
    try:
        oks, errs = command(clean, "*", "enable", rid="fan-" + uuid.uuid4().hex)
        assert errs == []
        assert sorted(k for k, _ in oks) == [keys.drive_cmd(HOST, a, "enable") for a in AXES]
        assert outcomes(oks) == {a: "done" for a in AXES}
        # The goal changed for every drive in one cycle: the first status with goal 'enabled'
        # of each drive carries the same cycle number.
        first = {}
        for st in recs.snapshot():
            if st.goal == "enabled" and st.axis not in first:
                first[st.axis] = st.cycle
        assert set(first) == set(AXES) and len(set(first.values())) == 1, first
    finally:
        recs.close()


def _unchanged_view(session):
    return {a: (s.state, s.goal, s.mode, s.halt, s.lease_holder) for a, s in statuses(session).items()}


@pytest.mark.parametrize("payload, words", [
    (b"\x93\xc1random\xff bytes", "msgpack"),
    (msgpack.packb({"v": 99, "type": "command_request", "request_id": "a", "op": "enable"}), "schema version 99"),
    (msgpack.packb({"v": 1, "type": "command_request", "request_id": "a", "op": "launch"}), "launch"),
    (msgpack.packb({"v": 1, "type": "command_request", "request_id": "a", "op": "set_mode",
                    "args": {"mode": 42}}), "mode"),
    (msgpack.packb({"v": 1, "type": "command_request", "op": "enable"}), "request_id"),
    (msgpack.packb({"v": 1, "type": "command_request", "request_id": "a", "op": "halt"}), "on"),
    (msgpack.packb({"v": 1, "type": "command_request", "request_id": "a", "op": "disable"}), "does not match"),
    (None, "no payload"),
])
def test_malformed_payloads_get_reply_err_and_change_nothing(clean, payload, words):
    before = _unchanged_view(clean)
    op = "set_mode" if payload and b"set_mode" in payload else "halt" if payload and b"halt" in payload else "enable"
    oks, errs = send(clean, keys.drive_cmd(HOST, "*", op), payload, timeout_s=3.0)
    assert oks == [] and len(errs) == 1, (oks, errs)
    assert words in errs[0] and HOST in errs[0]
    assert _unchanged_view(clean) == before


def test_unknown_op_key_gets_reply_err(clean):
    req = msgpack.packb({"v": 1, "type": "command_request", "request_id": "u1", "op": "jump"})
    oks, errs = send(clean, keys.drive_cmd(HOST, "axis0", "jump"), req, timeout_s=3.0)
    assert oks == [] and "jump" in errs[0]


def test_repeated_request_id_returns_the_first_outcome(clean):
    events = Recorder(clean, keys.drive_event(HOST, "axis2"))
    try:
        rid = "rep-" + uuid.uuid4().hex
        first, _ = command(clean, "axis2", "enable", rid=rid)
        command(clean, "axis2", "disable")   # the state moves on
        again, _ = command(clean, "axis2", "enable", rid=rid)
        assert [r for _, r in again] == [r for _, r in first]          # the same reply, to the field
        assert statuses(clean, axis="axis2")["axis2"].state == "switch_on_disabled"   # no second action
        marker = "mark-" + uuid.uuid4().hex   # events of one drive arrive in order: this one comes last
        command(clean, "axis2", "disable", rid=marker)
        wait_for(lambda: any(e.request_id == marker for e in events.snapshot()), what="marker event")
        assert len([e for e in events.snapshot() if e.request_id == rid and e.kind == "outcome"]) == 1
        _, errs = command(clean, "axis2", "disable", rid=rid)
        assert "already used" in errs[0]
    finally:
        events.close()


def test_status_on_change_with_seq_and_get(clean):
    recs = Recorder(clean, keys.drive_status(HOST, "axis0"))
    try:
        assert outcomes(command(clean, "axis0", "enable")[0]) == {"axis0": "done"}
        wait_for(lambda: any(s.state == "operation_enabled" for s in recs.snapshot()), what="status published")
        seen = recs.snapshot()
        states = [s.state for s in seen]
        # every state on the way was published (on change, not only by the heartbeat)
        for st in ("ready_to_switch_on", "switched_on", "operation_enabled"):
            assert st in states, states
        seqs = [s.seq for s in seen]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        got = statuses(clean, axis="axis0")["axis0"]
        assert got.state == "operation_enabled" and got.seq >= seqs[-1] and got.host == HOST
        agent_st = [m.decode(r.ok.payload, m.AgentStatus) for r in clean.get(keys.agent_status(HOST), timeout=3.0)]
        assert agent_st[0].axes == list(AXES) and agent_st[0].state == "running" and agent_st[0].backend == "sim"
    finally:
        recs.close()


def test_liveliness_token(session):
    tokens = [str(r.ok.key_expr) for r in session.liveliness().get(keys.ALL_ALIVE, timeout=3.0) if r.ok]
    assert keys.alive(HOST) in tokens


def test_lease_busy_takeover_release(clean):
    oks, _ = command(clean, "*", "lease", {"holder": "supA", "ttl_s": 30.0}, supervisor="supA")
    assert outcomes(oks) == {a: "done" for a in AXES}
    assert {a: s.lease_holder for a, s in statuses(clean).items()} == {a: "supA" for a in AXES}
    oks, _ = command(clean, "axis0", "enable", supervisor="supB")
    assert oks[0][1].outcome == "busy" and "supA" in oks[0][1].reason and oks[0][1].lease_holder == "supA"
    assert statuses(clean, axis="axis0")["axis0"].state == "switch_on_disabled"
    oks, _ = command(clean, "axis0", "enable")                      # anonymous: busy too
    assert oks[0][1].outcome == "busy"
    oks, _ = command(clean, "axis0", "enable", supervisor="supA")   # the holder may
    assert outcomes(oks) == {"axis0": "done"}
    oks, _ = command(clean, "axis1", "lease", {"holder": "supB"}, supervisor="supB")
    assert outcomes(oks) == {"axis1": "busy"}
    events = Recorder(clean, keys.drive_event(HOST, "axis1"))
    try:
        oks, _ = command(clean, "axis1", "lease", {"holder": "supB", "takeover": True}, supervisor="supB")
        assert [(r.outcome, r.lease_holder) for _, r in oks] == [("done", "supB")]
        wait_for(lambda: any(e.kind == "lease" and "taken over by supB" in e.detail for e in events.snapshot()),
                 what="lease event")
    finally:
        events.close()
    oks, _ = command(clean, "axis1", "release", {"holder": "supA"}, supervisor="supA")
    assert outcomes(oks) == {"axis1": "busy"}                      # not supA's any more
    oks, _ = command(clean, "*", "release", {"holder": "supA"}, supervisor="supA")
    assert outcomes(oks) == {"axis0": "done", "axis1": "busy", "axis2": "done"}
    assert outcomes(command(clean, "axis1", "release", {"holder": "supB"}, supervisor="supB")[0]) == {"axis1": "done"}
    assert {a: s.lease_holder for a, s in statuses(clean).items()} == {a: "" for a in AXES}


HOLDER_SCRIPT = textwrap.dedent("""
    import sys, time, zenoh
    from bus_agent.gateway.zenoh_config import make_zenoh_config
    from schemas import keys, messages as m
    ep, host, axis = sys.argv[1:4]
    s = zenoh.open(make_zenoh_config("peer", [], [ep]))
    tok = s.liveliness().declare_token(keys.supervisor_alive("supK"))
    time.sleep(0.5)
    req = m.CommandRequest(request_id="k1", op="lease", args={"holder": "supK", "ttl_s": 600.0}, supervisor="supK")
    for r in s.get(keys.drive_cmd(host, axis, "lease"), payload=m.encode(req), timeout=5.0):
        print("lease", m.decode(r.ok.payload).outcome if r.ok else r.err.payload.to_string(), flush=True)
    time.sleep(600)
""")


def test_lease_holder_killed_runs_the_reaction(clean, agent):
    assert outcomes(command(clean, "axis2", "enable")[0]) == {"axis2": "done"}
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    holder = subprocess.Popen([sys.executable, "-c", HOLDER_SCRIPT, agent.endpoint, HOST, "axis2"],
                              stdout=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    events = Recorder(clean, keys.drive_event(HOST, "axis2"))
    try:
        assert holder.stdout.readline().strip() == "lease done"
        assert statuses(clean, axis="axis2")["axis2"].lease_holder == "supK"
        holder.kill()   # a crash: its liveliness token disappears
        holder.wait(10)
        wait_for(lambda: (lambda s: s.state == "switch_on_disabled" and s.lease_holder == "")(
            statuses(clean, axis="axis2")["axis2"]), what="reaction to the lost holder")
        evs = events.snapshot()
        assert any(e.kind == "lease" and "supK" in e.detail and "liveliness" in e.detail for e in evs), evs
        assert any(e.kind == "outcome" and "quick_stop" in e.detail for e in evs), evs
    finally:
        events.close()
        if holder.poll() is None:
            holder.kill()
            holder.wait(10)


def test_lease_expiry_runs_the_reaction(clean):
    assert outcomes(command(clean, "axis0", "enable")[0]) == {"axis0": "done"}
    oks, _ = command(clean, "axis0", "lease", {"holder": "supE", "ttl_s": 0.5}, supervisor="supE")
    assert outcomes(oks) == {"axis0": "done"}
    wait_for(lambda: (lambda s: s.state == "switch_on_disabled" and s.lease_holder == "")(
        statuses(clean, axis="axis0")["axis0"]), what="reaction to the expired lease")


def test_sigterm_runs_the_ordered_shutdown(start_agent, zenoh_session):
    a = start_agent("sterm", sim=2)
    s = zenoh_session(connect=[a.endpoint])
    wait_for(lambda: len(statuses(s, host="sterm")) == 2, what="agent reachable")
    events = Recorder(s, keys.drive_event("sterm", "*"), host="sterm")
    agent_st = Recorder(s, keys.agent_status("sterm"), host="sterm")
    gone = threading.Event()
    alive_sub = s.liveliness().declare_subscriber(
        keys.alive("sterm"), lambda smp: gone.set() if smp.kind == zenoh.SampleKind.DELETE else None)
    try:
        oks, _ = command(s, "*", "enable", host="sterm")
        assert outcomes(oks) == {"axis0": "done", "axis1": "done"}
        assert a.terminate() == 0, a.output()
        for axis in ("axis0", "axis1"):
            path = [e.to_state for e in events.snapshot() if e.axis == axis and e.kind == "transition"]
            i = path.index("operation_enabled")
            assert path[i + 1:] == ["switched_on", "ready_to_switch_on", "switch_on_disabled"], path
        assert [x.state for x in agent_st.snapshot()][-1] == "stopped"
        assert gone.wait(5)
        assert any("bus-agent stopped" in ln for ln in a.lines)
    finally:
        alive_sub.undeclare()
        events.close()
        agent_st.close()


def enable_all(session, host, proc, attempts=3):
    """Enable every drive of ``host``. On a starved machine a simulated slave may trip its
    100 ms SM watchdog and be lost for a moment (the agent brings it back): retry then."""
    for _ in range(attempts):
        oks, errs = command(session, "*", "enable", host=host)
        if set(outcomes(oks).values()) == {"done"}:
            return
        assert all(r.outcome == "done" or "lost" in r.reason for _, r in oks), (oks, errs, proc.output())
        wait_for(lambda: not any(st.lost for st in statuses(session, host=host).values()), what=f"{host} back")
    raise AssertionError(f"{host}: could not enable: {oks} {errs}\n{proc.output()}")


def test_group_reflex_across_two_agent_processes(start_agent, zenoh_session, tmp_path):
    cfg = tmp_path / "group.toml"
    cfg.write_text(textwrap.dedent("""
        host = "placeholder"
        sim_drives = 2
        [groups]
        line = ["ga/axis0", "gb/axis0"]
    """))
    a = start_agent("ga", sim=None, extra_args=["--config", str(cfg), "--sim", "2"])
    b = start_agent("gb", sim=None, connect=[a.endpoint], extra_args=["--config", str(cfg), "--sim", "2"])
    s = zenoh_session(connect=[a.endpoint, b.endpoint])
    wait_for(lambda: len(statuses(s, host="ga")) == 2 and len(statuses(s, host="gb")) == 2, what="both agents")
    for h, proc in (("ga", a), ("gb", b)):
        enable_all(s, h, proc)
    # gb watches ga's member: its gateway logs the first status it receives from it.
    wait_for(lambda: any("member ga/axis0 seen" in ln for ln in b.lines), what="gb sees ga/axis0")
    sim_inject(s, "ga", 0, "fault", error_code=0x7300)
    wait_for(lambda: statuses(s, host="gb", axis="axis0")["axis0"].goal == "quick_stop", timeout_s=5.0,
             what="reflex on the other host")
    assert statuses(s, host="gb", axis="axis1")["axis1"].state == "operation_enabled"   # not in the group
    # agent loss is a trigger too
    assert outcomes(command(s, "axis0", "fault_reset", host="ga")[0]) == {"axis0": "done"}
    assert outcomes(command(s, "axis0", "enable", host="gb")[0]) == {"axis0": "done"}
    a.kill()
    wait_for(lambda: statuses(s, host="gb", axis="axis0")["axis0"].goal == "quick_stop", timeout_s=10.0,
             what="reflex on agent loss")


def test_agent_nmt_command_one_reply_on_the_agent_key(clean):
    events = Recorder(clean, keys.drive_event(HOST, "axis0"))
    try:
        def nmt(command_, rid=None):
            req = m.CommandRequest(request_id=rid or uuid.uuid4().hex, op="nmt",
                                   args={"command": command_, "axis": "axis1"}, timeout_s=5.0)
            return send(clean, keys.agent_cmd(HOST, "nmt"), m.encode(req))

        oks, errs = nmt("stop", rid="nmt-stop")
        assert errs == [] and [(k, r.axis, r.outcome) for k, r in oks] == [(keys.agent_cmd(HOST, "nmt"), "", "done")]
        wait_for(lambda: statuses(clean, axis="axis1")["axis1"].al_state == "safeop", what="axis1 in SAFE-OP")
        assert statuses(clean, axis="axis0")["axis0"].al_state == "op"       # only the addressed slave
        # the agent-wide NMT event reaches every drive's event key
        wait_for(lambda: any(e.request_id == "nmt-stop" for e in events.snapshot()), what="nmt event on axis0")
        oks, _ = nmt("start")
        assert [r.outcome for _, r in oks] == ["done"]
        wait_for(lambda: statuses(clean, axis="axis1")["axis1"].al_state == "op", what="axis1 back in OP")
        assert statuses(clean, axis="axis1")["axis1"].goal == "disabled"      # never re-enabled by itself
    finally:
        events.close()
