"""Leases and the other hosts: lease commands and loss reactions, supervisors' liveliness, remote group members.

:class:`Peers` is the part of :class:`bus_agent.gateway.gateway.Gateway` that owns the lease table,
the published copy of its holders and the remote group members. Lease work runs on the
``gw-command`` thread (Zenoh callbacks only enqueue to it); a remote member's status is handled on
zenoh's callback thread. A lost lease runs the axis's configured reaction
(:data:`LEASE_REACTION_OPS`) as internal commands; a remote group member in fault or gone triggers
the group here (:meth:`Cycle.trigger_group`).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterable

import zenoh

from bus_agent import hops
from bus_agent import runtime as rt
from bus_agent.gateway.handoff import Feed
from bus_agent.gateway.leases import EndedLease, LeaseDecision, LeaseResult, LeaseTable
from bus_agent.gateway.requests import ParsedCommand, Request
from bus_agent.gateway.settings import BAD_STATES, CycleLike, GatewaySettings
from schemas import keys
from schemas import messages as m

log = logging.getLogger("bus_agent.gateway.gateway")

#: Lease loss reactions (``DrivePolicy.lease_reaction``) -> drive ops run one after the other.
LEASE_REACTION_OPS: dict[str, tuple[str, ...]] = {
    "quick_stop_then_disable": ("quick_stop", "disable"),
    "quick_stop": ("quick_stop",),
    "disable": ("disable",),
    "none": (),
}
#: Identity of commands the agent issues itself (lease loss reactions).
AGENT_SUPERVISOR = ""


@dataclass
class RemoteMember:
    """A group member on another host, as seen through its status and its agent's token."""

    group: str
    host: str
    axis: str
    bad: bool = False
    seen: bool = False


