"""The supervisor against real bus agents (simulated buses), each in its own process, through a
Zenoh router on loopback (multicast scouting off everywhere)."""

from __future__ import annotations

import sys
import textwrap
import threading
from typing import Iterator

import pytest

from schemas.messages import DriveStatus
from supervisor.fleet import Fleet
from supervisor.selectors import DriveRef, SelectorError
from supervisor.testbed import Proc, spawn, start_agent, start_router

pytestmark = pytest.mark.timeout(120)

HOSTS = ("h1", "h2", "h3")
N_DRIVES = 4
#: A killed agent is reported gone within this (safety bound: link lease 3 s, plus a loaded host).
DEPARTURE_BOUND_S = 10.0


@pytest.fixture(scope="module")
def bed() -> Iterator[dict]:
    router, ep = start_router()
    agents: dict[str, Proc] = {}
    try:
        for h in HOSTS:
            agents[h] = start_agent(h, N_DRIVES, ep)
        yield {"router": ep, "agents": agents}
    finally:
        for p in agents.values():
            p.stop()
        router.stop()


def _all_in(fleet: Fleet, refs, *states: str) -> bool:
    d = fleet.drives()
    return all(r in d and d[r].state in states for r in refs)


@pytest.fixture()
def fleet(bed: dict) -> Iterator[Fleet]:
    with Fleet(connect=[bed["router"]], name="sup-test") as f:
        assert f.wait_for_agents(HOSTS, timeout_s=10, drives=len(HOSTS) * N_DRIVES), f.hosts()
        # every test starts from a disabled, fault-free fleet
        faulted = [r for r, st in f.drives().items() if st.state in ("fault", "fault_reaction_active")]
        if faulted:
            f.command("fault_reset", f.selection_of(faulted))
        f.command("disable", "**")
        assert f.wait_until(lambda f: _all_in(f, f.roster(), "switch_on_disabled"), 5), _states(f)
        yield f


def _states(f: Fleet) -> dict[str, str]:
    return {str(r): st.state for r, st in sorted(f.drives().items())}


def _inject_fault(fleet: Fleet, ref: DriveRef, code: int = 0x7500) -> None:
    from bus_agent.sim.control import sim_inject

    st = fleet.status(ref)
    assert st is not None
    sim_inject(fleet.session, ref.host, st.slave, "fault", error_code=code)


def test_discovery_snapshot_and_selection(fleet: Fleet) -> None:
    assert set(HOSTS) <= set(fleet.hosts())
    roster = fleet.roster()
    assert len(roster) == len(HOSTS) * N_DRIVES
    axes = sorted({r.axis for r in roster})
    assert len(axes) == N_DRIVES
    sel = fleet.select(f"*/{axes[0]}")
    assert [r.host for r in sel.drives] == list(HOSTS)
    assert len(sel.plan.pairs) == 1  # one fan-out query
    with pytest.raises(SelectorError):
        fleet.select("h9*/x")
    for st in fleet.drives().values():
        assert isinstance(st, DriveStatus) and st.state == "switch_on_disabled"


def test_two_phase_enable_then_ordered_shutdown(fleet: Fleet) -> None:
    phases: list[str] = []
    report = fleet.enable("h1/*", "h2/*", "h3/*", before_phase=phases.append)
    assert report.ok, report.reason
    assert phases == ["switch_on", "enable"]
    assert [label for label, _ in report.steps] == ["switch_on", "enable"]
    assert len(report.final) == 12 and all(r.state == "operation_enabled" for r in report.final)
    assert fleet.wait_until(lambda f: _all_in(f, f.roster(), "operation_enabled"), 5), _states(fleet)

    reached: list[str] = []
    lock = threading.Lock()

    def on_status(st: DriveStatus) -> None:
        if st.state == "switch_on_disabled":
            with lock:
                if st.host not in reached:
                    reached.append(st.host)

    fleet.on("status", on_status)
    report = fleet.take_down([["h1/*"], ["h2/*"], ["h3/*"]])
    assert report.ok, report.reason
    assert [label for label, _ in report.steps] == ["disable:stage3", "disable:stage2", "disable:stage1"]
    assert fleet.wait_until(lambda f: _all_in(f, f.roster(), "switch_on_disabled"), 5), _states(fleet)
    assert fleet.wait_until(lambda f: len(reached) == 3, 5)
    assert reached == ["h3", "h2", "h1"]  # last enabled stage goes down first


def test_rollback_when_one_drive_faults_during_switch_on(fleet: Fleet) -> None:
    victim = fleet.select("h2/*").drives[1]

    def before(phase: str) -> None:
        if phase == "switch_on":
            _inject_fault(fleet, victim)

    report = fleet.enable("**", before_phase=before)
    assert not report.ok
    assert str(victim) in report.reason
    labels = [label for label, _ in report.steps]
    assert labels[0] == "switch_on" and "enable" not in labels
    assert any(label.startswith("rollback:") for label in labels), labels
    final = {DriveRef(r.host, r.axis): r for r in report.final}
    assert final[victim].outcome != "done"
    others = [r for r in fleet.roster() if r != victim]
    # every drive that moved went back; nothing was enabled
    assert fleet.wait_until(lambda f: _all_in(f, others, "switch_on_disabled"), 5), _states(fleet)
    assert fleet.wait_until(lambda f: _all_in(f, [victim], "fault"), 5), _states(fleet)
    assert not any(st.state == "operation_enabled" for st in fleet.drives().values())
    # a fault is reset only when asked
    res = fleet.fault_reset(str(victim))
    assert res.ok, res.failures


