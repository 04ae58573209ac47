"""The gateway: the agent's Zenoh side (status publishers, command queryables, liveliness, leases).

It never blocks the cycle. The cycle hands over one :class:`~bus_agent.runtime.CycleSnapshot`
per cycle through :meth:`Gateway.on_snapshot` (an attribute store, a deque extend and an event
set) and one :class:`~bus_agent.runtime.Outcome` per addressed axis through each command's
``on_outcome`` (a queue put). Everything else runs on the gateway's two threads:

- ``gw-publish`` turns snapshots into ``DriveStatus`` puts (on change of a discrete field,
  within one cycle; motion fields at most every ``motion_period_s``; everything every
  ``heartbeat_s``), ``Event`` puts (cycle events and command outcomes) and ``AgentStatus``;
- ``gw-command`` owns every piece of mutable command state (pending requests, the request-id
  memory, the lease table, remote group members). Zenoh callbacks only enqueue to it.

Command path (one query): find which of this host's axes the query key intersects (none: not
for us, finish silently); decode and validate the payload (``schemas.messages``); any problem
-> ``reply_err`` with a text naming it, nothing changes. Otherwise one DriveCommand for all the
addressed axes (the cycle applies it in one cycle) and, as the outcomes arrive, one
``CommandReply`` per axis on ``drives/@v1/<host>/drive/<axis>/cmd/<op>``; the query is finished
when every axis has answered. A repeated request id attaches to the first request's outcomes.
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
import time
from typing import Any, Callable, Iterable, Sequence

import zenoh

from bus_agent import hops
from bus_agent import runtime as rt
from bus_agent.cycle.realtime import name_thread, set_thread_fifo
from bus_agent.gateway.base import (AGENT_SUPERVISOR, BAD_STATES, CHANGE_FIELDS, CONFLICT_REFUSED_OPS, DEDUP_SIZE,
                                    DEDUP_TTL_S, LEASE_REACTION_OPS, MOTION_FIELDS, CycleLike,
                                    GatewaySettings)
from bus_agent.gateway.hostclaim import ClaimLink, check_host_free
from bus_agent.gateway.peers import PeersMixin
from bus_agent.gateway.publisher import PublisherMixin
from bus_agent.gateway.requests import (LEASE_OPS, MSGPACK, RECORDING_QUEUE, RECORDING_TIMEOUT_S, TEXT, ParsedCommand, Request, RequestError,
                                        axes_in_key, finish, key_expr, parse_command, recording_message, reply_err, requester)
from schemas import keys
from schemas import messages as m

__all__ = ["Gateway", "GatewaySettings", "CycleLike", "RequestError", "ParsedCommand", "axes_in_key", "parse_command",
           "requester", "recording_message", "CHANGE_FIELDS", "MOTION_FIELDS", "BAD_STATES", "LEASE_OPS",
           "LEASE_REACTION_OPS", "CONFLICT_REFUSED_OPS", "DEDUP_SIZE", "DEDUP_TTL_S", "AGENT_SUPERVISOR", "MSGPACK",
           "TEXT"]

log = logging.getLogger(__name__)


class Gateway(PublisherMixin, PeersMixin):
    """Zenoh I/O of one bus agent. ``start`` declares everything; ``stop_commands`` stops
