"""Leases and the other hosts: lease commands and loss reactions, remote group members, host-name conflicts.

The :class:`PeersMixin` part of :class:`bus_agent.gateway.gateway.Gateway`; runs on the
``gw-command`` thread (Zenoh callbacks only enqueue to it). A lost lease runs the axis's
configured reaction (:data:`LEASE_REACTION_OPS`) as internal commands; a remote group member in
fault or gone triggers the group here (:meth:`Cycle.trigger_group`).
"""

from __future__ import annotations

import logging
import threading
import time

import zenoh

from bus_agent import hops
from bus_agent import runtime as rt
from bus_agent.gateway.base import AGENT_SUPERVISOR, BAD_STATES, LEASE_REACTION_OPS, GatewayBase, RemoteMember
from bus_agent.gateway.leases import EndedLease, LeaseDecision, LeaseResult
from bus_agent.gateway.requests import ParsedCommand, Request
from schemas import keys
from schemas import messages as m

log = logging.getLogger("bus_agent.gateway.gateway")


class PeersMixin(GatewayBase):
    """Leases, lease loss, conflicts over the host name, remote group members."""

    def _lease_command(self, req: Request, parsed: ParsedCommand) -> None:
        args, r = parsed.args, parsed.request
        holder = args["holder"]
        now = time.monotonic()
        if r.op == "lease":
            ttl = args["ttl_s"] if "ttl_s" in r.args else self.s.lease_ttl_s.get(parsed.axes[0], args["ttl_s"])
            decisions = self.leases.acquire(parsed.axes, holder, ttl, args["takeover"], now)
        else:
            decisions = self.leases.release(parsed.axes, holder)
        self._lease_holders = self.leases.holders()
        self._wake.set()
        for dec in decisions:
            self._lease_outcome(req, dec)

    def _lease_outcome(self, req: Request, dec: LeaseDecision) -> None:
        where = f"drive {self.host}/{dec.axis}"
        if dec.result is LeaseResult.BUSY:
            reason = f"{where} is leased by {dec.previous}" if dec.previous == dec.holder else \
                     f"lease refused: another addressed drive is leased by {dec.previous}"
            self._outcome(req, rt.Outcome(dec.axis, "busy", state=self._state(dec.axis), reason=reason))
            return
        if dec.result is LeaseResult.TAKEN_OVER:
            self._emit(rt.CycleEvent(dec.axis, "lease", detail=f"lease taken over by {dec.holder} from {dec.previous}",
                                     request_id=req.request_id))
        elif dec.result in (LeaseResult.GRANTED, LeaseResult.RELEASED):
            who = dec.holder or dec.previous
            self._emit(rt.CycleEvent(dec.axis, "lease", detail=f"lease {dec.result.value} ({who})",
                                     request_id=req.request_id))
        self._outcome(req, rt.Outcome(dec.axis, "done", state=self._state(dec.axis), reason=dec.result.value))

    def _on_supervisor_token(self, sample: zenoh.Sample) -> None:
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

    def _leases_ended(self, ended: list[EndedLease]) -> None:
        """Lease expired or holder lost: run the configured reaction on those drives."""
        self._lease_holders = self.leases.holders()
        self._wake.set()
        by_reaction: dict[tuple[str, ...], list[str]] = {}
        for e in ended:
            why = "expired" if e.why.value == "expired" else "holder's liveliness token disappeared"
            reaction = self.s.lease_reaction.get(e.lease.axis, "quick_stop_then_disable")
            ops = LEASE_REACTION_OPS.get(reaction, LEASE_REACTION_OPS["quick_stop_then_disable"])
            log.warning("drive %s/%s: lease of %s %s: %s", self.host, e.lease.axis, e.lease.holder, why,
                        " then ".join(ops) or "no reaction")
            self._emit(rt.CycleEvent(e.lease.axis, "lease",
                                     detail=f"lease of {e.lease.holder} ended ({why}): {', then '.join(ops) or 'no reaction'}"))
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

        def on_outcome(o: rt.Outcome) -> None:  # cycle thread
            self._inbox.put((step_done, (o,)))

        def step_done(o: rt.Outcome) -> None:
            remaining.discard(o.axis)
            if not remaining:
                self._run_internal(ops[1:], axes, why)

        cmd = rt.DriveCommand(request_id=rid, op=ops[0], axes=axes, timeout_s=5.0, supervisor=AGENT_SUPERVISOR,
                              received_ns=time.monotonic_ns(), on_outcome=on_outcome)
        if not self.cycle.submit(cmd):
            log.error("agent %s: %s reaction %s for %s could not be queued (inbox full); retrying",
                      self.host, why, ops[0], ", ".join(axes))
            threading.Timer(0.01, lambda: self._inbox.put((self._run_internal, (ops, axes, why)))).start()

    def _on_own_host_status(self, sample: zenoh.Sample) -> None:
        try:
            st = m.decode(sample.payload.to_bytes(), m.AgentStatus)
        except m.SchemaError:
            return
        if self._conflicts.seen(st.instance, time.monotonic()):
            self._conflict_changed()

    def _conflict_changed(self) -> None:
        self._conflict_text = self._conflicts.text
        if self._conflict_text:
            log.error("agent %s: %s", self.host, self._conflict_text)
        else:
            log.warning("agent %s: host name conflict over (no other instance for %.0f s)", self.host,
                        self._conflicts.hold_s)
        self._emit(rt.CycleEvent("", "conflict", detail=self._conflict_text or "host name conflict over"))
        self._next_agent_s = 0.0  # say it in the agent status now

    def _on_remote_status(self, sample: zenoh.Sample) -> None:
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
        for r in self._remotes:
            if r.host == st.host and r.axis == st.axis:
                with self._remotes_lock:
                    seen, r.seen = r.seen, True
                    self._remote_member(r, bad, reason)
                if not seen:
                    log.info("agent %s: group %s member %s/%s seen: %s", self.host, r.group, r.host, r.axis,
                             "lost" if st.lost else st.state)

    def _on_remote_token(self, sample: zenoh.Sample) -> None:
        try:
            host = keys.parse(str(sample.key_expr)).host
        except keys.InvalidKey:
            return
        if sample.kind == zenoh.SampleKind.DELETE:
            for r in self._remotes:
                if r.host == host:
                    with self._remotes_lock:
                        self._remote_member(r, True, f"agent {host} lost (liveliness)")

    def _remote_member(self, r: RemoteMember, bad: bool, reason: str) -> None:
        """Trigger ``r``'s group once per change to bad. Hold ``_remotes_lock``."""
        if bad and not r.bad:
            hops.stamp("gw.trigger")
            self.cycle.trigger_group(r.group, reason)
            log.warning("agent %s: group %s member %s/%s: %s -> trigger", self.host, r.group, r.host, r.axis, reason)
        r.bad = bad
