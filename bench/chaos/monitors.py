"""The soak's monitors: each promise of the README as a pure function of a :class:`Trace`.

A monitor is written against the wire contract alone (status, events, replies, flight
recordings) and the soak's own log of what it sent and injected. Each returns a :class:`Result`:
how many cases it checked, how many it could not judge (``skipped``: the host was cut off, its
agent or the router restarting, so the wire could not carry the answer) and its violations, each
with the details needed to find it again. :data:`MONITORS` lists them in report order; the
self-test (:mod:`bench.chaos.selftest`) feeds each a trace that breaks it and one that keeps it.
"""

from __future__ import annotations

import bisect
from collections import defaultdict
from typing import Any, Callable, Iterable

from .limits import check_limits
from .trace import BAD_STATES, DOWN_GOALS, DOWN_STATES, REFUSED, UP, Command, Event, Injection, Result, Status, Trace, Violation

#: Within this long after a host's link, agent or the router came back (the twin saw every drive
#: of the host answer again), other sessions' routes to it may still be forming: its cases are
#: skipped, not judged. Subscriptions (status, events: the reflex) come back first; a query's
#: route to the agent's queryables later (a simulator query right after a restored cut found no
#: queryable at once, while the twin already saw the host's status), so queries get longer.
SETTLE_NS = 2_000_000_000
QUERY_SETTLE_NS = 5_000_000_000
#: A remote group member reacts within this long of its origin's fault or loss (agent time stamps).
#: The README promises "within milliseconds"; the latency target (p99 <= 3 ms, real-time priority,
#: a quiet machine) is bench_reflex's. The soak runs a whole twin without real-time priority on a
#: shared 2-core machine (p50 19 ms, 95 ms seen at load 4), so its bound is the drives' own: the
#: simulated slaves' SM watchdog (100 ms) stops a drive whose master went silent, and a reflex
#: slower than that is one a plant would notice. It catches a reflex missing or late beyond
#: that, not one off the latency target; the result reports the latencies seen (``remote_reflex_ms``).
REFLEX_REMOTE_DEADLINE_MS = 100.0
#: A host's stall (its agent's longest cycle period) is looked up in the agent statuses received
#: this long after an origin: each covers the last 1000 cycles and comes every second.
STALL_LOOKUP_NS = 2_500_000_000
#: A fault, unplug or WKC fault reaches the agent's next cycle; a status stamped later than this
#: after the simulator applied it must not show the drive enabled and healthy.
INJECTION_MARGIN_NS = 10_000_000
#: Most examples listed per violation kind (the counts are always complete).
EXAMPLES = 5

Monitor = Callable[[Trace], Result]


# ---- helpers ------------------------------------------------------------------------------------


def disrupted(trace: Trace, host: str, t0: int, t1: int, settle_ns: int = SETTLE_NS) -> bool:
    """Whether ``host``'s messages may have been cut off between ``t0`` and ``t1``: its link cut,
    its agent or the router restarting, or within ``settle_ns`` after."""
    for inj in trace.injections:
        if inj.kind == "router_restart" or (inj.kind in ("cut", "agent_restart") and inj.host == host):
            if inj.start_ns <= t1 and t0 <= inj.end_ns + settle_ns:
                return True
    return False


def restarted_between(trace: Trace, host: str, t0: int, t1: int) -> bool:
    """Whether ``host``'s agent was killed between ``t0`` and ``t1`` (a new instance numbers anew)."""
    return any(i.kind == "agent_restart" and i.host == host and t0 <= i.end_ns and i.start_ns <= t1
               for i in trace.injections)


def statuses_by_ref(trace: Trace) -> dict[str, list[Status]]:
    """Each drive's statuses in the agent's time order."""
    out: dict[str, list[Status]] = defaultdict(list)
    for s in trace.statuses:
        out[s.ref].append(s)
    for v in out.values():
        v.sort(key=lambda s: s.time_ns)
    return out


def last_before(statuses: list[Status], t_ns: int) -> Status | None:
    i = bisect.bisect_left([s.time_ns for s in statuses], t_ns)
    return statuses[i - 1] if i else None


