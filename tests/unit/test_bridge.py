"""The cycle <-> gateway process bridge: encoding, the forward filter, and both ends of the
bridge over a socketpair (a fake cycle on one side, a CycleProxy on the other; no zenoh)."""

from __future__ import annotations

import functools
import dataclasses
import os
import socket
import threading
from multiprocessing.connection import Connection

import pytest

from bus_agent.sim import child
from bus_agent import runtime as rt
from bus_agent.gateway.bridge import GatewayProcess
from bus_agent.gateway.child import CycleProxy
from bus_agent.gateway.wire import (FORWARD_NOW_FIELDS, ForwardFilter, Msg, decode_command, decode_event, decode_outcome,
                                    decode_snapshot, dumps, encode_command, encode_event, encode_snapshot, encode_update,
                                    loads)

pytestmark = pytest.mark.timeout(30)

AXES = ("a0", "a1")


def drive(axis="a0", slave=0, **kw) -> rt.DriveSnapshot:
    base = dict(axis=axis, slave=slave, state="switch_on_disabled", statusword=0x0250, controlword=0,
                goal="disabled", halt=False, mode=8, mode_display=8, position=0, velocity=0, torque=0,
                error_code=0, error_text="", al_state="op", lost=False)
    base.update(kw)
    return rt.DriveSnapshot(**base)


def snapshot(cycle=1, drives=None, events=(), state="running") -> rt.CycleSnapshot:
    drives = drives if drives is not None else (drive("a0", 0), drive("a1", 1))
    return rt.CycleSnapshot(cycle=cycle, time_ns=1_700_000_000_000_000_000 + cycle, drives=tuple(drives),
                            events=tuple(events), stats=rt.CycleStats(cycles=cycle, period_p99_us=1001.5, overruns=2),
                            agent_state=state)


wait_for = functools.partial(child.wait_for, timeout_s=5.0, poll_s=0.005)


# ---- pure encoding ----------------------------------------------------------------------------


def test_snapshot_round_trip_keeps_every_field():
    s = snapshot(7, drives=(drive("a0", 0, position=-123456, velocity=5, torque=-7, halt=True, lost=True,
                                  error_code=0x7300, error_text="over temp"), drive("a1", 1)))
    back = decode_snapshot(loads(dumps((Msg.UPDATE.value, encode_snapshot(s))))[1])
    assert back == dataclasses.replace(s, events=())


def test_an_unchanged_drive_keeps_its_snapshot_object_and_a_changed_one_is_read_anew():
    first_t = encode_snapshot(snapshot(1, drives=(drive("a0", 0), drive("a1", 1))))
    first = decode_snapshot(first_t)
    s2 = snapshot(2, drives=(drive("a0", 0), drive("a1", 1, state="ready_to_switch_on", statusword=0x0231)))
    second = decode_snapshot(encode_snapshot(s2), (), (first_t, first))
    assert second == dataclasses.replace(s2, events=())
    assert second.drives[0] is first.drives[0] and second.drives[1] is not first.drives[1]
    assert second.drives[1].state == "ready_to_switch_on"
    three = snapshot(3, drives=(drive("a0", 0), drive("a1", 1), drive("a2", 2)))  # the drive list changed
    back = decode_snapshot(encode_snapshot(three), (), (first_t, first))
    assert back == dataclasses.replace(three, events=()) and back.drives[0] is not first.drives[0]


def test_event_outcome_and_command_round_trip():
    ev = rt.CycleEvent("a1", "transition", "cw 0x000F", from_state="switched_on", to_state="operation_enabled",
                       error_code=0, request_id="r1")
    assert decode_event(encode_event(ev, 42, 99)) == (ev, 42, 99)
    o = rt.Outcome("a0", "done", state="operation_enabled", reason="", elapsed_s=0.004, cycles=4)
    kind, snap_t, events_t, outcomes_t = loads(encode_update(None, [(ev, 42, 99)], [(5, o)]))
    assert kind is Msg.UPDATE and snap_t is None
    assert [decode_event(e) for e in events_t] == [(ev, 42, 99)]
    assert [(cid, decode_outcome(t)) for cid, t in outcomes_t] == [(5, o)]
    cb = lambda o: None  # noqa: E731
    d = rt.DriveCommand("r2", "set_mode", ("a0", "a1"), args={"mode": 9}, timeout_s=2.0, supervisor="sup",
                        received_ns=123, on_outcome=cb)
    kind, cid, fields = loads(encode_command(3, d))
    assert (kind, cid) == (Msg.SUBMIT, 3) and decode_command(fields, cb) == d
    a = rt.AgentCommand("r3", "nmt", args={"command": "stop", "axis": "a1"}, received_ns=5, on_outcome=cb)
    assert decode_command(loads(encode_command(4, a))[2], cb) == a


def test_loads_refuses_what_is_not_a_tagged_tuple():
    with pytest.raises(ValueError):
        loads(dumps([]))
    with pytest.raises(ValueError):
        loads(dumps((99,)))


