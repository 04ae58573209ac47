"""The gateway against a tiny fake cycle, over two in-process zenoh sessions on loopback."""

from __future__ import annotations

import contextlib
import functools
import socket
import threading
import time
import uuid
from dataclasses import replace

import msgpack
import pytest
import zenoh

from bus_agent.sim import child
from bus_agent import runtime as rt
from bus_agent.gateway.gateway import Gateway, GatewaySettings
from bus_agent.gateway.zenoh_config import make_zenoh_config
from schemas import keys
from schemas import messages as m

HOST = "gw1"
AXES = ("x1", "x2", "x3")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


wait_for = functools.partial(child.wait_for, timeout_s=5.0, poll_s=0.01)


class FakeCycle:
    """Runs commands instantly: goal ops set the state; every addressed axis answers 'done'."""

    STATE_OF_OP = {"enable": "operation_enabled", "switch_on": "switched_on", "shutdown": "ready_to_switch_on",
                   "disable": "switch_on_disabled", "quick_stop": "quick_stop_active"}

    def __init__(self, axes=AXES):
        self.snapshot_sink = None
        self.latest = None
        self.state = "running"
        self.accept = True
        self.hold = False           # keep outcomes back (pending commands)
        self.held: list = []
        self.submitted: list = []
        self.triggers: list = []
        self.cycle = 0
        self.drives = {a: rt.DriveSnapshot(a, i, "switch_on_disabled", 0x0250, 0, "disabled", False, 8, 8, 0, 0, 0,
                                           0, "", "op", False) for i, a in enumerate(axes)}
        self.lock = threading.Lock()

    def submit(self, cmd):
        if not self.accept:
            return False
        with self.lock:
            self.submitted.append(cmd)
            if self.hold:
                self.held.append(cmd)
                return True
        self.finish(cmd)
        return True

    def finish(self, cmd, outcome="done"):
        axes = getattr(cmd, "axes", ("",))
        for a in axes:
            if a and cmd.op in self.STATE_OF_OP:
                self.set(a, state=self.STATE_OF_OP[cmd.op])
            cmd.on_outcome(rt.Outcome(a, outcome, state=self.drives[a].state if a else "unknown"))

    def release_held(self):
        with self.lock:
            held, self.held = self.held, []
        for cmd in held:
            self.finish(cmd)

    def set(self, axis, **fields):
        with self.lock:
            self.drives[axis] = replace(self.drives[axis], **fields)

    def tick(self, events=()):
        with self.lock:
            self.cycle += 1
            snap = rt.CycleSnapshot(self.cycle, time.time_ns(), tuple(self.drives.values()), tuple(events),
                                    rt.CycleStats(cycles=self.cycle))
        self.latest = snap
        if self.snapshot_sink:
            self.snapshot_sink(snap)
        return snap

    def trigger_group(self, group, reason):
        self.triggers.append((group, reason))


class Ticker:
    def __init__(self, cycle, period_s=0.002):
        self.cycle, self.period_s = cycle, period_s
        self.stop = threading.Event()
        self.t = threading.Thread(target=self.run, daemon=True)

    def run(self):
        while not self.stop.wait(self.period_s):
            self.cycle.tick()


@pytest.fixture
def net():
    port = free_port()
    agent_s = zenoh.open(make_zenoh_config("peer", [f"tcp/127.0.0.1:{port}"], []))
    client_s = zenoh.open(make_zenoh_config("peer", [], [f"tcp/127.0.0.1:{port}"]))
    yield agent_s, client_s
    client_s.close()
    agent_s.close()


def make_gateway(agent_s, cycle, **kw):
    settings = GatewaySettings(host=HOST, axes=tuple(cycle.drives), heartbeat_s=kw.pop("heartbeat_s", 0.3),
                               agent_period_s=0.3, **kw)
    gw = Gateway(agent_s, cycle, settings)
    gw.start()
    return gw


@pytest.fixture
def gw(net):
    agent_s, client_s = net
    cycle = FakeCycle()
    ticker = Ticker(cycle)
    gateway = make_gateway(agent_s, cycle, lease_reaction={a: "quick_stop_then_disable" for a in AXES})
    ticker.t.start()
    wait_for(lambda: list(client_s.get(keys.agent_status(HOST), timeout=1.0)), what="agent reachable")
    yield gateway, cycle, client_s
    ticker.stop.set()
    ticker.t.join()
    gateway.close()