def add(result: Result, what: str, **detail: Any) -> None:
    result.violations.append(Violation(result.monitor, what, detail))


# ---- 1. exactly one terminal reply per addressed drive -------------------------------------------


def one_reply(trace: Trace) -> Result:
    """Every well-formed command gets exactly one reply per addressed drive (a refusal of the
    whole query by the drive's agent counts as its one answer), and none for other drives."""
    r = Result("one_terminal_reply")
    for c in trace.commands:
        if c.malformed:
            continue
        for ref in c.addressed:
            host = ref.split("/")[0]
            if disrupted(trace, host, c.sent_ns, c.done_ns, QUERY_SETTLE_NS):
                r.skipped += 1
                continue
            r.checked += 1
            n = len(c.replies_of(ref)) + sum(1 for e in c.errors if e.host == host)
            if n != 1:
                add(r, "no terminal reply" if n == 0 else f"{n} replies", request_id=c.request_id, op=c.op,
                    drive=ref, outcomes=[x.outcome for x in c.replies_of(ref)],
                    errors=[e.text for e in c.errors if e.host == host])
        for x in c.replies:
            if x.ref not in c.addressed:
                add(r, "reply from a drive not addressed", request_id=c.request_id, op=c.op, drive=x.ref)
    return r


# ---- 2. no unrequested enable ---------------------------------------------------------------------


def _enables(trace: Trace) -> dict[str, list[tuple[Command, str, int]]]:
    """Per drive: (command, its outcome for that drive or '', its reply time or 0) of every enable."""
    out: dict[str, list[tuple[Command, str, int]]] = defaultdict(list)
    for c in trace.commands:
        if c.op != "enable" or c.malformed:
            continue
        for ref in c.addressed:
            rs = c.replies_of(ref)
            out[ref].append((c, rs[0].outcome if rs else "", rs[0].t_ns if rs else 0))
    return out


def _enable_covers(c: Command, outcome: str, reply_ns: int, down_ns: int, up_ns: int) -> bool:
    """Whether enable ``c`` explains a rise to operation enabled at ``up_ns`` after the drive was
    last seen going down at ``down_ns``: accepted (not rejected or busy), sent before the rise,
    and either sent after the drive went down or pending then and done; one that failed or timed
    out covers only a rise before its answer."""
    if outcome in REFUSED or c.sent_ns > up_ns:
        return False
    if c.sent_ns < down_ns and not (outcome == "done" and reply_ns >= down_ns):
        return False
    return outcome in ("done", "") or up_ns <= reply_ns


def no_unrequested_enable(trace: Trace) -> Result:
    """A drive seen ``operation_enabled`` (and not lost) had an accepted enable since it last went
    down: seen in another state, seen lost, or its agent killed."""
    r = Result("no_unrequested_enable")
    enables = _enables(trace)
    kills = [i for i in trace.injections if i.kind == "agent_restart"]
    for ref, sts in statuses_by_ref(trace).items():
        host = ref.split("/")[0]
        downs = sorted(i.start_ns for i in kills if i.host == host)
        up, down_ns = False, 0
        for s in sts:
            # an agent killed since the last status: the drive went down then (SM watchdog)
            k = bisect.bisect_right(downs, s.time_ns)
            if up and k and downs[k - 1] > down_ns and downs[k - 1] <= s.time_ns:
                up, down_ns = False, downs[k - 1]
            if s.state == UP and not s.lost:
                if not up:
                    r.checked += 1
                    if not any(_enable_covers(c, o, t, down_ns, s.time_ns) for c, o, t in enables.get(ref, ())):
                        add(r, "operation_enabled without an accepted enable since it went down", drive=ref,
                            seq=s.seq, time_ns=s.time_ns, cycle=s.cycle, down_since_ns=down_ns)
                    up = True
            elif up or not down_ns:
                up, down_ns = False, s.time_ns
    return r


# ---- 3. group reflex deadline ---------------------------------------------------------------------


def _bad(s: Status | None) -> bool:
    return s is not None and (s.lost or s.state in BAD_STATES)