def test_forward_now_fields_are_the_gateways_change_fields():
    from bus_agent.gateway.gateway import CHANGE_FIELDS

    assert FORWARD_NOW_FIELDS == CHANGE_FIELDS


# ---- forward filter ---------------------------------------------------------------------------------


def test_filter_forwards_first_then_motion_only_at_the_period():
    f = ForwardFilter(0.05)
    assert f.due(snapshot(1), 10.0)
    moved = snapshot(2, drives=(drive("a0", 0, position=100, velocity=3, torque=1), drive("a1", 1)))
    assert not f.due(moved, 10.01)
    assert not f.due(moved, 10.049)
    assert f.due(moved, 10.05)            # the period passed
    assert not f.due(moved, 10.06)


@pytest.mark.parametrize("field, value", [
    ("state", "ready_to_switch_on"), ("statusword", 0x0231), ("controlword", 6), ("goal", "enabled"),
    ("halt", True), ("mode", 9), ("mode_display", 9), ("error_code", 0x2310), ("error_text", "x"),
    ("al_state", "safeop"), ("lost", True)])
def test_filter_forwards_a_change_of_a_published_field_at_once(field, value):
    f = ForwardFilter(10.0)
    assert f.due(snapshot(1), 0.0)
    assert not f.due(snapshot(2), 0.001)
    assert f.due(snapshot(3, drives=(drive("a0", 0), drive("a1", 1, **{field: value}))), 0.002)
    assert not f.due(snapshot(4, drives=(drive("a0", 0), drive("a1", 1, **{field: value}))), 0.003)


def test_filter_forwards_agent_state_changes_and_pending_items():
    f = ForwardFilter(10.0)
    assert f.due(snapshot(1), 0.0)
    assert f.due(snapshot(2, state="stopping"), 0.001)
    assert not f.due(snapshot(3, state="stopping"), 0.002)
    assert f.due(snapshot(4, state="stopping"), 0.003, pending=True)


# ---- both ends over a socketpair ------------------------------------------------------------------------


class FakeCycle:
    def __init__(self):
        self.snapshot_sink = None
        self.state = "running"
        self.accept = True
        self.submitted: list = []
        self.triggers: list = []

    def submit(self, cmd):
        if not self.accept:
            return False
        self.submitted.append(cmd)
        return True

    def trigger_group(self, group, reason):
        self.triggers.append((group, reason))


class Pair:
    """GatewayProcess (cycle side) attached to a CycleProxy (gateway side) on a socketpair."""

    def __init__(self, handlers=None):
        ours, theirs = socket.socketpair()
        self.cycle = FakeCycle()
        self.lost: list[str] = []
        self.gp = GatewayProcess(self.cycle, {"host": "h1", "axes": AXES, "heartbeat_s": 1.0}, zenoh=None,
                                 sim_handlers=handlers, n_slaves=2, on_lost=self.lost.append,
                                 forward_period_s=0.05)
        self.child = Connection(theirs.detach())
        self.proxy = CycleProxy(self.child, AXES)
        self.snaps: list = []
        self.events: list = []
        self.proxy.snapshot_sink = self.snaps.append
        self.proxy.event_sink = self.events.extend
        self.init = None
        self.ended: list[str] = []
        self.reader = threading.Thread(target=self._child, daemon=True)
        self.reader.start()
        self.gp.attach(Connection(ours.detach()), timeout_s=5.0)

    def _child(self):
        self.init = loads(self.child.recv_bytes())
        self.child.send_bytes(dumps((Msg.READY.value,)))
        while True:
            try:
                msg = loads(self.child.recv_bytes())
            except (EOFError, OSError):
                self.ended.append("eof")
                return
            if msg[0] in (Msg.CLOSE, Msg.STOPPING):
                self.ended.append(msg[0].name)
                if msg[0] is Msg.CLOSE:
                    self.child.close()   # as the process exit would
                    return
                continue
            self.proxy.dispatch(msg)


@pytest.fixture
def pair():
    p = Pair(handlers={"fault": lambda pos, args: f"slave {pos}: fault 0x{args['error_code']:04X}",
                       "plug": lambda pos, args: (_ for _ in ()).throw(ValueError("takes no arguments"))})
    yield p
    p.gp.close(timeout_s=2.0)


def test_init_carries_settings_and_sim_actions(pair):
    kind, settings, _zenoh, sim = pair.init
    assert kind is Msg.INIT and settings["axes"] == AXES and sim == ("h1", 2, ("fault", "plug"))
    assert pair.cycle.snapshot_sink == pair.gp.on_snapshot


def test_submit_is_a_round_trip_and_outcomes_route_by_command(pair):
    got: list = []
    cmd = rt.DriveCommand("r1", "enable", AXES, timeout_s=3.0, received_ns=77, on_outcome=got.append)
    assert pair.proxy.submit(cmd)
    (sent,) = pair.cycle.submitted
    assert (sent.request_id, sent.op, sent.axes, sent.received_ns) == ("r1", "enable", AXES, 77)
    sent.on_outcome(rt.Outcome("a0", "done", state="operation_enabled"))   # as the cycle thread would
    sent.on_outcome(rt.Outcome("a1", "timeout"))
    wait_for(lambda: len(got) == 2, what="outcomes")
    assert [(o.axis, o.outcome) for o in got] == [("a0", "done"), ("a1", "timeout")]


