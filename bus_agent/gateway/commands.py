"""The gateway's command path: command queries in, drive and agent commands to the cycle, replies out.

:class:`Commands` is the part of :class:`bus_agent.gateway.gateway.Gateway` that owns every piece of
mutable command state (pending requests, the request-id memory, the outcomes waiting for
their replies) and the ``gw-command`` thread, which runs the :class:`~bus_agent.gateway.handoff.Inbox`
(Zenoh callbacks and the cycle only enqueue) and the timers (lease expiry, the host-name
conflict, outcomes overdue).

One query: find which of this host's axes the query key intersects (none: not for us, finish
silently); decode and validate the payload (:func:`~bus_agent.gateway.requests.parse_command`);
any problem -> ``reply_err`` with a text naming it, nothing changes. Otherwise one DriveCommand
for all the addressed axes (the cycle applies it in one cycle) and, as the outcomes arrive, one
``CommandReply`` per axis; the query is finished when every axis has answered. A repeated
request id attaches to the first request's outcomes. The reply path is latency-critical: no
thread hop beyond the one to ``gw-command``, no lock.
"""

from __future__ import annotations

import collections
import functools
import logging
import queue
import threading
import time
from typing import Any, Sequence

import zenoh

from bus_agent import hops
from bus_agent import runtime as rt
from bus_agent.cycle.realtime import name_thread, set_thread_fifo
from bus_agent.gateway.handoff import Feed, Inbox
from bus_agent.gateway.hostclaim import HostClaim
from bus_agent.gateway.peers import Peers
from bus_agent.gateway.requests import (LEASE_OPS, ParsedCommand, Request, RequestError, axes_in_key, finish,
                                        parse_command, reply_err, undeclare)
from bus_agent.gateway.settings import CycleLike, GatewaySettings
from schemas import keys
from schemas import messages as m

log = logging.getLogger("bus_agent.gateway.gateway")

#: Ops an agent refuses while another agent uses its host name: whatever raises power, clears a
#: fault, changes the mode or moves (the other agent may obey the same command); lowering ops
#: (disable, shutdown, quick_stop, halt, stop) and leases still work.
CONFLICT_REFUSED_OPS = frozenset({"enable", "switch_on", "fault_reset", "set_mode", "nmt", "move", "jog", "home"})
#: Request-id memory: size and time to live of finished requests.
DEDUP_SIZE = 1024
DEDUP_TTL_S = 300.0