class Peers:
    """Leases, lease loss, remote group members.

    Given: the settings, the cycle (internal commands, group triggers), the
    :class:`~bus_agent.gateway.handoff.Feed` (lease events, drive states) and ``enqueue``, which
    queues work on ``gw-command``."""

    def __init__(self, settings: GatewaySettings, cycle: CycleLike, feed: Feed,
                 enqueue: Callable[[tuple[Callable[..., None], tuple]], None]) -> None:
        self.s = settings
        self.host = settings.host
        self._cycle = cycle
        self._feed = feed
        self._enqueue = enqueue
        #: The lease table; touched only on ``gw-command``.
        self.leases = LeaseTable()
        #: axis -> lease holder, the copy the publisher reads (replaced whole, never changed).
        self.holders: dict[str, str] = {}
        #: Group members on other hosts, in configuration order.
        self.remotes: list[RemoteMember] = []
        # Remote members change on zenoh's callback threads (status) and the command thread (tokens).
        self._remotes_lock = threading.Lock()
        for group, members in settings.groups.items():
            for member in members:
                host, _, axis = member.partition("/")
                if host != self.host:
                    self.remotes.append(RemoteMember(group, host, axis))
        self._internal_seq = 0

    # ---- leases (gw-command) --------------------------------------------------------------

    def blocking(self, supervisor: str, axes: Iterable[str]) -> str:
        """The leases that keep ``supervisor`` from commanding ``axes`` ('' when none)."""
        leases = self.leases
        return ", ".join(f"{a} by {h}" for a in axes if (h := leases.check(a, supervisor)))

    def lease_command(self, req: Request, parsed: ParsedCommand,
                      answer: Callable[[Request, rt.Outcome], None]) -> None:
        """Carry out a ``lease`` or ``release`` request; ``answer`` gets each axis' outcome."""
        args, r = parsed.args, parsed.request
        holder = args["holder"]
        now = time.monotonic()
        if r.op == "lease":
            ttl = args["ttl_s"] if "ttl_s" in r.args else self.s.lease_ttl_s.get(parsed.axes[0], args["ttl_s"])
            decisions = self.leases.acquire(parsed.axes, holder, ttl, args["takeover"], now)
        else:
            decisions = self.leases.release(parsed.axes, holder)
        self.holders = self.leases.holders()
        self._feed.wake.set()
        for dec in decisions:
            answer(req, self._lease_outcome(req, dec))

    def _lease_outcome(self, req: Request, dec: LeaseDecision) -> rt.Outcome:
        """The outcome of one axis' lease decision (its lease event emitted)."""
        state = self._feed.state(dec.axis)
        if dec.result is LeaseResult.BUSY:
            reason = f"drive {self.host}/{dec.axis} is leased by {dec.previous}" if dec.previous == dec.holder else \
                     f"lease refused: another addressed drive is leased by {dec.previous}"
            return rt.Outcome(dec.axis, "busy", state=state, reason=reason)
        if dec.result is LeaseResult.TAKEN_OVER:
            detail = f"lease taken over by {dec.holder} from {dec.previous}"
            self._feed.emit(rt.CycleEvent(dec.axis, "lease", detail=detail, request_id=req.request_id))
        elif dec.result in (LeaseResult.GRANTED, LeaseResult.RELEASED):
            who = dec.holder or dec.previous
            self._feed.emit(rt.CycleEvent(dec.axis, "lease", detail=f"lease {dec.result.value} ({who})",
                                          request_id=req.request_id))
        return rt.Outcome(dec.axis, "done", state=state, reason=dec.result.value)

    def on_supervisor_token(self, sample: zenoh.Sample) -> None:
        """A supervisor's liveliness token changed: a deleted one ends that holder's leases."""
        if sample.kind != zenoh.SampleKind.DELETE:
            return
        try:
            name = keys.parse(str(sample.key_expr)).name
        except keys.InvalidKey:
            return
        if name:
            ended = self.leases.holder_lost(name)
            if ended:
                self._leases_ended(ended)

    def tick(self, now: float) -> None:
        """End the leases expired at ``now`` (their reactions run)."""
        ended = self.leases.expire(now)
        if ended:
            self._leases_ended(ended)

    def _leases_ended(self, ended: list[EndedLease]) -> None:
        """Lease expired or holder lost: run the configured reaction on those drives."""
        self.holders = self.leases.holders()
        self._feed.wake.set()
        by_reaction: dict[tuple[str, ...], list[str]] = {}
        for e in ended:
            why = "expired" if e.why.value == "expired" else "holder's liveliness token disappeared"
            reaction = self.s.lease_reaction.get(e.lease.axis, "quick_stop_then_disable")
            ops = LEASE_REACTION_OPS.get(reaction, LEASE_REACTION_OPS["quick_stop_then_disable"])
            log.warning("drive %s/%s: lease of %s %s: %s", self.host, e.lease.axis, e.lease.holder, why,
                        " then ".join(ops) or "no reaction")
            detail = f"lease of {e.lease.holder} ended ({why}): {', then '.join(ops) or 'no reaction'}"
            self._feed.emit(rt.CycleEvent(e.lease.axis, "lease", detail=detail))
            if ops:
                by_reaction.setdefault(ops, []).append(e.lease.axis)
        for ops, axes in by_reaction.items():
            self._run_internal(ops, tuple(axes), "lease")

    def _run_internal(self, ops: tuple[str, ...], axes: tuple[str, ...], why: str) -> None:
        """Issue ``ops[0]`` for ``axes`` as the agent itself; each next op after every axis answered."""
        if not ops:
            return
        self._internal_seq += 1
        rid = f"@{self.host}-{why}-{self._internal_seq}"
        remaining = set(axes)
        enqueue = self._enqueue

        def on_outcome(o: rt.Outcome) -> None:  # cycle thread
            enqueue((step_done, (o,)))

        def step_done(o: rt.Outcome) -> None:
            remaining.discard(o.axis)
            if not remaining:
                self._run_internal(ops[1:], axes, why)

        cmd = rt.DriveCommand(request_id=rid, op=ops[0], axes=axes, timeout_s=5.0, supervisor=AGENT_SUPERVISOR,
                              received_ns=time.monotonic_ns(), on_outcome=on_outcome)
        if not self._cycle.submit(cmd):
            log.error("agent %s: %s reaction %s for %s could not be queued (inbox full); retrying",
                      self.host, why, ops[0], ", ".join(axes))
            threading.Timer(0.01, lambda: enqueue((self._run_internal, (ops, axes, why)))).start()

    # ---- remote group members -------------------------------------------------------------

    def on_remote_status(self, sample: zenoh.Sample) -> None:
        """A remote group member's status, on zenoh's callback thread: a member turning bad
        triggers the group at once (``trigger_group`` is thread-safe and only queues), rather
        than after whatever the command thread is doing (replies, validation, lease timers)."""
        hops.stamp("gw.remote")
        try:
            st = m.decode(sample.payload.to_bytes(), m.DriveStatus)
        except m.SchemaError as exc:
            log.warning("remote status on %s undecodable: %s", sample.key_expr, exc)
            return
        bad = st.lost or st.state in BAD_STATES
        reason = f"{st.host}/{st.axis} {'lost' if st.lost else st.state}"
        for r in self.remotes:
            if r.host == st.host and r.axis == st.axis:
                with self._remotes_lock:
                    seen, r.seen = r.seen, True
                    self._remote_member(r, bad, reason)
                if not seen:
                    log.info("agent %s: group %s member %s/%s seen: %s", self.host, r.group, r.host, r.axis,
                             "lost" if st.lost else st.state)

    def on_remote_token(self, sample: zenoh.Sample) -> None:
        """A remote agent's liveliness token changed (on ``gw-command``): gone -> its members are bad."""
        try:
            host = keys.parse(str(sample.key_expr)).host
        except keys.InvalidKey:
            return
        if sample.kind == zenoh.SampleKind.DELETE:
            for r in self.remotes:
                if r.host == host:
                    with self._remotes_lock:
                        self._remote_member(r, True, f"agent {host} lost (liveliness)")

    def _remote_member(self, r: RemoteMember, bad: bool, reason: str) -> None:
        """Trigger ``r``'s group once per change to bad. Hold ``_remotes_lock``."""
        if bad and not r.bad:
            hops.stamp("gw.trigger")
            self._cycle.trigger_group(r.group, reason)
            log.warning("agent %s: group %s member %s/%s: %s -> trigger", self.host, r.group, r.host, r.axis, reason)
        r.bad = bad
