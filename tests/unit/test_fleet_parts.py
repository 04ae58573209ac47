"""The Fleet's parts on their own (no Zenoh): the view's status bookkeeping, the events'
dispatcher, the leases' renewal, and the exact selection a part plans its queries with."""

from __future__ import annotations

import threading
import time

from schemas import keys
from schemas.messages import DriveStatus
from supervisor.events import FleetEvents
from supervisor.leases import FleetLeases
from supervisor.results import CommandResult, DriveResult
from supervisor.selectors import DriveRef, exact_selection
from supervisor.view import FleetView


def status(axis: str = "a0", seq: int = 1, host: str = "h1") -> DriveStatus:
    return DriveStatus(host=host, axis=axis, seq=seq, time_ns=1, cycle=1, state="switch_on_disabled",
                       statusword=0x40, controlword=0, goal="disabled", halt=False, mode=8, mode_display=8,
                       position=0, velocity=0, torque=0, error_code=0)


def test_view_keeps_the_newest_status_counts_gaps_and_forgets_them_when_the_agent_returns() -> None:
    events: list[tuple] = []
    departed: list[str] = []
    view = FleetView("t", lambda *e: events.append(e), departed.append)
    view.host_alive(keys.alive("h1"), True)
    ref = DriveRef("h1", "a0")
    view.apply_status(status(seq=5))
    view.apply_status(status(seq=4))          # older (a get reply after the subscription): ignored
    view.apply_status(status(seq=8))          # 6 and 7 lost
    assert view.status(ref).seq == 8 and view.missed() == {ref: 2} and view.status_count == 2
    assert view.roster() == [ref] and view.hosts() == ["h1"]
    view.host_alive(keys.alive("h1"), False)
    assert departed == ["h1"] and view.roster() == [] and view.hosts() == []
    view.host_alive(keys.alive("h1"), True)   # a restarted agent counts anew
    view.apply_status(status(seq=1))
    assert view.status(ref).seq == 1 and view.missed() == {ref: 0}
    assert [e[0] for e in events] == ["arrival", "status", "status", "departure", "arrival", "status"]


def test_view_wait_until_wakes_on_an_update() -> None:
    view = FleetView("t", lambda *e: None, lambda h: None)
    threading.Timer(0.05, view.host_alive, (keys.alive("h2"), True)).start()
    t0 = time.monotonic()
    assert view.wait_until(lambda: view.hosts() == ["h2"], 5.0)
    assert time.monotonic() - t0 < 2.0
    assert not view.wait_until(lambda: False, 0.05)


def test_events_run_listeners_in_order_on_their_own_thread_and_survive_a_failing_one() -> None:
    ev = FleetEvents("t")
    got: list[tuple[str, str]] = []
    done = threading.Event()
    ev.on("arrival", lambda h: 1 / 0)
    ev.on("arrival", lambda h: got.append((h, threading.current_thread().name)))
    ev.on("departure", lambda h: done.set())
    ev.emit("status", "nobody listens")
    ev.start()
    ev.emit("arrival", "h1")
    ev.emit("departure", "h1")
    assert done.wait(5)
    ev.stop()
    assert got == [("h1", "fleet-t-events")]


def test_leases_are_renewed_and_a_lost_one_is_dropped_and_reported() -> None:
    calls: list[tuple[str, tuple[DriveRef, ...], dict]] = []
    lost: list[DriveResult] = []
    reported = threading.Event()

    def command(op, sel, args, timeout_s):
        calls.append((op, sel.drives, dict(args)))
        renewals = sum(1 for c in calls if c[0] == "lease") - 1
        out = []
        for r in sel.drives:
            busy = renewals >= 1 and r.axis == "b"   # taken over after the first renewal
            out.append(DriveResult(r.host, r.axis, "busy" if busy else "done", lease_holder="other" if busy else ""))
        return CommandResult(op, "r", tuple(out))

    def on_lost(event, r):
        lost.append(r)
        reported.set()

    leases = FleetLeases("sup", 0.15, command, lambda refs: exact_selection(refs, {}), on_lost)
    refs = [DriveRef("h1", "a"), DriveRef("h1", "b")]
    res = leases.lease(exact_selection(refs, {}), 0.15, False, 1.0)
    assert res.ok and leases.held() == refs
    assert reported.wait(5)
    assert leases.held() == [DriveRef("h1", "a")] and [r.name for r in lost] == ["h1/b"]
    leases.release(exact_selection(leases.held(), {}), 1.0)
    leases.stop()
    assert leases.held() == [] and calls[-1][0] == "release" and calls[0][2]["holder"] == "sup"


def test_exact_selection_queries_a_whole_host_once() -> None:
    refs = [DriveRef("h1", "a"), DriveRef("h1", "b"), DriveRef("h2", "a")]
    sel = exact_selection(refs, {"h1": ["a", "b"], "h2": ["a", "b"]})
    assert sel.plan.pairs == (("h1", "*"), ("h2", "a")) and len(sel) == 3
    assert exact_selection(refs, {}, per_host=True).plan.pairs == (("h1", "*"), ("h2", "*"))
