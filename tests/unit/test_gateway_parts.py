"""The gateway's parts on their own: the hand-offs (Feed, Inbox) and the host claim's conflict."""

from __future__ import annotations

import time
from types import SimpleNamespace

from bus_agent import runtime as rt
from bus_agent.gateway.handoff import Feed, Inbox
from bus_agent.gateway.hostclaim import HostClaim
from bus_agent.gateway.settings import GatewaySettings
from schemas import messages as m


def _snap(cycle: int, state: str) -> rt.CycleSnapshot:
    drive = rt.DriveSnapshot("x1", 0, state, 0x0237, 0, "enabled", False, 8, 8, 0, 0, 0, 0, "", "op", False)
    return rt.CycleSnapshot(cycle, 1_000, (drive,), (rt.CycleEvent("x1", "transition"),), rt.CycleStats())


def test_feed_keeps_the_latest_snapshot_its_events_in_order_and_wakes_the_publisher():
    feed = Feed()
    assert feed.state("x1") == "unknown"
    feed.on_snapshot(_snap(7, "operation_enabled"))
    assert feed.wake.is_set() and feed.state("x1") == "operation_enabled" and feed.state("x9") == "unknown"
    feed.wake.clear()
    feed.emit_all(rt.CycleEvent(a, "command") for a in ("x1", "x2"))
    assert feed.wake.is_set()
    assert [(ev.axis, ev.kind, cycle) for ev, cycle, _ in feed.events] == [
        ("x1", "transition", 7), ("x1", "command", 7), ("x2", "command", 7)]
    feed.agent_status_now()
    assert feed.agent_due


def test_inbox_work_marks_the_command_thread_busy_before_it_is_queued():
    inbox = Inbox()
    assert inbox.idle.is_set() and inbox.empty()
    inbox.put((print, ()))
    assert inbox.idle.is_set()   # plain work answers nobody waiting: the publisher need not wait
    inbox.work((print, ()))
    assert not inbox.idle.is_set() and inbox.get() == (print, ()) and inbox.get() == (print, ())


def test_host_claim_reports_a_conflict_at_once_and_its_end_after_the_other_instance_is_silent():
    events: list[rt.CycleEvent] = []
    due: list[bool] = []
    settings = GatewaySettings(host="h1", axes=("x1",), agent_period_s=0.1, instance="mine")
    claim = HostClaim(settings, None, events.append, lambda: due.append(True))
    status = m.AgentStatus(host="h1", seq=1, time_ns=1, state="running", backend="sim", cycle_us=1000, cycles=1,
                           period_p50_us=1000.0, period_p99_us=1000.0, period_max_us=1000.0, overruns=0,
                           wkc_errors=0, expected_wkc=3, instance="other")
    claim.on_own_status(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: m.encode(status))))
    assert "other" in claim.conflict_text and "mine" in claim.conflict_text and due == [True]
    assert [(e.axis, e.kind) for e in events] == [("", "conflict")]
    claim.tick(time.monotonic())            # still within hold_s (1 s at the least): no change
    assert claim.conflict_text and len(events) == 1
    claim.tick(time.monotonic() + 1.5)
    assert claim.conflict_text == "" and events[-1].detail == "host name conflict over" and due == [True, True]
