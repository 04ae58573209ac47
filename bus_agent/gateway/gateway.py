"""The gateway: the agent's Zenoh side (status publishers, command queryables, liveliness, leases).

It never blocks the cycle. The cycle hands over one :class:`~bus_agent.runtime.CycleSnapshot`
per cycle through the snapshot sink (:meth:`Feed.on_snapshot <bus_agent.gateway.handoff.Feed.on_snapshot>`:
an attribute store, a deque extend and an event set) and one :class:`~bus_agent.runtime.Outcome`
per addressed axis through each command's ``on_outcome`` (a queue put). Everything else runs on
the gateway's threads:

- ``gw-publish`` (:class:`~bus_agent.gateway.publisher.Publisher`) turns snapshots into
  ``DriveStatus`` puts (on change of a discrete field, within one cycle; motion fields at most
  every ``motion_period_s``; everything every ``heartbeat_s``), ``Event`` puts (cycle events and
  command outcomes) and ``AgentStatus``;
- ``gw-command`` (:class:`~bus_agent.gateway.commands.Commands`) owns every piece of mutable
  command state; with it run the lease table and remote group members
  (:class:`~bus_agent.gateway.peers.Peers`) and the host-name conflict
  (:class:`~bus_agent.gateway.hostclaim.HostClaim`). Zenoh callbacks only enqueue to it;
- ``gw-record`` (:class:`~bus_agent.gateway.recording.RecordingServer`) serves flight recordings.

:class:`Gateway` constructs these parts, hands each what it needs, declares the Zenoh entities
that tie them to the session in order (commands last) and undeclares them at the end
(docs/agent-gateway.md, "The gateway's parts").
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import zenoh

from bus_agent.gateway.commands import CONFLICT_REFUSED_OPS, DEDUP_SIZE, DEDUP_TTL_S, Commands
from bus_agent.gateway.handoff import Feed, Inbox
from bus_agent.gateway.hostclaim import HostClaim
from bus_agent.gateway.peers import AGENT_SUPERVISOR, LEASE_REACTION_OPS, Peers
from bus_agent.gateway.publisher import CHANGE_FIELDS, MOTION_FIELDS, Publisher
from bus_agent.gateway.recording import RecordingServer
from bus_agent.gateway.requests import (LEASE_OPS, MSGPACK, TEXT, ParsedCommand, RequestError, axes_in_key,
                                        parse_command, recording_message, requester, undeclare)
from bus_agent.gateway.settings import BAD_STATES, CycleLike, GatewaySettings
from schemas import keys

__all__ = ["Gateway", "GatewaySettings", "CycleLike", "RequestError", "ParsedCommand", "axes_in_key", "parse_command",
           "requester", "recording_message", "CHANGE_FIELDS", "MOTION_FIELDS", "BAD_STATES", "LEASE_OPS",
           "LEASE_REACTION_OPS", "CONFLICT_REFUSED_OPS", "DEDUP_SIZE", "DEDUP_TTL_S", "AGENT_SUPERVISOR", "MSGPACK",
           "TEXT"]

log = logging.getLogger(__name__)


class Gateway:
    """Zenoh I/O of one bus agent. ``start`` declares everything; ``stop_commands`` stops