class Commands:
    """Command queries -> the cycle -> one reply per addressed axis.

    Given: the settings, the cycle (``submit``), the :class:`~bus_agent.gateway.handoff.Feed`
    (audit and outcome events, drive states), the :class:`~bus_agent.gateway.handoff.Inbox` it
    runs, the :class:`~bus_agent.gateway.peers.Peers` (leases), the
    :class:`~bus_agent.gateway.hostclaim.HostClaim` (the conflict that refuses ops) and the
    gateway's ``stop``."""

    def __init__(self, settings: GatewaySettings, cycle: CycleLike, feed: Feed, inbox: Inbox, peers: Peers,
                 claim: HostClaim, stop: threading.Event) -> None:
        self.s = settings
        self.host = settings.host
        self.axes = tuple(settings.axes)
        self._cycle = cycle
        self._feed = feed
        self._inbox = inbox
        self._peers = peers
        self._leases = peers.leases
        self._claim = claim
        self._stop = stop
        self._cycle_outcomes: collections.deque[tuple[Request, rt.Outcome]] = collections.deque()
        self._drain_queued = False   # a drain of _cycle_outcomes is queued on gw-command
        self._requests: collections.OrderedDict[str, Request] = collections.OrderedDict()
        self._pending: set[Request] = set()
        self._accepting = False
        self._queryables: list[Any] = []
        #: 'op.outcome' -> replies given (published in AgentStatus.commands, for metrics).
        self.counts: dict[str, int] = {}

    # ---- declarations ---------------------------------------------------------------------

    def declare(self, session: zenoh.Session) -> None:
        """Start accepting: declare the command queryables of the drives and of the agent."""
        self._accepting = True
        enqueue = self._inbox.put
        # Authenticated keys always; the unauthenticated ones (the v1 contract's) only without --pki.
        for principal in ("*",) if self.s.secure else ("*", None):
            self._queryables.append(session.declare_queryable(
                keys.drive_cmd(self.host, "*", "*", principal), self.on_drive_query))
            self._queryables.append(session.declare_queryable(
                keys.agent_cmd(self.host, "*", principal), lambda q: enqueue((self._on_agent_cmd, (q,)))))

    def stop_accepting(self) -> None:
        """Refuse new commands and undeclare their queryables (accepted ones still get outcomes)."""
        self._accepting = False
        for q in self._queryables:
            undeclare(q)
        self._queryables.clear()

    def fail_pending(self) -> None:
        """Answer every axis still waiting with ``failed`` (the agent stopped first)."""
        for req in list(self._pending):
            for axis in req.axes:
                if axis not in req.replies:
                    req.add(*self._reply(req, rt.Outcome(axis, "failed", reason="agent stopped before the outcome")))
        self._pending.clear()

    def request(self, request_id: str) -> Request | None:
        """The request remembered under ``request_id`` (pending or finished), or None."""
        return self._requests.get(request_id)

    # ---- the command thread ---------------------------------------------------------------

    def run(self) -> None:
        """The ``gw-command`` thread: inbox items in order, timers after each, until ``stop``."""
        name_thread("gw-command")
        set_thread_fifo(self.s.rt_priority, f"gw-command of {self.host}")
        inbox = self._inbox
        idle = inbox.idle
        while True:
            timeout = self._next_timer_s() - time.monotonic()
            try:
                fn, args = inbox.get(timeout=max(0.001, timeout))
            except queue.Empty:
                fn, args = None, ()
            if self._stop.is_set():
                break
            if fn is not None:
                idle.clear()
            try:
                if fn is not None:
                    fn(*args)
                self._timers(time.monotonic())
            except Exception:
                log.exception("gateway %s: command thread", self.host)
            if inbox.empty():
                idle.set()
                if not inbox.empty():  # queued between the test and the set: still busy
                    idle.clear()

    def _next_timer_s(self) -> float:
        t = time.monotonic() + 0.2
        nxt = self._leases.next_expiry_s()
        if nxt is not None:
            t = min(t, nxt)
        return t

    def _timers(self, now: float) -> None:
        self._claim.tick(now)
        self._peers.tick(now)
        for req in [r for r in self._pending if now >= r.deadline_s]:
            for axis in req.axes:
                if axis not in req.replies:
                    self._outcome(req, rt.Outcome(axis, "timeout", reason="no outcome from the cycle in time"))

    # ---- queries --------------------------------------------------------------------------

    def on_drive_query(self, query: zenoh.Query) -> None:
        """Zenoh's callback for a drive command: onto ``gw-command``, marked busy at once."""
        hops.stamp("gw.query")
        self._inbox.work((self._on_drive_cmd, (query,)))

    def _on_drive_cmd(self, query: zenoh.Query) -> None:
        hops.stamp("gw.command")
        key = str(query.key_expr)
        if not (axes_in_key(key, self.host, self.axes) or axes_in_key(key, self.host, self.axes, principal="*")):
            finish(query)  # a selector for other drives or hosts: not ours to answer
            return
        self._command(query, key, agent=False)

    def _on_agent_cmd(self, query: zenoh.Query) -> None:
        self._command(query, str(query.key_expr), agent=True)

    def _requester(self, key: str, request: m.CommandRequest | None) -> str:
        """Who is asking, for the audit trail: the requester :func:`requester` decided for a parsed
        request (the key's authenticated principal, else the declared ``supervisor``), followed
        by ``for <user>`` when it sends for someone (``on_behalf_of``, a gateway's claim about its
        user); for a refused one, the key's principal if it names one; '' -> anonymous."""
        if request is not None:
            who = request.supervisor or "anonymous"
            return f"{who} for {request.on_behalf_of}" if request.on_behalf_of else who
        try:
            return keys.command_principal(key) or "anonymous"
        except keys.InvalidKey:
            return "anonymous"

    def audit(self, key: str, request: m.CommandRequest | None, axes: Sequence[str], requester: str,
               outcome: str, reason: str = "") -> None:
        """Log (INFO) and publish (event kind ``command``) one accepted or refused command."""
        rid = request.request_id if request is not None else ""
        op = request.op if request is not None else key.split("/cmd/", 1)[-1].split("/", 1)[0]
        log.info("agent %s: command %s op %s axes %s from %s: %s%s", self.host, rid or "-", op,
                 ",".join(axes) or "-", requester, outcome, f": {reason}" if reason else "")
        detail = f"{op} {outcome} from {requester}" + (f": {reason}" if reason else "")
        # One event per addressed drive, queued together with one wake-up of the publish thread.
        self._feed.emit_all(rt.CycleEvent(axis, "command", detail=detail, request_id=rid, requester=requester)
                            for axis in axes or ("",))

    def _key_axes(self, key: str, agent: bool) -> tuple[str, ...]:
        """The axes a refused query's key addresses (for its audit event)."""
        return () if agent else (axes_in_key(key, self.host, self.axes)
                                 or axes_in_key(key, self.host, self.axes, principal="*"))

    def _command(self, query: zenoh.Query, key: str, agent: bool) -> None:
        if not self._accepting:
            self.audit(key, None, self._key_axes(key, agent), self._requester(key, None), "refused", "shutting down")
            reply_err(query, f"agent {self.host} is shutting down: no new commands")
            return
        try:
            parsed = parse_command(query.payload, key, self.host, self.axes, agent=agent, secure=self.s.secure)
        except RequestError as exc:
            self.audit(key, None, self._key_axes(key, agent), self._requester(key, None), "refused", str(exc))
            reply_err(query, f"{self.host}: {exc}")
            return
        hops.stamp("gw.parsed")
        requester = self._requester(key, parsed.request)
        now = time.monotonic()
        self._forget_old(now)
        rid = parsed.request.request_id
        first = self._requests.get(rid)
        if first is not None:
            if not first.same_command(parsed):
                reason = (f"request_id {rid!r} was already used for op {first.op} on "
                          f"{', '.join(first.axes) or 'the agent'}: use a new request_id")
                self.audit(key, parsed.request, parsed.axes, requester, "refused", reason)
                reply_err(query, f"{self.host}: {reason}")
                return
            first.attach(query)  # the first outcome(s), now or when they come: no second action
            return
        self.audit(key, parsed.request, parsed.axes, requester, "accepted")
        req = Request(parsed, self.host, now)
        req.requester = requester
        self._requests[rid] = req
        self._pending.add(req)
        req.attach(query)
        if parsed.request.op in LEASE_OPS:
            self._peers.lease_command(req, parsed, self._outcome)
        else:
            self._submit(req, parsed)

    def _submit(self, req: Request, parsed: ParsedCommand) -> None:
        r = parsed.request
        if self._claim.conflict_text and r.op in CONFLICT_REFUSED_OPS:
            # Another agent may obey the same command: nothing that raises power or clears a fault.
            conflict = self._claim.conflict_text
            for axis in parsed.axes or ("",):
                self._outcome(req, rt.Outcome(axis, "rejected", state=self._feed.state(axis), reason=conflict))
            return
        on_outcome = functools.partial(self._outcome_from_cycle, req)
        if not parsed.axes:  # agent command
            axes = [parsed.args["axis"]] if parsed.args.get("axis") else self.axes
            blocked = self._peers.blocking(r.supervisor, axes)
            if blocked:
                self._outcome(req, rt.Outcome("", "busy", reason=f"leased: {blocked}"))
                return
            cmd: rt.DriveCommand | rt.AgentCommand = rt.AgentCommand(
                request_id=r.request_id, op=r.op, args=dict(parsed.args), timeout_s=r.timeout_s,
                supervisor=r.supervisor, received_ns=req.received_ns, on_outcome=on_outcome)
            if not self._cycle.submit(cmd):
                self._outcome(req, rt.Outcome("", "busy", reason=self._refused()))
            return
        free = []
        for axis in parsed.axes:
            holder = self._leases.check(axis, r.supervisor)
            if holder:
                self._outcome(req, rt.Outcome(axis, "busy", state=self._feed.state(axis),
                                              reason=f"drive {self.host}/{axis} is leased by {holder}"))
            else:
                free.append(axis)
        if not free:
            return
        cmd = rt.DriveCommand(request_id=r.request_id, op=r.op, axes=tuple(free), args=dict(parsed.args),
                              timeout_s=r.timeout_s, supervisor=r.supervisor, received_ns=req.received_ns,
                              on_outcome=on_outcome)
        hops.stamp("gw.submit")
        accepted = self._cycle.submit(cmd)
        hops.stamp("gw.submitted")
        if not accepted:
            reason = self._refused()
            for axis in free:
                self._outcome(req, rt.Outcome(axis, "busy", state=self._feed.state(axis), reason=reason))

    def _refused(self) -> str:
        """Why ``cycle.submit`` said no."""
        state = getattr(self._cycle, "state", "running")
        if state != "running":
            return f"agent {self.host} is {state}: command not taken"
        return "command inbox full: retry"

    def _outcome_from_cycle(self, req: Request, outcome: rt.Outcome) -> None:
        """Called from the cycle thread (or the bridge's reader): enqueue only. (The cycle publishes
        its own outcome event.) Outcomes gather in one deque and every put is a drain of all of
        them, so one cycle's outcomes are answered in one go on ``gw-command``: the publish pass,
        which waits while that thread is busy, cannot slip in between two replies of a batch."""
        self._cycle_outcomes.append((req, outcome))
        if not self._drain_queued:  # one drain for a batch (a cycle's outcomes), not one per axis
            self._drain_queued = True
            self._inbox.work((self._drain_outcomes, ()))

    def _drain_outcomes(self) -> None:
        hops.stamp("gw.drain")
        self._drain_queued = False  # before draining: an outcome appended from now on queues a drain
        outcomes = self._cycle_outcomes
        while outcomes:
            req, outcome = outcomes.popleft()
            self._outcome(req, outcome, False)

    def _outcome(self, req: Request, outcome: rt.Outcome, event: bool = True) -> None:
        """Record one axis' terminal outcome and answer the waiting queries. ``event``: also
        publish an ``outcome`` event (for outcomes the gateway decided itself)."""
        if outcome.axis in req.replies or outcome.axis not in req.axes:
            return
        reply, payload = self._reply(req, outcome)
        req.add(reply, payload)
        if event and outcome.axis:
            detail = f"{req.op} {reply.outcome}" + (f": {reply.reason}" if reply.reason else "")
            self._feed.emit(rt.CycleEvent(outcome.axis, "outcome", detail=detail, to_state=reply.state,
                                          error_code=reply.error_code, request_id=req.request_id))
        if req.done:
            self._pending.discard(req)
            log.info("agent %s: command %s op %s from %s finished: %s", self.host, req.request_id, req.op,
                     req.requester, ", ".join(f"{a or 'agent'}={r.outcome}" for a, r in sorted(req.replies.items())))

    def _reply(self, req: Request, o: rt.Outcome) -> tuple[m.CommandReply, bytes]:
        """The reply for outcome ``o`` of ``req`` and its encoding (validated once)."""
        outcome = o.outcome if o.outcome in m.OUTCOMES else "failed"
        key = f"{req.op}.{outcome}"
        self.counts[key] = self.counts.get(key, 0) + 1
        fields = {
            "request_id": req.request_id, "host": self.host, "op": req.op, "outcome": outcome, "axis": o.axis,
            "state": o.state if o.state in m.DRIVE_STATES else "unknown", "error_code": o.error_code & 0xFFFF,
            "reason": o.reason[:400], "elapsed_s": o.elapsed_s or (time.monotonic_ns() - req.received_ns) / 1e9,
            "cycles": o.cycles, "lease_holder": self._leases.holder(o.axis) if o.axis else "",
            "duration_s": min(max(o.duration_s, 0.0), 1e6),
        }
        try:
            return m.encode_new(m.CommandReply, fields)
        except m.SchemaError as exc:  # still one terminal answer for the axis: failed, saying why
            log.error("agent %s: reply to %s for %r not encodable: %s", self.host, req.request_id, o.axis, exc)
            return m.encode_new(m.CommandReply, {**fields, "outcome": "failed", "cycles": 0, "elapsed_s": 0.0,
                                                 "reason": f"reply not encodable: {exc}"[:400]})

    def _forget_old(self, now: float) -> None:
        while self._requests:
            rid, req = next(iter(self._requests.items()))
            if len(self._requests) > DEDUP_SIZE or (req.done and now - req.created_s > DEDUP_TTL_S):
                self._requests.popitem(last=False)
            else:
                break