def test_enable_refused_before_sending_when_a_drive_is_in_fault(fleet: Fleet) -> None:
    victim = fleet.select("h3/*").drives[0]
    _inject_fault(fleet, victim)
    assert fleet.wait_until(lambda f: _all_in(f, [victim], "fault"), 5)
    report = fleet.enable("**")
    assert not report.ok and report.steps == ()
    assert "nothing sent" in report.reason and str(victim) in report.reason
    assert not any(st.state in ("switched_on", "operation_enabled") for st in fleet.drives().values())


def test_quick_stop_everywhere_and_partial_failure_reported(fleet: Fleet) -> None:
    assert fleet.enable("h1/*").ok
    res = fleet.quick_stop()  # every drive: enabled ones stop, the others are reported as they are
    assert len(res.results) == 12
    by = {DriveRef(r.host, r.axis): r for r in res.results}
    for ref in fleet.select("h1/*").drives:
        assert by[ref].outcome == "done"
    missing = fleet.command("disable", ["h1/*", "h9/x"])  # h9/x: named, absent -> missing
    bad = [r for r in missing.results if r.host == "h9"]
    assert len(bad) == 1 and bad[0].outcome == "missing" and not missing.ok


def test_two_supervisors_busy_then_takeover(bed: dict, fleet: Fleet) -> None:
    lost = threading.Event()
    with Fleet(connect=[bed["router"]], name="sup-a", lease_ttl_s=1.0) as a, \
            Fleet(connect=[bed["router"]], name="sup-b", lease_ttl_s=1.0) as b:
        a.on("lease_lost", lambda r: lost.set())
        got = a.lease("h1/*")
        assert got.ok, got.failures
        assert fleet.wait_until(lambda f: all(f.status(r).lease_holder == "sup-a" for r in f.select("h1/*").drives), 5)
        res = b.command("switch_on", "h1/*")
        assert {r.outcome for r in res.results} == {"busy"}
        assert {r.lease_holder for r in res.results} == {"sup-a"}
        assert not b.lease("h1/*").ok  # no takeover: busy
        took = b.lease("h1/*", takeover=True)
        assert took.ok, took.failures
        assert lost.wait(5), "sup-a was not told its lease was taken over"
        assert a.leases() == []
        res = a.command("switch_on", "h1/*")
        assert {r.outcome for r in res.results} == {"busy"}
        assert {r.lease_holder for r in res.results} == {"sup-b"}
        # b leaves cleanly: leases released, no reaction
    assert fleet.wait_until(lambda f: all(f.status(r).lease_holder == "" for r in f.select("h1/*").drives), 5)


SUPERVISOR_SCRIPT = textwrap.dedent("""
    import sys, time
    from supervisor.fleet import Fleet
    f = Fleet(connect=[sys.argv[1]], name="sup-doomed", lease_ttl_s=float(sys.argv[2])).open()
    assert f.wait_for_agents(["h3"], 10)
    assert f.lease("h3/*").ok
    assert f.enable("h3/*").ok
    print("enabled", flush=True)
    while True:  # mid-operation: toggling halt when the kill comes
        f.halt("h3/*", on=True); f.halt("h3/*", on=False)
""")


def test_supervisor_killed_mid_operation_runs_the_lease_reaction(bed: dict, fleet: Fleet) -> None:
    ttl_s = 2.0
    p = spawn("supervisor", [sys.executable, "-c", SUPERVISOR_SCRIPT, bed["router"], str(ttl_s)], ready_marker="enabled")
    try:
        assert p.wait_ready(30), p.output()
        h3 = fleet.select("h3/*").drives
        assert fleet.wait_until(lambda f: _all_in(f, h3, "operation_enabled"), 5), _states(fleet)
        assert all(fleet.status(r).lease_holder == "sup-doomed" for r in h3)
        p.kill()  # SIGKILL: no release, no clean-up
    finally:
        p.stop()
    # the agents run the reaction (quick stop, then disable) within the lease
    assert fleet.wait_until(lambda f: _all_in(f, h3, "switch_on_disabled", "quick_stop_active")
                            and all(f.status(r).lease_holder == "" for r in h3), ttl_s + 1.0), _states(fleet)
    others = [r for r in fleet.roster() if r.host != "h3"]
    assert _all_in(fleet, others, "switch_on_disabled")


def test_agent_killed_is_reported_gone(bed: dict, fleet: Fleet) -> None:
    gone = threading.Event()
    fleet.on("departure", lambda host: host == "h8" and gone.set())
    agent = start_agent("h8", 2, bed["router"])
    try:
        assert fleet.wait_for_agents(["h8"], 10, drives=len(HOSTS) * N_DRIVES + 2)
        agent.kill()
        # a safety bound (the link lease is 3 s), not a latency figure; generous for a loaded host
        assert gone.wait(DEPARTURE_BOUND_S), f"departure of h8 not reported within {DEPARTURE_BOUND_S} s"
        assert "h8" not in fleet.hosts()
        res = fleet.command("switch_on", fleet.selection_of([r for r in fleet.drives() if r.host == "h8"]))
        assert res.results and {r.outcome for r in res.results} == {"missing"}
        assert all("gone" in r.error for r in res.results)
        with pytest.raises(SelectorError):
            fleet.select("h8/*")  # no live drive matches any more
    finally:
        agent.stop()