accepting commands (shutdown begins); ``close`` publishes the last snapshot and undeclares.

    ``claim_config``: the ``zenoh.Config`` of the host claim's client session
    (:func:`~bus_agent.gateway.hostclaim.claim_config`), None when this session serves.
    """

    def __init__(self, session: zenoh.Session, cycle: CycleLike, settings: GatewaySettings,
                 claim_config: Any = None) -> None:
        self.session = session
        self.cycle = cycle
        self.host = settings.host
        self.axes = tuple(settings.axes)
        self._stop = threading.Event()
        self.feed = Feed()
        self.inbox = Inbox()
        self.claim = HostClaim(settings, claim_config, self.feed.emit, self.feed.agent_status_now)
        self.peers = Peers(settings, cycle, self.feed, self.inbox.put)
        self.commands = Commands(settings, cycle, self.feed, self.inbox, self.peers, self.claim, self._stop)
        self.publisher = Publisher(settings, self.feed, self.inbox.idle, self._stop, self.peers, self.claim,
                                   self.commands.counts)
        self.recordings = RecordingServer(self.host, cycle, self._stop)
        self._decls: list[Any] = []   # queryables and subscribers tying the parts to the session
        self._token: Any = None
        self._threads: list[threading.Thread] = []

    @property
    def agent_state_override(self) -> str | None:
        """The agent state published instead of the cycle's ('stopping', 'stopped'), or None."""
        return self.publisher.agent_state_override

    @agent_state_override.setter
    def agent_state_override(self, state: str | None) -> None:
        self.publisher.agent_state_override = state

    # ---- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Check that the host name is free (:class:`~bus_agent.gateway.hostclaim.HostNameTaken`
        otherwise, nothing declared), then declare everything, commands last."""
        s = self.session
        enqueue = self.inbox.put
        claim, peers, publisher = self.claim, self.peers, self.publisher
        on_own_status = lambda smp: enqueue((claim.on_own_status, (smp,)))  # noqa: E731
        claim.check(s, on_own_status)
        # A cycle already running (behind the process bridge) has a snapshot: drive status goes
        # out in the first publish pass, before the agent status that lists the axes.
        self.feed.latest = self.feed.latest or getattr(self.cycle, "latest", None)
        publisher.declare(s)
        decls = self._decls
        decls.append(s.declare_queryable(
            keys.drive_status(self.host, "*"), lambda q: enqueue((publisher.answer_status_query, (q,)))))
        decls.append(s.declare_queryable(
            keys.agent_status(self.host), lambda q: enqueue((publisher.answer_agent_query, (q,)))))
        decls.append(s.liveliness().declare_subscriber(
            keys.ALL_SUPERVISORS, lambda smp: enqueue((peers.on_supervisor_token, (smp,))), history=True))
        decls.append(s.declare_subscriber(keys.agent_status(self.host), on_own_status))
        # The group reflex's path: only the members' own status (not every drive of their hosts),
        # handled on zenoh's callback thread, not queued behind the command thread's work (see
        # Peers.on_remote_status).
        for host, axis in sorted({(r.host, r.axis) for r in peers.remotes}):
            decls.append(s.declare_subscriber(keys.drive_status(host, axis), peers.on_remote_status))
        for host in sorted({r.host for r in peers.remotes}):
            decls.append(s.liveliness().declare_subscriber(
                keys.alive(host), lambda smp: enqueue((peers.on_remote_token, (smp,))), history=True))
        decls.append(s.declare_queryable(keys.agent_recording(self.host), self.recordings.on_query))
        self._threads = [threading.Thread(target=publisher.run, name="gw-publish", daemon=True),
                         threading.Thread(target=self.commands.run, name="gw-command", daemon=True),
                         threading.Thread(target=self.recordings.run, name="gw-record", daemon=True)]
        for t in self._threads:
            t.start()
        retry = claim.retry(self._stop)
        if retry is not None:
            self._threads.append(retry)
        if hasattr(self.cycle, "event_sink"):  # a cycle behind the process bridge forwards events apart
            self.cycle.event_sink = self.feed.on_events
        self.cycle.snapshot_sink = self.feed.on_snapshot
        # Commands last: by now status flows and the lease/group subscribers are in place.
        self.commands.declare(s)
        self._token = s.liveliness().declare_token(keys.alive(self.host))
        log.info("gateway %s: %d drive(s), %d remote group member(s)", self.host, len(self.axes), len(peers.remotes))

    def stop_commands(self) -> None:
        """Stop taking new commands (queries already accepted still get their outcomes)."""
        self.commands.stop_accepting()

    def close(self, timeout_s: float = 2.0) -> None:
        """Publish what the cycle last reported, answer what is pending, undeclare everything.
        Call after the cycle stopped. Idempotent."""
        self.stop_commands()
        if self._stop.is_set():
            return
        # Outcomes the cycle gave during its ordered stop are in the inbox: let them through.
        done = threading.Event()
        self.inbox.put((lambda: done.set(), ()))
        done.wait(timeout_s)
        self._stop.set()
        self.feed.wake.set()
        self.inbox.put((lambda: None, ()))
        for t in self._threads:
            t.join(timeout_s)
        self.publisher.agent_state_override = "stopped"
        self.publisher.publish_once(final=True)
        self.commands.fail_pending()
        for decl in self._decls:
            undeclare(decl)
        self._decls.clear()
        self.claim.close()
        if self._token is not None:
            undeclare(self._token)
            self._token = None
        self.publisher.undeclare()