def test_refused_submit_reports_the_cycle_state(pair):
    pair.cycle.accept = False
    pair.cycle.state = "stopping"
    assert not pair.proxy.submit(rt.AgentCommand("r2", "nmt", args={"command": "stop"}))
    assert pair.proxy.state == "stopping"


def test_snapshots_and_events_keep_their_cycle(pair):
    ev1 = rt.CycleEvent("a0", "transition", to_state="ready_to_switch_on")
    ev2 = rt.CycleEvent("a1", "fault", error_code=0x7300)
    s3 = snapshot(3, events=(ev1,))
    s4 = snapshot(4, drives=(drive("a0", 0), drive("a1", 1, state="fault")), events=(ev2,))
    pair.gp.on_snapshot(s3)
    pair.gp.on_snapshot(s4)
    wait_for(lambda: len(pair.events) == 2, what="events")
    assert pair.events == [(ev1, 3, s3.time_ns), (ev2, 4, s4.time_ns)]
    wait_for(lambda: pair.proxy.latest is not None and pair.proxy.latest.cycle == 4, what="latest snapshot")
    assert pair.proxy.latest == dataclasses.replace(s4, events=())
    assert pair.snaps[-1] is pair.proxy.latest


def test_trigger_and_sim_calls_reach_the_cycle_side(pair):
    pair.proxy.trigger_group("line", "gb/axis0 fault")
    wait_for(lambda: pair.cycle.triggers, what="trigger")
    assert pair.cycle.triggers == [("line", "gb/axis0 fault")]
    assert pair.proxy.sim_call("fault", 1, {"error_code": 0x7300}) == "slave 1: fault 0x7300"
    with pytest.raises(ValueError, match="takes no arguments"):
        pair.proxy.sim_call("plug", 0, {"x": 1})


def test_close_flushes_then_closes(pair):
    pair.gp.stop_commands()
    ev = rt.CycleEvent("a0", "transition", to_state="switch_on_disabled")
    pair.gp.on_snapshot(snapshot(9, events=(ev,), state="stopped"))
    pair.gp.close(timeout_s=2.0)
    pair.reader.join(5)
    assert pair.ended == ["STOPPING", "CLOSE"]
    assert pair.proxy.latest.agent_state == "stopped" and pair.events[-1][0] == ev
    assert pair.lost == []


def test_lost_gateway_is_reported_once_and_events_are_logged(pair, caplog):
    # the gateway process died: its end of the socketpair is shut (both directions)
    with socket.socket(fileno=os.dup(pair.child.fileno())) as s:
        s.shutdown(socket.SHUT_RDWR)
    wait_for(lambda: pair.lost, what="on_lost")
    assert pair.gp.lost_reason and "lost" in pair.lost[0]
    with caplog.at_level("WARNING", logger="bus_agent.gateway.bridge"):
        pair.gp.on_snapshot(snapshot(10, events=(rt.CycleEvent("a1", "transition", to_state="switched_on"),)))
        wait_for(lambda: "no gateway" in caplog.text, what="event logged")
    assert "a1" in caplog.text and "switched_on" in caplog.text
    assert len(pair.lost) == 1


# ---- configuration: gateway mode and cycle priority ------------------------------------------------


def test_gateway_mode_and_rt_priority_from_toml_and_flags():
    from bus_agent.cli import _parser, build_config
    from bus_agent.config import ConfigError, config_from_dict

    cfg = config_from_dict({"host": "h1", "sim_drives": 2})
    assert (cfg.gateway, cfg.rt_priority) == ("process", 0)
    cfg = config_from_dict({"host": "h1", "sim_drives": 2, "gateway": "thread", "cycle": {"rt_priority": 10}})
    assert (cfg.gateway, cfg.rt_priority) == ("thread", 10)
    with pytest.raises(ConfigError, match="gateway"):
        config_from_dict({"host": "h1", "sim_drives": 2, "gateway": "fork"})
    with pytest.raises(ConfigError, match="cycle.rt_priority"):
        config_from_dict({"host": "h1", "sim_drives": 2, "cycle": {"rt_priority": 100}})
    with pytest.raises(ConfigError, match="cycle.period"):
        config_from_dict({"host": "h1", "sim_drives": 2, "cycle": {"period": 1}})
    args = _parser().parse_args(["--sim", "2", "--host", "h1", "--rt-priority", "20", "--gateway-thread"])
    cfg = build_config(args)
    assert (cfg.gateway, cfg.rt_priority) == ("thread", 20)
    cfg = build_config(_parser().parse_args(["--sim", "2", "--host", "h1"]))
    assert (cfg.gateway, cfg.rt_priority) == ("process", 0)