accepting commands (shutdown begins); ``close`` publishes the last snapshot and undeclares.
    """

    # ---- called from the cycle thread: enqueue only --------------------------------------

    def on_snapshot(self, snap: rt.CycleSnapshot) -> None:
        """Snapshot sink of the cycle. Cycle-safe: no I/O, no locks held for long."""
        self._latest = snap
        if snap.events:
            self._events.extend((ev, snap.cycle, snap.time_ns) for ev in snap.events)
        self._wake.set()

    def on_events(self, items: Iterable[tuple[rt.CycleEvent, int, int]]) -> None:
        """Event sink of a cycle in another process (``bridge.CycleProxy.event_sink``): events
        with the cycle number and wall time of the snapshot they came in, in order."""
        self._events.extend(items)
        self._wake.set()

    # ---- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Check that the host name is free (:class:`~bus_agent.gateway.hostclaim.HostNameTaken`
        otherwise, nothing declared), then declare everything, commands last."""
        s = self.session
        enqueue = self._inbox.put
        own_status = keys.agent_status(self.host)
        on_own_status = lambda smp: enqueue((self._on_own_host_status, (smp,)))  # noqa: E731
        # The claim goes through a session the routers route for (hostclaim.claim_config): a
        # peer's own session does not reach another peer behind the same router.
        claim = None
        if self._claim_config is not None:
            self._claim = ClaimLink(self._claim_config, own_status, on_own_status)
            claim = self._claim.open()
        if self.s.check_host:
            try:
                if claim is not None:
                    check_host_free(claim, self.host, has_connect=True)
                else:  # a client open already waited for a router: check what the own session sees now
                    check_host_free(s, self.host, has_connect=self.s.has_connect and self._claim is None)
            except Exception:
                if self._claim is not None:
                    self._claim.close()
                raise
        # A cycle already running (behind the process bridge) has a snapshot: drive status goes
        # out in the first publish pass, before the agent status that lists the axes.
        self._latest = self._latest or getattr(self.cycle, "latest", None)
        for axis in self.axes:
            # BLOCK: a watcher must see every publication (seq without gaps); a slow subscriber
            # slows only this publishing thread, which coalesces to the latest snapshot, never the cycle.
            self._status_pubs[axis] = s.declare_publisher(keys.drive_status(self.host, axis), encoding=MSGPACK,
                                                          express=True,
                                                          congestion_control=zenoh.CongestionControl.BLOCK)
            self._event_pubs[axis] = s.declare_publisher(keys.drive_event(self.host, axis), encoding=MSGPACK,
                                                         congestion_control=zenoh.CongestionControl.BLOCK)
        self._agent_pub = s.declare_publisher(keys.agent_status(self.host), encoding=MSGPACK)
        self._other_decls.append(s.declare_queryable(
            keys.drive_status(self.host, "*"), lambda q: enqueue((self._on_status_query, (q,)))))
        self._other_decls.append(s.declare_queryable(
            keys.agent_status(self.host), lambda q: enqueue((self._on_agent_query, (q,)))))
        self._other_decls.append(s.liveliness().declare_subscriber(
            keys.ALL_SUPERVISORS, lambda smp: enqueue((self._on_supervisor_token, (smp,))), history=True))
        self._other_decls.append(s.declare_subscriber(own_status, on_own_status))
        # The group reflex's path: only the members' own status (not every drive of their hosts),
        # handled on zenoh's callback thread, not queued behind the command thread's work (see
        # PeersMixin._on_remote_status).
        for host, axis in sorted({(r.host, r.axis) for r in self._remotes}):
            self._other_decls.append(s.declare_subscriber(keys.drive_status(host, axis), self._on_remote_status))
        for host in sorted({r.host for r in self._remotes}):
            self._other_decls.append(s.liveliness().declare_subscriber(
                keys.alive(host), lambda smp: enqueue((self._on_remote_token, (smp,))), history=True))
        self._other_decls.append(s.declare_queryable(keys.agent_recording(self.host), self._on_recording_query))
        self._threads = [threading.Thread(target=self._publish_loop, name="gw-publish", daemon=True),
                         threading.Thread(target=self._command_loop, name="gw-command", daemon=True),
                         threading.Thread(target=self._recording_loop, name="gw-record", daemon=True)]
        for t in self._threads:
            t.start()
        if self._claim is not None and claim is None:
            self._threads.append(self._claim.retry(self._stop))
        if hasattr(self.cycle, "event_sink"):  # a cycle behind the process bridge forwards events apart
            self.cycle.event_sink = self.on_events
        self.cycle.snapshot_sink = self.on_snapshot
        # Commands last: by now status flows and the lease/group subscribers are in place.
        self._accepting = True
        # Authenticated keys always; the unauthenticated ones (the v1 contract's) only without --pki.
        for principal in ("*",) if self.s.secure else ("*", None):
            self._cmd_queryables.append(s.declare_queryable(
                keys.drive_cmd(self.host, "*", "*", principal), self._drive_cmd_callback))
            self._cmd_queryables.append(s.declare_queryable(
                keys.agent_cmd(self.host, "*", principal), lambda q: enqueue((self._on_agent_cmd, (q,)))))
        self._token = s.liveliness().declare_token(keys.alive(self.host))
        log.info("gateway %s: %d drive(s), %d remote group member(s)", self.host, len(self.axes), len(self._remotes))

    def stop_commands(self) -> None:
        """Stop taking new commands (queries already accepted still get their outcomes)."""
        self._accepting = False
        for q in self._cmd_queryables:
            _undeclare(q)
        self._cmd_queryables.clear()

    def close(self, timeout_s: float = 2.0) -> None:
        """Publish what the cycle last reported, answer what is pending, undeclare everything.
        Call after the cycle stopped. Idempotent."""
        self.stop_commands()
        if self._stop.is_set():
            return
        # Outcomes the cycle gave during its ordered stop are in the inbox: let them through.
        done = threading.Event()
        self._inbox.put((lambda: done.set(), ()))
        done.wait(timeout_s)
        self._stop.set()
        self._wake.set()
        self._inbox.put((lambda: None, ()))
        for t in self._threads:
            t.join(timeout_s)
        self.agent_state_override = "stopped"
        self._publish_once(final=True)
        for req in list(self._pending):
            for axis in req.axes:
                if axis not in req.replies:
                    req.add(*self._reply(req, rt.Outcome(axis, "failed", reason="agent stopped before the outcome")))
        self._pending.clear()
        for decl in self._other_decls:
            _undeclare(decl)
        self._other_decls.clear()
        if self._claim is not None:
            self._claim.close()
        if self._token is not None:
            _undeclare(self._token)
            self._token = None
        for pub in [*self._status_pubs.values(), *self._event_pubs.values(), self._agent_pub]:
            if pub is not None:
                _undeclare(pub)
        self._status_pubs.clear()
        self._event_pubs.clear()
        self._agent_pub = None

    # ---- command thread ---------------------------------------------------------------------

    def _command_loop(self) -> None:
        name_thread("gw-command")
        set_thread_fifo(self.s.rt_priority, f"gw-command of {self.host}")
        while True:
            timeout = self._next_timer_s() - time.monotonic()
            try:
                fn, args = self._inbox.get(timeout=max(0.001, timeout))
            except queue.Empty:
                fn, args = None, ()
            if self._stop.is_set():
                break
            if fn is not None:
                self._commands_idle.clear()
            try:
                if fn is not None:
                    fn(*args)
                self._timers(time.monotonic())
            except Exception:
                log.exception("gateway %s: command thread", self.host)
            if self._inbox.empty():
                self._commands_idle.set()
                if not self._inbox.empty():  # queued between the test and the set: still busy
                    self._commands_idle.clear()

    def _next_timer_s(self) -> float:
        t = time.monotonic() + 0.2
        nxt = self.leases.next_expiry_s()
        if nxt is not None:
            t = min(t, nxt)
        return t

    def _timers(self, now: float) -> None:
        if self._conflicts.expire(now):
            self._conflict_changed()
        ended = self.leases.expire(now)
        if ended:
            self._leases_ended(ended)
        for req in [r for r in self._pending if now >= r.deadline_s]:
            for axis in req.axes:
                if axis not in req.replies:
                    self._outcome(req, rt.Outcome(axis, "timeout", reason="no outcome from the cycle in time"))

    def _on_status_query(self, query: zenoh.Query) -> None:
        with query:
            snap = self._latest
            if snap is None:
                return
            qke = query.key_expr
            holders = self._lease_holders
            for d in snap.drives:
                key = self._status_key(d.axis)
                if key_expr(key).intersects(qke):
                    seq = self._status_seq.get(d.axis, 0)
                    query.reply(key, self._status_encoded(snap, d, holders.get(d.axis, ""), seq)[1],
                                encoding=MSGPACK)

    def _status_key(self, axis: str) -> str:
        """The status key of ``axis`` (built and checked once: every status get asks for all)."""
        key = self._status_keys.get(axis)
        if key is None:
            key = self._status_keys[axis] = keys.drive_status(self.host, axis)
        return key

    def _on_agent_query(self, query: zenoh.Query) -> None:
        with query:
            query.reply(keys.agent_status(self.host), m.encode(self._agent_status(self._agent_seq)),
                        encoding=MSGPACK)

    def _on_recording_query(self, query: zenoh.Query) -> None:
        try:
            self._recordings.put_nowait(query)
        except queue.Full:
            reply_err(query, f"{self.host}: flight recorder busy: {RECORDING_QUEUE} requests are waiting")

    def _recording_loop(self) -> None:
        while not self._stop.is_set():
            try:
                query = self._recordings.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._serve_recording(query)
            except Exception as exc:  # keep serving; the querier gets the reason
                log.exception("gateway %s: recording query failed", self.host)
                reply_err(query, f"{self.host}: recording failed: {exc}")

    def _serve_recording(self, query: zenoh.Query) -> None:
        try:
            payload: Any = query.payload
            req = m.RecordingRequest() if payload is None else m.decode(payload, m.RecordingRequest)
        except m.SchemaError as exc:
            reply_err(query, f"{self.host}: invalid recording_request: {exc}")
            return
        fetch = getattr(self.cycle, "recording", None)
        if fetch is None:
            reply_err(query, f"{self.host}: this agent has no flight recorder")
            return
        try:
            data = fetch(req.what, req.last_s, RECORDING_TIMEOUT_S)
        except LookupError as exc:
            reply_err(query, f"{self.host}: {exc}")
            return
        query.reply(keys.agent_recording(self.host), m.encode(recording_message(self.host, data)), encoding=MSGPACK)
        finish(query)

    def _drive_cmd_callback(self, query: zenoh.Query) -> None:
        hops.stamp("gw.query")
        self._command_work((self._on_drive_cmd, (query,)))

    def _command_work(self, item: tuple[Callable[..., None], tuple]) -> None:
        """Queue work that answers a querier (a command, a batch of outcomes) on ``gw-command``,
        marking that thread busy at once: the publish thread, woken by the same bridge message
        or status change, waits before its next put instead of taking the GIL from the replies
        while ``gw-command`` is still waking up."""
        self._commands_idle.clear()
        self._inbox.put(item)

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

    def _audit(self, key: str, request: m.CommandRequest | None, axes: Sequence[str], requester: str,
               outcome: str, reason: str = "") -> None:
        """Log (INFO) and publish (event kind ``command``) one accepted or refused command."""
        rid = request.request_id if request is not None else ""
        op = request.op if request is not None else key.split("/cmd/", 1)[-1].split("/", 1)[0]
        log.info("agent %s: command %s op %s axes %s from %s: %s%s", self.host, rid or "-", op,
                 ",".join(axes) or "-", requester, outcome, f": {reason}" if reason else "")
        detail = f"{op} {outcome} from {requester}" + (f": {reason}" if reason else "")
        # One event per addressed drive, queued together with one wake-up of the publish thread.
        snap = self._latest
        cycle, now_ns = (snap.cycle if snap else 0), time.time_ns()
        self._events.extend((rt.CycleEvent(axis, "command", detail=detail, request_id=rid, requester=requester),
                             cycle, now_ns) for axis in axes or ("",))
        self._wake.set()

    def _key_axes(self, key: str, agent: bool) -> tuple[str, ...]:
        """The axes a refused query's key addresses (for its audit event)."""
        return () if agent else (axes_in_key(key, self.host, self.axes)
                                 or axes_in_key(key, self.host, self.axes, principal="*"))

    def _command(self, query: zenoh.Query, key: str, agent: bool) -> None:
        if not self._accepting:
            self._audit(key, None, self._key_axes(key, agent), self._requester(key, None), "refused", "shutting down")
            reply_err(query, f"agent {self.host} is shutting down: no new commands")
            return
        try:
            parsed = parse_command(query.payload, key, self.host, self.axes, agent=agent, secure=self.s.secure)
        except RequestError as exc:
            self._audit(key, None, self._key_axes(key, agent), self._requester(key, None), "refused", str(exc))
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
                self._audit(key, parsed.request, parsed.axes, requester, "refused", reason)
                reply_err(query, f"{self.host}: {reason}")
                return
            first.attach(query)  # the first outcome(s), now or when they come: no second action
            return
        self._audit(key, parsed.request, parsed.axes, requester, "accepted")
        req = Request(parsed, self.host, now)
        req.requester = requester
        self._requests[rid] = req
        self._pending.add(req)
        req.attach(query)
        if parsed.request.op in LEASE_OPS:
            self._lease_command(req, parsed)
        else:
            self._submit(req, parsed)

    def _submit(self, req: Request, parsed: ParsedCommand) -> None:
        r = parsed.request
        if self._conflict_text and r.op in CONFLICT_REFUSED_OPS:
            # Another agent may obey the same command: nothing that raises power or clears a fault.
            for axis in parsed.axes or ("",):
                self._outcome(req, rt.Outcome(axis, "rejected", state=self._state(axis), reason=self._conflict_text))
            return
        on_outcome = functools.partial(self._outcome_from_cycle, req)
        if not parsed.axes:  # agent command
            blocked = self._blocking_leases(r.supervisor, [parsed.args["axis"]] if parsed.args.get("axis") else self.axes)
            if blocked:
                self._outcome(req, rt.Outcome("", "busy", reason=f"leased: {blocked}"))
                return
            cmd: rt.DriveCommand | rt.AgentCommand = rt.AgentCommand(
                request_id=r.request_id, op=r.op, args=dict(parsed.args), timeout_s=r.timeout_s,
                supervisor=r.supervisor, received_ns=req.received_ns, on_outcome=on_outcome)
            if not self.cycle.submit(cmd):
                self._outcome(req, rt.Outcome("", "busy", reason=self._refused()))
            return
        free = []
        for axis in parsed.axes:
            holder = self.leases.check(axis, r.supervisor)
            if holder:
                self._outcome(req, rt.Outcome(axis, "busy", state=self._state(axis),
                                              reason=f"drive {self.host}/{axis} is leased by {holder}"))
            else:
                free.append(axis)
        if not free:
            return
        cmd = rt.DriveCommand(request_id=r.request_id, op=r.op, axes=tuple(free), args=dict(parsed.args),
                              timeout_s=r.timeout_s, supervisor=r.supervisor, received_ns=req.received_ns,
                              on_outcome=on_outcome)
        hops.stamp("gw.submit")
        accepted = self.cycle.submit(cmd)
        hops.stamp("gw.submitted")
        if not accepted:
            reason = self._refused()
            for axis in free:
                self._outcome(req, rt.Outcome(axis, "busy", state=self._state(axis), reason=reason))

    def _refused(self) -> str:
        """Why ``cycle.submit`` said no."""
        state = getattr(self.cycle, "state", "running")
        if state != "running":
            return f"agent {self.host} is {state}: command not taken"
        return "command inbox full: retry"

    def _blocking_leases(self, supervisor: str, axes: Iterable[str]) -> str:
        blocked = [f"{a} by {h}" for a in axes if (h := self.leases.check(a, supervisor))]
        return ", ".join(blocked)

    def _outcome_from_cycle(self, req: Request, outcome: rt.Outcome) -> None:
        """Called from the cycle thread (or the bridge's reader): enqueue only. (The cycle publishes
        its own outcome event.) Outcomes gather in one deque and every put is a drain of all of
        them, so one cycle's outcomes are answered in one go on ``gw-command``: the publish pass,
        which waits while that thread is busy, cannot slip in between two replies of a batch."""
        self._cycle_outcomes.append((req, outcome))
        if not self._drain_queued:  # one drain for a batch (a cycle's outcomes), not one per axis
            self._drain_queued = True
            self._command_work((self._drain_outcomes, ()))

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
            self._emit(rt.CycleEvent(outcome.axis, "outcome", detail=detail, to_state=reply.state,
                                     error_code=reply.error_code, request_id=req.request_id))
        if req.done:
            self._pending.discard(req)
            log.info("agent %s: command %s op %s from %s finished: %s", self.host, req.request_id, req.op,
                     req.requester, ", ".join(f"{a or 'agent'}={r.outcome}" for a, r in sorted(req.replies.items())))

    def _reply(self, req: Request, o: rt.Outcome) -> tuple[m.CommandReply, bytes]:
        """The reply for outcome ``o`` of ``req`` and its encoding (validated once)."""
        outcome = o.outcome if o.outcome in m.OUTCOMES else "failed"
        key = f"{req.op}.{outcome}"
        self._command_counts[key] = self._command_counts.get(key, 0) + 1
        fields = {
            "request_id": req.request_id, "host": self.host, "op": req.op, "outcome": outcome, "axis": o.axis,
            "state": o.state if o.state in m.DRIVE_STATES else "unknown", "error_code": o.error_code & 0xFFFF,
            "reason": o.reason[:400], "elapsed_s": o.elapsed_s or (time.monotonic_ns() - req.received_ns) / 1e9,
            "cycles": o.cycles, "lease_holder": self.leases.holder(o.axis) if o.axis else "",
            "duration_s": min(max(o.duration_s, 0.0), 1e6),
        }
        try:
            return m.encode_new(m.CommandReply, fields)
        except m.SchemaError as exc:  # still one terminal answer for the axis: failed, saying why
            log.error("agent %s: reply to %s for %r not encodable: %s", self.host, req.request_id, o.axis, exc)
            return m.encode_new(m.CommandReply, {**fields, "outcome": "failed", "cycles": 0, "elapsed_s": 0.0,
                                                 "reason": f"reply not encodable: {exc}"[:400]})

    def _emit(self, ev: rt.CycleEvent) -> None:
        snap = self._latest
        self._events.append((ev, snap.cycle if snap else 0, time.time_ns()))
        self._wake.set()

    def _state(self, axis: str) -> str:
        snap = self._latest
        if snap is not None:
            for d in snap.drives:
                if d.axis == axis:
                    return d.state
        return "unknown"

    def _forget_old(self, now: float) -> None:
        while self._requests:
            rid, req = next(iter(self._requests.items()))
            if len(self._requests) > DEDUP_SIZE or (req.done and now - req.created_s > DEDUP_TTL_S):
                self._requests.popitem(last=False)
            else:
                break


def _undeclare(decl: Any) -> None:
    try:
        decl.undeclare()
    except Exception as exc:
        log.debug("undeclare: %s", exc)