def command(session, axis, op, args=None, rid=None, supervisor="", timeout_s=3.0, host=HOST):
    body = m.CommandRequest(request_id=rid or uuid.uuid4().hex, op=op, args=args or {}, supervisor=supervisor)
    oks, errs = [], []
    for r in session.get(keys.drive_cmd(host, axis, op), payload=m.encode(body), target=zenoh.QueryTarget.ALL,
                         consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
        if r.ok is not None:
            oks.append((str(r.ok.key_expr), m.decode(r.ok.payload, m.CommandReply)))
        else:
            errs.append(r.err.payload.to_string())
    return oks, errs


def test_fan_out_one_command_one_reply_per_axis(gw):
    gateway, cycle, client = gw
    oks, errs = command(client, "*", "enable", rid="fan1")
    assert errs == []
    assert sorted(k for k, _ in oks) == [keys.drive_cmd(HOST, a, "enable") for a in AXES]
    assert {r.axis: (r.outcome, r.state) for _, r in oks} == {a: ("done", "operation_enabled") for a in AXES}
    drive_cmds = [c for c in cycle.submitted if c.request_id == "fan1"]
    assert len(drive_cmds) == 1 and drive_cmds[0].axes == AXES   # ONE DriveCommand: same cycle


def test_malformed_is_refused_and_changes_nothing(gw):
    gateway, cycle, client = gw
    replies = list(client.get(keys.drive_cmd(HOST, "x1", "enable"), payload=b"\x00\x01garbage", timeout=2.0))
    assert len(replies) == 1 and replies[0].err is not None
    assert "msgpack" in replies[0].err.payload.to_string() or "map" in replies[0].err.payload.to_string()
    bad = msgpack.packb({"v": 1, "type": "command_request", "request_id": "r", "op": "set_mode", "args": {"mode": 99}})
    replies = list(client.get(keys.drive_cmd(HOST, "*", "set_mode"), payload=bad, timeout=2.0))
    assert len(replies) == 1 and "mode" in replies[0].err.payload.to_string()
    assert cycle.submitted == []


def test_repeated_request_id_returns_first_outcome(gw):
    gateway, cycle, client = gw
    cycle.hold = True
    results = []
    t = threading.Thread(target=lambda: results.append(command(client, "x1", "enable", rid="dup")))
    t.start()
    wait_for(lambda: cycle.held, what="first command submitted")
    t2 = threading.Thread(target=lambda: results.append(command(client, "x1", "enable", rid="dup")))
    t2.start()
    wait_for(lambda: len(gateway.commands.request("dup").waiting) == 2, what="repeat attached to the pending request")
    cycle.release_held()
    t.join(5)
    t2.join(5)
    assert len(cycle.submitted) == 1
    assert [[r.outcome for _, r in oks] for oks, _ in results] == [["done"], ["done"]]
    oks, errs = command(client, "x1", "enable", rid="dup")        # after completion
    assert [r.outcome for _, r in oks] == ["done"] and len(cycle.submitted) == 1
    oks, errs = command(client, "x1", "disable", rid="dup")       # same id, other command
    assert oks == [] and "already used" in errs[0]


def test_inbox_full_is_busy(gw):
    gateway, cycle, client = gw
    cycle.accept = False
    oks, errs = command(client, "*", "enable")
    assert {r.outcome for _, r in oks} == {"busy"} and len(oks) == 3
    assert "inbox full" in oks[0][1].reason


def test_status_heartbeat_republishes_an_unchanged_status(gw):
    gateway, cycle, client = gw
    got = []
    sub = client.declare_subscriber(keys.drive_status(HOST, "x2"), lambda s: got.append(m.decode(s.payload)))
    try:
        wait_for(lambda: len(got) >= 2, what="heartbeats")       # heartbeat every 0.3 s, nothing changes
        assert {(s.state, s.error_code) for s in got} == {("switch_on_disabled", 0)}
        seqs = [s.seq for s in got]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    finally:
        sub.undeclare()


@contextlib.contextmanager
def watching_x2(net, **settings):
    """A ticking gateway whose heartbeat is an hour away and the x2 statuses a client receives,
    from after the first one (published and the subscriber matched)."""
    agent_s, client = net
    cycle = FakeCycle()
    ticker = Ticker(cycle)
    gateway = make_gateway(agent_s, cycle, heartbeat_s=3600.0, **settings)
    ticker.t.start()
    got: list = []
    sub = client.declare_subscriber(keys.drive_status(HOST, "x2"), lambda s: got.append(m.decode(s.payload)))
    try:
        wait_for(lambda: "x2" in gateway.publisher.published and gateway.publisher.status_pubs["x2"].matching_status.matching,
                 what="first status published and the subscriber matched")
        yield gateway, cycle, got
    finally:
        sub.undeclare()
        ticker.stop.set()
        ticker.t.join()
        gateway.close()


def test_status_on_change_and_get(net):
    """With the heartbeat an hour away, only the on-change path can publish the fault."""
    with watching_x2(net) as (gateway, cycle, got):
        client = net[1]
        n = len(got)
        cycle.set("x2", state="fault", error_code=0x2310)
        wait_for(lambda: any(s.state == "fault" for s in got[n:]), what="on-change status")
        assert [(s.state, s.error_code) for s in got[n:]] == [("fault", 0x2310)]  # once, on the change
        seqs = [s.seq for s in got]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
        replies = list(client.get(keys.drive_status(HOST, "*"), timeout=2.0))
        st = {m.decode(r.ok.payload).axis: m.decode(r.ok.payload) for r in replies}
        assert set(st) == set(AXES) and st["x2"].state == "fault" and st["x2"].error_code == 0x2310


def test_cycle_events_published_with_seq(gw):
    gateway, cycle, client = gw
    got = []
    sub = client.declare_subscriber(keys.drive_event(HOST, "x1"), lambda s: got.append(m.decode(s.payload)))
    try:
        ev = rt.CycleEvent("x1", "transition", "t2", "switch_on_disabled", "ready_to_switch_on")

        def burst():  # until the subscription is in place
            cycle.tick([ev] * 3)
            time.sleep(0.05)
            return len(got) >= 3

        wait_for(burst, what="events")
        seqs = [e.seq for e in got]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and got[0].kind == "transition"
    finally:
        sub.undeclare()


def test_lease_busy_takeover_release(gw):
    gateway, cycle, client = gw
    oks, _ = command(client, "x1", "lease", args={"holder": "supA"}, supervisor="supA")
    assert [(r.outcome, r.lease_holder) for _, r in oks] == [("done", "supA")]
    oks, _ = command(client, "x1", "enable", supervisor="supB")
    assert oks[0][1].outcome == "busy" and "supA" in oks[0][1].reason and oks[0][1].lease_holder == "supA"
    oks, _ = command(client, "x1", "enable", supervisor="supA")
    assert oks[0][1].outcome == "done"
    oks, _ = command(client, "x1", "lease", args={"holder": "supB"}, supervisor="supB")
    assert oks[0][1].outcome == "busy"
    oks, _ = command(client, "x1", "lease", args={"holder": "supB", "takeover": True}, supervisor="supB")
    assert (oks[0][1].outcome, oks[0][1].lease_holder) == ("done", "supB")
    wait_for(lambda: gateway.publisher.published.get("x1") and gateway.publisher.published["x1"].lease_holder == "supB",
             what="status shows the holder")
    oks, _ = command(client, "x1", "release", args={"holder": "supB"}, supervisor="supB")
    assert oks[0][1].outcome == "done"
    oks, _ = command(client, "x1", "enable", supervisor="supC")
    assert oks[0][1].outcome == "done"


def test_lease_expiry_runs_reaction(gw):
    gateway, cycle, client = gw
    command(client, "x1", "enable")
    oks, _ = command(client, "x1", "lease", args={"holder": "supA", "ttl_s": 0.3}, supervisor="supA")
    assert oks[0][1].outcome == "done"
    wait_for(lambda: [c.op for c in cycle.submitted if c.request_id.startswith("@")] == ["quick_stop", "disable"],
             what="quick stop then disable")
    assert cycle.drives["x1"].state == "switch_on_disabled"
    assert gateway.peers.leases.holders() == {}


def test_holder_token_loss_runs_reaction(gw):
    gateway, cycle, client = gw
    token = client.liveliness().declare_token(keys.supervisor_alive("supT"))
    try:
        command(client, "x2", "enable")
        oks, _ = command(client, "x2", "lease", args={"holder": "supT", "ttl_s": 60.0}, supervisor="supT")
        assert oks[0][1].outcome == "done"
    finally:
        token.undeclare()
    wait_for(lambda: [c.op for c in cycle.submitted if c.request_id.startswith("@")] == ["quick_stop", "disable"],
             what="reaction after the token disappeared")


def test_remote_group_member_fault_triggers(net):
    agent_s, client_s = net
    cycle = FakeCycle()
    gateway = make_gateway(agent_s, cycle, groups={"g": ("gw1/x1", "far/y1")})
    try:
        pub = client_s.declare_publisher(keys.drive_status("far", "y1"))
        good = m.DriveStatus(host="far", axis="y1", seq=1, time_ns=1, cycle=1, state="operation_enabled",
                             statusword=0x0237, controlword=0xF, goal="enabled", halt=False, mode=8, mode_display=8,
                             position=0, velocity=0, torque=0, error_code=0)
        fault = replace(good, seq=2, state="fault", error_code=0x7300)

        def publish_fault():
            pub.put(m.encode(fault))  # repeated until the subscription is in place
            return cycle.triggers

        wait_for(publish_fault, what="group trigger")
        for _ in range(3):
            pub.put(m.encode(fault))  # still faulted: no second trigger
        time.sleep(0.2)
        assert len(cycle.triggers) == 1 and cycle.triggers[0][0] == "g" and "far/y1 fault" in cycle.triggers[0][1]
        token = client_s.liveliness().declare_token(keys.alive("far"))
        remote = gateway.peers.remotes[0]

        def publish_good():
            pub.put(m.encode(good))
            return not remote.bad

        wait_for(publish_good, what="member good again")
        token.undeclare()
        wait_for(lambda: len(cycle.triggers) == 2, what="trigger on agent loss")
        assert "agent far lost" in cycle.triggers[1][1]
        pub.undeclare()
    finally:
        gateway.close()


def test_a_change_of_what_was_asked_alone_waits_for_the_drives_answer_bounded(net):
    """Controlword and goal changed, statusword not yet: no status until the drive answers, then
    one status carrying both; a change nobody answers goes out alone once the bound passed
    (HOLD_CYCLES cycles; 1 s cycles here, so the hold is long enough to be seen under load)."""
    with watching_x2(net, cycle_us=1_000_000) as (gateway, cycle, got):
        n = len(got)
        cycle.set("x2", controlword=0x0006, goal="enabled")
        wait_for(lambda: "x2" in gateway.publisher.held_until, what="the asked change held")
        assert got[n:] == []
        cycle.set("x2", state="ready_to_switch_on", statusword=0x0231)
        wait_for(lambda: len(got) > n, what="the answer's status")
        assert [(s.state, s.statusword, s.controlword, s.goal) for s in got[n:]] == [
            ("ready_to_switch_on", 0x0231, 0x0006, "enabled")]
        n = len(got)
        cycle.set("x2", controlword=0x0007)                       # the drive never answers this one
        wait_for(lambda: len(got) > n, timeout_s=20.0, what="the held change, out after the bound")
        assert [(s.state, s.controlword) for s in got[n:]] == [("ready_to_switch_on", 0x0007)]
        assert "x2" not in gateway.publisher.held_until
        cycle.set("x2", state="fault", error_code=0x2310)         # a drive's own change: never held
        wait_for(lambda: any(s.state == "fault" for s in got), what="the fault at once")
        seqs = [s.seq for s in got]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # no gap: nothing was dropped


def test_a_moving_drive_is_published_at_the_motion_rate_though_its_snapshot_object_stays(net):
    """A position change inside the motion period waits, and goes out once the period passed,
    while the cycle hands over the very same drive object pass after pass."""
    with watching_x2(net, motion_period_s=0.2) as (gateway, cycle, got):
        cycle.set("x2", position=100)
        wait_for(lambda: any(s.position == 100 for s in got), what="the first move")
        cycle.set("x2", position=200)                       # inside the motion period: waits
        wait_for(lambda: any(s.position == 200 for s in got), what="the second move, after the motion period")
        assert [s.position for s in got if s.position in (100, 200)] == [100, 200]