def stall_ns(trace: Trace, host: str, t0: int) -> int:
    """The longest cycle period ``host``'s agent reported in the statuses received within
    :data:`STALL_LOOKUP_NS` after ``t0`` (0 if none): how long its cycle could not run."""
    return int(1000 * max((a.period_max_us for a in trace.agents
                           if a.host == host and t0 <= a.t_ns <= t0 + STALL_LOOKUP_NS), default=0.0))


def group_reflex(trace: Trace, remote_deadline_ms: float = REFLEX_REMOTE_DEADLINE_MS) -> Result:
    """When a group member turns bad (event ``fault`` or ``lost`` after a healthy status), every
    other member not lost gets its ``reflex`` event: in the same cycle on the same host; on
    another host within ``remote_deadline_ms`` (agent time stamps) of the origin's bad status
    being on the wire (the soak's subscriber saw it: a starved origin gateway publishes late,
    ``origin_on_wire_ms`` reports how late), plus the longest cycle period the reacting host's
    agent reported around then (a stalled host reacts with its first cycle after the stall; the
    result counts reflexes later than the deadline as ``late_by_stall``)."""
    r = Result("group_reflex")
    by_ref = statuses_by_ref(trace)
    reflexes: dict[str, list[Event]] = defaultdict(list)
    for e in trace.events:
        if e.kind == "reflex":
            reflexes[e.ref].append(e)
    deadline_ns = int(remote_deadline_ms * 1e6)
    lost_events = [e for e in trace.events if e.kind == "lost"]
    remote_ms: list[float] = []
    publish_ms: list[float] = []  # origin's event to its bad status seen on the wire
    for e in trace.events:
        if e.kind not in ("fault", "lost") or _bad(last_before(by_ref.get(e.ref, []), e.time_ns)):
            continue
        for group, members in trace.groups.items():
            if e.ref not in members:
                continue
            for m in members:
                if m == e.ref:
                    continue
                host = m.split("/")[0]
                local = host == e.host
                if disrupted(trace, host, e.time_ns, e.time_ns + deadline_ns) \
                        or disrupted(trace, e.host, e.time_ns, e.time_ns + deadline_ns):
                    r.skipped += 1
                    continue
                before = last_before(by_ref.get(m, []), e.time_ns)
                if before is None or before.lost or any(
                        x.ref == m and (x.cycle == e.cycle if local else abs(x.time_ns - e.time_ns) <= deadline_ns)
                        for x in lost_events):
                    r.skipped += 1  # a lost member does not react (its slave takes no commands)
                    continue
                r.checked += 1
                # remotely: from when the origin's bad status was on the wire (seen by the soak's own
                # subscriber, through the same router) plus the reacting host's own stall
                on_wire = next((x.t_ns for x in by_ref.get(e.ref, ()) if x.time_ns >= e.time_ns and _bad(x)), e.time_ns)
                publish_ms.append(max(0, on_wire - e.time_ns) / 1e6)
                allowed = deadline_ns if local else \
                    max(0, on_wire - e.time_ns) + deadline_ns + stall_ns(trace, host, e.time_ns)
                seen = [x for x in reflexes.get(m, ()) if
                        (x.cycle == e.cycle if local else e.time_ns - deadline_ns <= x.time_ns <= e.time_ns + allowed)]
                if seen and not local:
                    late = min(x.time_ns - e.time_ns for x in seen)
                    remote_ms.append(late / 1e6)
                    if late > deadline_ns:
                        r.figures["late_by_stall"] = r.figures.get("late_by_stall", 0) + 1  # or a late publish
                if not seen:
                    later = [x.time_ns - e.time_ns for x in reflexes.get(m, ()) if x.time_ns >= e.time_ns]
                    add(r, "no reflex in the same cycle" if local else f"no reflex within {remote_deadline_ms:g} ms "
                        "and the host's stall", allowed_ms=round(allowed / 1e6, 3), group=group, origin=e.ref, origin_kind=e.kind, origin_cycle=e.cycle, origin_time_ns=e.time_ns,
                        member=m, next_reflex_after_ms=round(min(later) / 1e6, 3) if later else None)
    for name, values in (("remote_reflex_ms", remote_ms), ("origin_on_wire_ms", publish_ms)):
        if values:
            v = sorted(values)
            r.figures[name] = {"n": len(v), "p50": round(v[len(v) // 2], 3), "max": round(v[-1], 3)}
    return r


# ---- 4. status seq rising per agent instance ------------------------------------------------------


def seq_rising(trace: Trace) -> Result:
    """Each drive's status ``seq`` rises from one put to the next as received (a new agent
    instance after a kill numbers anew); each agent instance's status ``seq`` rises likewise."""
    r = Result("status_seq_rising")
    last: dict[str, Status] = {}
    for s in sorted(trace.statuses, key=lambda s: s.t_ns):
        p = last.get(s.ref)
        last[s.ref] = s
        if p is None:
            continue
        r.checked += 1
        if s.seq <= p.seq and not restarted_between(trace, s.host, p.t_ns, s.t_ns):
            add(r, "drive status seq not rising", drive=s.ref, seq=s.seq, previous_seq=p.seq, time_ns=s.time_ns)
    last_agent: dict[tuple[str, str], int] = {}
    for a in sorted(trace.agents, key=lambda a: a.t_ns):
        k = (a.host, a.instance)
        if k in last_agent:
            r.checked += 1
            if a.seq <= last_agent[k]:
                add(r, "agent status seq not rising", host=a.host, instance=a.instance, seq=a.seq,
                    previous_seq=last_agent[k])
        last_agent[k] = a.seq
    return r


# ---- 5. malformed commands refused, nothing changed -----------------------------------------------

#: Status fields a refused command must leave as they were.
UNCHANGED_FIELDS = ("goal", "mode", "halt", "lease_holder")
#: Event kinds that change a drive for reasons of their own (a concurrent command, a reflex, ...).
_OTHER_CAUSES = frozenset({"reflex", "lost", "found", "fault", "lease", "conflict"})


def malformed_refused(trace: Trace) -> Result:
    """A malformed command is refused by every addressed agent (``reply_err``, or ``rejected`` per
    drive), is acted on nowhere (no event carries its request id but a refusal) and leaves the
    addressed drives' goal, mode, halt and lease as they were (judged when nothing else touched
    them meanwhile)."""
    r = Result("malformed_refused")
    for c in trace.commands:
        if not c.malformed:
            continue
        hosts = sorted({ref.split("/")[0] for ref in c.addressed})
        for host in hosts:
            if disrupted(trace, host, c.sent_ns, c.done_ns, QUERY_SETTLE_NS):
                r.skipped += 1
                continue
            r.checked += 1
            refs = [x for x in c.addressed if x.split("/")[0] == host]
            errs = [e for e in c.errors if e.host == host]
            oks = [x for x in c.replies if x.host == host]
            refused = len(errs) == 1 and not oks or not errs and sorted(x.ref for x in oks) == sorted(refs) and all(
                x.outcome == "rejected" and x.reason for x in oks)
            if not refused:
                add(r, "not refused", request_id=c.request_id, flaw=c.malformed, host=host,
                    errors=[e.text for e in errs], outcomes={x.ref: x.outcome for x in oks})
        # the audit trail's entry (kind command) and a rejected outcome are the refusal itself
        acted = [e for e in trace.events if c.request_id and e.request_id == c.request_id and e.kind != "command"
                 and not (e.kind == "outcome" and " rejected" in e.detail)]
        if acted:
            add(r, "acted on", request_id=c.request_id, flaw=c.malformed,
                events=[(e.ref, e.kind, e.detail) for e in acted[:EXAMPLES]])
        for ref, b in c.before.items():
            a = c.after.get(ref)
            if a is None:
                continue
            other_events = any(e.ref == ref and b.time_ns < e.time_ns <= a.time_ns
                               and (e.kind in _OTHER_CAUSES or e.request_id not in ("", c.request_id))
                               for e in trace.events)
            other_commands = any(x is not c and ref in x.addressed and x.sent_ns <= a.t_ns and x.done_ns >= b.t_ns
                                 for x in trace.commands)
            if other_events or other_commands or disrupted(trace, ref.split("/")[0], c.sent_ns, c.done_ns, QUERY_SETTLE_NS):
                r.skipped += 1
                continue
            r.checked += 1
            changed = {f: (getattr(b, f), getattr(a, f)) for f in UNCHANGED_FIELDS if getattr(b, f) != getattr(a, f)}
            if changed:
                add(r, "changed by a refused command", request_id=c.request_id, flaw=c.malformed, drive=ref,
                    changed=changed)
    return r


# ---- 6. targets on the wire within limits: bench/chaos/limits.py ----------------------------------


def wire_limits(trace: Trace) -> Result:
    """Every target written while the drive follows it is within the axis's limits (flight recordings)."""
    return check_limits(trace)


# ---- 7. no process dying that the schedule did not kill -------------------------------------------


def no_unexpected_death(trace: Trace) -> Result:
    r = Result("no_unexpected_death")
    r.checked = trace.processes
    for text in trace.unexpected_exits:
        add(r, "process exited unasked", output=text[-2000:])
    return r


# ---- 8. every drive down after the final disable --------------------------------------------------


def final_down(trace: Trace) -> Result:
    """After the final disable every drive answers, is not lost, is in a state without power for
    motion (switch on disabled, not ready, or fault) and has no goal above it (``disabled``, or
    ``quick_stop`` from a group reflex after the disable, which keeps a disabled drive down)."""
    r = Result("final_disable_down")
    for ref in trace.refs():
        r.checked += 1
        s = trace.final.get(ref)
        if s is None:
            add(r, "no status after the final disable", drive=ref)
        elif s.lost or s.state not in DOWN_STATES or s.goal not in DOWN_GOALS:
            add(r, "not down after the final disable", drive=ref, state=s.state, lost=s.lost, goal=s.goal)
    return r


# ---- 9. a lost drive's state is unknown -----------------------------------------------------------


def _summarised(r: Result, what: str, cases: Iterable[Status]) -> None:
    """One violation per drive with its count and first examples (there may be hundreds)."""
    per: dict[str, list[Status]] = defaultdict(list)
    for s in cases:
        per[s.ref].append(s)
    for ref, ss in sorted(per.items()):
        add(r, what, drive=ref, count=len(ss),
            examples=[{"seq": s.seq, "time_ns": s.time_ns, "state": s.state, "lost": s.lost} for s in ss[:EXAMPLES]])


def lost_is_unknown(trace: Trace) -> Result:
    """A status with ``lost=true`` has state ``unknown`` (its last known state may go elsewhere)."""
    r = Result("lost_state_unknown")
    lost = [s for s in trace.statuses if s.lost]
    r.checked = len(lost)
    _summarised(r, "lost drive reported with a state", (s for s in lost if s.state != "unknown"))
    return r


# ---- 10. a faulted slave is never reported enabled and healthy ------------------------------------


def _faulted_windows(trace: Trace, by_ref: dict[str, list[Status]]) -> list[tuple[str, int, int, Injection]]:
    """(drive, from, to, injection): when its slave was faulted, unplugged or without valid process
    data. A fault lasts until a fault_reset done for the drive or a power cycle (unplugged and
    plugged back); an unplug until plugged again; a
    WKC fault until it is off and the drive was next seen healthy and down (or an enable sent).
    With the drives simulated in the agent's process, any of them ends when that agent is killed.
    A fault is judged from its next cycle on (the statusword says it). An unplug or a WKC fault
    is judged from the drive's first ``lost`` status after it: the working counter is one sum
    for the segment, so until the agent finds the slave lost (its AL state, or its SM watchdog
    tripping in 100 ms) its drives are what they last were; the promise judged is that a lost
    drive is never found again on data that is not valid ("found means valid process data")."""
    resets: dict[str, list[int]] = defaultdict(list)
    enables: dict[str, list[int]] = defaultdict(list)
    for c in trace.commands:
        for x in c.replies:
            if c.op == "fault_reset" and x.outcome == "done":
                resets[x.ref].append(x.t_ns)
        if c.op == "enable" and not c.malformed:
            for ref in c.addressed:
                enables[ref].append(c.sent_ns)
    out = []
    for inj in trace.injections:
        if not inj.ok or inj.kind not in ("fault", "unplug", "wkc_fault"):
            continue
        refs = [inj.target] if "/" in inj.target else [f"{inj.host}/{a}" for a in trace.hosts.get(inj.host, ())]
        for ref in refs:
            t0 = inj.applied_ns + INJECTION_MARGIN_NS
            if inj.kind == "fault":
                # a reset, or a power cycle: unplugged and plugged back (the slave restarts in INIT)
                plugs = [k.end_ns for k in trace.injections if k.kind == "unplug" and k.ok and k.target == ref
                         and k.start_ns >= inj.applied_ns]
                t1 = min([*(t for t in resets.get(ref, ()) if t > inj.applied_ns), *plugs, trace.final_ns or 2**63])
            elif inj.kind == "unplug":
                t1 = inj.end_ns
            else:
                after = [s.time_ns for s in by_ref.get(ref, ()) if s.time_ns > inj.end_ns and not s.lost and s.state != UP]
                t1 = min([*after[:1], *(t for t in enables.get(ref, ()) if t > inj.end_ns), trace.final_ns or 2**63])
            if trace.sim_in_agent:
                t1 = min([t1, *(k.start_ns for k in trace.injections
                                if k.kind == "agent_restart" and k.host == inj.host and k.start_ns > inj.start_ns)])
            if inj.kind != "fault":
                lost = [s.time_ns for s in by_ref.get(ref, ()) if s.lost and s.time_ns >= inj.applied_ns]
                if not lost:
                    continue  # never lost in it: no "found" to judge
                t0 = max(t0, lost[0])
            out.append((ref, t0, t1, inj))
    return out


def no_stale_found(trace: Trace) -> Result:
    """A drive whose slave is faulted, unplugged or WKC-faulted is never reported
    ``operation_enabled`` with ``lost=false``."""
    r = Result("faulted_never_enabled")
    by_ref = statuses_by_ref(trace)
    bad: dict[tuple[str, int, int], Status] = {}  # overlapping windows name a status once
    for ref, t0, t1, _inj in _faulted_windows(trace, by_ref):
        r.checked += 1
        bad.update(((s.ref, s.seq, s.time_ns), s) for s in by_ref.get(ref, ())
                   if t0 <= s.time_ns < t1 and s.state == UP and not s.lost)
    _summarised(r, "reported operation_enabled, lost=false while its slave was faulted",
                sorted(bad.values(), key=lambda s: s.time_ns))
    return r


#: Every monitor, in report order: name -> (the promise in words, the function).
MONITORS: dict[str, tuple[str, Monitor]] = {
    "one_terminal_reply": ("exactly one terminal reply per addressed drive", one_reply),
    "no_unrequested_enable": ("a drive seen operation_enabled had an accepted enable since it last went down",
                              no_unrequested_enable),
    "group_reflex": ("a group member's fault or loss makes the others react: same cycle locally, within "
                     f"{REFLEX_REMOTE_DEADLINE_MS:g} ms on other hosts", group_reflex),
    "status_seq_rising": ("status seq rising per drive and agent instance", seq_rising),
    "malformed_refused": ("malformed commands refused, with nothing changed", malformed_refused),
    "wire_limits": ("every target on the wire within the velocity and acceleration limits", wire_limits),
    "no_unexpected_death": ("no process dies that the schedule did not kill", no_unexpected_death),
    "final_disable_down": ("every drive down after a final disable", final_down),
    "lost_state_unknown": ("a drive reported lost=true never has a state other than unknown", lost_is_unknown),
    "faulted_never_enabled": ("a drive whose slave is faulted/WKC-faulted is never reported operation_enabled "
                              "with lost=false", no_stale_found),
}


def run_monitors(trace: Trace, only: Iterable[str] | None = None) -> dict[str, Result]:
    """Every monitor (or those named in ``only``) over ``trace``."""
    names = list(MONITORS) if only is None else list(only)
    return {n: MONITORS[n][1](trace) for n in names}

