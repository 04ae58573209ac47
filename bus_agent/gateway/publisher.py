"""The gateway's publisher: drive status on change and as a heartbeat, events, agent status.

:class:`Publisher` is the part of :class:`bus_agent.gateway.gateway.Gateway` that owns the status,
event and agent status publishers and what was last published; it runs on the ``gw-publish``
thread (and once more from ``close``) and answers status and agent status queries on
``gw-command``. Discrete fields (:data:`CHANGE_FIELDS`) go out within one cycle of a change;
motion fields (:data:`MOTION_FIELDS`) at most every ``motion_period_s``; everything with every
heartbeat.
"""

from __future__ import annotations

import dataclasses
import logging
import operator
import os
import threading
import time
from typing import Mapping

import zenoh

from bus_agent import hops
from bus_agent import runtime as rt
from bus_agent.cycle.realtime import name_thread, set_thread_fifo
from bus_agent.gateway.handoff import Feed
from bus_agent.gateway.hostclaim import HostClaim
from bus_agent.gateway.peers import Peers
from bus_agent.gateway.requests import MSGPACK, key_expr, undeclare
from bus_agent.gateway.settings import BAD_STATES, GatewaySettings
from schemas import keys
from schemas import messages as m
from schemas.error_codes import describe

log = logging.getLogger("bus_agent.gateway.gateway")

#: Drive status fields whose change is news and is published within one cycle. Position,
#: velocity and torque change every cycle in motion: they go out at most every
#: ``motion_period_s`` and with every heartbeat.
CHANGE_FIELDS = ("state", "statusword", "controlword", "goal", "halt", "mode", "mode_display",
                 "error_code", "error_text", "al_state", "lost", "axis_state", "homed", "motion_request_id")
MOTION_FIELDS = ("position", "velocity", "torque", "target_position", "following_error", "objects", "target_clamps")
#: What the agent asks of a drive (0x6040, the goal, the halt bit, 0x6060): a change of these
#: alone is answered by the drive within a cycle or two (0x6041, 0x6061), and the status waits
#: for that answer to go out with it, at most :data:`HOLD_CYCLES` cycles (docs/agent-gateway.md).
ASKED_FIELDS = ("controlword", "goal", "halt", "mode")
#: Positions of ASKED_FIELDS in the change tuple the publisher compares (CHANGE_FIELDS + holder).
ASKED_INDEX = frozenset(CHANGE_FIELDS.index(f) for f in ASKED_FIELDS)
#: The longest a change of ASKED_FIELDS alone waits for the drive's answer, in agent cycles.
HOLD_CYCLES = 3
#: How long one publish pass may wait, in all, for the command thread to finish its work (see
#: :meth:`Publisher._commands_first`).
COMMANDS_FIRST_MAX_S = 0.005

# The fields compared per drive in every pass (all drives, every snapshot): one C call each.
_change_fields = operator.attrgetter(*CHANGE_FIELDS)
_motion_fields = operator.attrgetter(*MOTION_FIELDS)


def _only_asked(last: tuple, fields: tuple) -> bool:
    """True when every field that differs between two change tuples is one of ASKED_FIELDS."""
    return all(i in ASKED_INDEX for i, (a, b) in enumerate(zip(last, fields)) if a != b)


class PublishPriority:
    """The scheduling of ``gw-publish``: it waits and starts each pass under SCHED_FIFO
    (``rt_priority``; 0: off) and runs the rest of the pass under SCHED_OTHER."""

    def __init__(self, rt_priority: int, host: str) -> None:
        self.rt_priority = rt_priority
        self.host = host
        self.fifo = False    # the thread is set up for SCHED_FIFO
        self.normal = False  # ... and is under SCHED_OTHER for the rest of this pass

    def start(self) -> None:
        """On the publish thread, once: SCHED_FIFO if configured and allowed."""
        self.fifo = set_thread_fifo(self.rt_priority, f"gw-publish of {self.host}")

    def to_normal(self) -> None:
        """The rest of this pass under normal scheduling (SCHED_OTHER); the loop goes back to
        SCHED_FIFO before it waits, so the next pass wakes, and the status of a drive in fault
        goes out, at real-time priority. A whole pass of an enable (a put per changed drive and
        per event, every cycle) under SCHED_FIFO kept every normal thread of the machine off the
        CPU while it ran: zenoh's own threads, which send the command replies, and any client on
        the host. The replies reached the client only after the pass (docs/agent-gateway.md,
        "Where the time goes"). Two system calls per pass."""
        if self.fifo and not self.normal:
            try:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
                self.normal = True
            except OSError as exc:
                log.debug("gw-publish: SCHED_OTHER refused: %s", exc)

    def to_fifo(self) -> None:
        """Back to SCHED_FIFO after :meth:`to_normal`, before the thread waits."""
        if self.normal:
            self.normal = not set_thread_fifo(self.rt_priority, f"gw-publish of {self.host}")


class Publisher:
    """Snapshots and events of the cycle turned into puts; the answers to status queries.

    Given: the settings, the :class:`~bus_agent.gateway.handoff.Feed` it drains, ``commands_idle``
    (set while ``gw-command`` has nothing to do: a pass waits for it, bounded, before each put),
    the gateway's ``stop``, and for the agent status the lease holders (``peers.holders``), the
    host claim (instance, conflict) and the command counts."""

    def __init__(self, settings: GatewaySettings, feed: Feed, commands_idle: threading.Event,
                 stop: threading.Event, peers: Peers, claim: HostClaim, command_counts: Mapping[str, int]) -> None:
        self.s = settings
        self.host = settings.host
        self.axes = tuple(settings.axes)
        self._feed = feed
        self._commands_idle = commands_idle
        self._stop = stop
        self._peers = peers
        self._claim = claim
        self._command_counts = command_counts
        self.priority = PublishPriority(settings.rt_priority, self.host)
        #: The agent state published instead of the cycle's ('stopping', 'stopped'), or None.
        self.agent_state_override: str | None = None
        self._status_seq: dict[str, int] = {a: 0 for a in self.axes}
        self._event_seq: dict[str, int] = {a: 0 for a in self.axes}
        self._agent_seq = 0
        self._last_fields: dict[str, tuple] = {}
        self._last_motion: dict[str, tuple] = {}
        self._last_motion_pub_s: dict[str, float] = {}
        self._status_keys: dict[str, str] = {}  # axis -> its status key, built once
        #: axis -> when its held change (ASKED_FIELDS alone) goes out at the latest
        self.held_until: dict[str, float] = {}
        # axis -> (drive snapshot, lease holder) last seen with nothing left to publish
        self._settled: dict[str, tuple[rt.DriveSnapshot, str]] = {}
        self._hold_s = HOLD_CYCLES * settings.cycle_us / 1e6
        #: axis -> the drive status last published
        self.published: dict[str, m.DriveStatus] = {}
        self._next_heartbeat_s = 0.0
        self._next_agent_s = 0.0
        #: axis -> its status publisher (declared by :meth:`declare`)
        self.status_pubs: dict[str, zenoh.Publisher] = {}
        self._event_pubs: dict[str, zenoh.Publisher] = {}
        self._agent_pub: zenoh.Publisher | None = None
        self._lock = threading.Lock()  # publish_once from close() vs the thread

    def declare(self, session: zenoh.Session) -> None:
        """Declare the status and event publishers of every axis and the agent status publisher."""
        for axis in self.axes:
            # BLOCK: a watcher must see every publication (seq without gaps); a slow subscriber
            # slows only this publishing thread, which coalesces to the latest snapshot, never the cycle.
            self.status_pubs[axis] = session.declare_publisher(
                keys.drive_status(self.host, axis), encoding=MSGPACK, express=True,
                congestion_control=zenoh.CongestionControl.BLOCK)
            self._event_pubs[axis] = session.declare_publisher(
                keys.drive_event(self.host, axis), encoding=MSGPACK, congestion_control=zenoh.CongestionControl.BLOCK)
        self._agent_pub = session.declare_publisher(keys.agent_status(self.host), encoding=MSGPACK)

    def undeclare(self) -> None:
        for pub in [*self.status_pubs.values(), *self._event_pubs.values(), self._agent_pub]:
            if pub is not None:
                undeclare(pub)
        self.status_pubs.clear()
        self._event_pubs.clear()
        self._agent_pub = None

    def run(self) -> None:
        """The ``gw-publish`` thread: a pass per wake-up (snapshot, event), held change or period."""
        name_thread("gw-publish")
        priority = self.priority
        priority.start()
        feed = self._feed
        while not self._stop.is_set():
            now = time.monotonic()
            held = self.held_until
            wait = max(0.0, min(self._next_heartbeat_s, self._next_agent_s, *held.values()) - now)
            feed.wake.wait(wait)
            feed.wake.clear()
            if self._stop.is_set():
                break
            try:
                self.publish_once(publish_thread=True)
            except Exception:  # keep publishing; the log says what broke
                log.exception("gateway %s: publish failed", self.host)
            finally:
                priority.to_fifo()

    def _commands_first(self, until_s: float) -> None:
        """Let the command thread finish what it is doing (replies, a query's validation) before
        the next put, until ``until_s`` at most. Both threads need the GIL, and a put or a reply
        gives it up while zenoh works: a publish pass (a put per changed drive and per event, all
        16 drives in every cycle of an enable) took it back each time and held a 16-drive reply
        batch up by milliseconds. Waiting on an event sleeps without the GIL."""
        if not self._commands_idle.is_set() and not self._stop.is_set():
            self._commands_idle.wait(max(0.0, until_s - time.monotonic()))

    def publish_once(self, final: bool = False, publish_thread: bool = False) -> None:
        """One pass: drives in fault or lost first, then the other drives, the events, and the
        agent status when due. ``final``: everything now (the last pass, from ``close``)."""
        with self._lock:
            feed = self._feed
            snap = feed.latest
            now = time.monotonic()
            until_s = now + (0.0 if final else COMMANDS_FIRST_MAX_S)
            heartbeat = final or now >= self._next_heartbeat_s
            if heartbeat:
                self._next_heartbeat_s = now + self.s.heartbeat_s
            holders = self._peers.holders
            if snap is not None:
                # A drive in fault or lost first and without waiting for the command thread: group
                # members on other hosts react to this status (docs/agent-gateway.md, reflexes).
                for d in snap.drives:
                    if d.lost or d.state in BAD_STATES:
                        self._maybe_publish_status(snap, d, holders.get(d.axis, ""), now, heartbeat)
            if publish_thread:
                self.priority.to_normal()
            if snap is not None:
                for d in snap.drives:
                    if not (d.lost or d.state in BAD_STATES):
                        self._commands_first(until_s)
                        self._maybe_publish_status(snap, d, holders.get(d.axis, ""), now, heartbeat)
            events = feed.events
            while events:
                self._commands_first(until_s)
                ev, cycle, time_ns = events.popleft()
                self.publish_event(ev, cycle, time_ns)
            if final or feed.agent_due or now >= self._next_agent_s:
                feed.agent_due = False
                self._next_agent_s = now + self.s.agent_period_s
                if self._agent_pub is not None:
                    self._agent_seq += 1
                    self._agent_pub.put(m.encode(self._agent_status(self._agent_seq)))

    def publish_bad_now(self, snap: rt.CycleSnapshot) -> None:
        """The status of every drive in ``snap`` that is in fault or lost, published now on the
        caller's thread when it changed: the bridge reader of the gateway process calls this for
        each forwarded snapshot, so a fault reaches the group members on other hosts without
        waiting for the publish thread's wake-up and GIL turn. Never the cycle thread. Skipped
        while the publish thread is in a pass (it publishes such drives first anyway)."""
        bad = [d for d in snap.drives if d.lost or d.state in BAD_STATES]
        if not bad or not self._lock.acquire(blocking=False):
            return
        try:
            now = time.monotonic()
            holders = self._peers.holders
            for d in bad:
                self._maybe_publish_status(snap, d, holders.get(d.axis, ""), now, False)
        finally:
            self._lock.release()

    def _maybe_publish_status(self, snap: rt.CycleSnapshot, d: rt.DriveSnapshot, holder: str, now: float,
                              heartbeat: bool) -> None:
        axis = d.axis
        pub = self.status_pubs.get(axis)
        if pub is None:
            return
        settled = self._settled.get(axis)
        if settled is not None and settled[0] is d and settled[1] == holder and not heartbeat:
            return  # the very object of a drive with nothing left to publish (wire.decode_snapshot)
        fields = _change_fields(d) + (holder,)
        motion = _motion_fields(d)
        last = self._last_fields.get(axis)
        changed = fields != last
        moved = (motion != self._last_motion.get(axis)
                 and now - self._last_motion_pub_s.get(axis, 0.0) >= self.s.motion_period_s)
        if not (changed or moved or heartbeat):
            self.held_until.pop(axis, None)  # a held change undone meanwhile: nothing to publish
            if motion == self._last_motion.get(axis):  # no motion publication pending either
                self._settled[axis] = (d, holder)
            return
        self._settled.pop(axis, None)
        if changed and not (moved or heartbeat) and last is not None and _only_asked(last, fields):
            # What the agent asked changed, the drive has not answered yet: the status waits for
            # the answer (the next statusword) to carry both, bounded; the publish loop wakes then.
            until = self.held_until.setdefault(axis, now + self._hold_s)
            if now < until:
                return
        self.held_until.pop(axis, None)
        self._status_seq[axis] = self._status_seq.get(axis, 0) + 1
        try:
            msg, payload = self._status_encoded(snap, d, holder, self._status_seq[axis])
        except m.SchemaError as exc:
            log.error("drive %s/%s: status not publishable: %s", self.host, axis, exc)
            return
        pub.put(payload)
        hops.stamp("pub.bad" if d.lost or d.state in BAD_STATES else "pub.status")
        self.published[axis] = msg
        self._last_fields[axis] = fields
        self._last_motion[axis] = motion
        self._last_motion_pub_s[axis] = now
        self._settled[axis] = (d, holder)

    def _status_encoded(self, snap: rt.CycleSnapshot, d: rt.DriveSnapshot, holder: str,
                        seq: int) -> tuple[m.DriveStatus, bytes]:
        """The status message of drive ``d`` and its encoding, validated once
        (:func:`schemas.messages.encode_new`); raises :class:`schemas.messages.SchemaError`."""
        return m.encode_new(m.DriveStatus, {
            "host": self.host, "axis": d.axis, "seq": seq, "time_ns": snap.time_ns, "cycle": snap.cycle,
            "state": d.state if d.state in m.DRIVE_STATES else "unknown", "statusword": d.statusword,
            "controlword": d.controlword, "goal": d.goal, "halt": d.halt, "mode": d.mode,
            "mode_display": d.mode_display, "position": d.position, "velocity": d.velocity, "torque": d.torque,
            "error_code": d.error_code, "error_text": (d.error_text or describe(d.error_code))[:200],
            "al_state": d.al_state, "lost": d.lost, "lease_holder": holder, "slave": d.slave,
            "absent": list(d.absent), "objects": dict(zip(d.object_names, d.objects)),
            "axis_state": d.axis_state, "homed": d.homed, "target_position": d.target_position,
            "following_error": max(-2**31, min(2**31 - 1, d.following_error)),
            "motion_request_id": d.motion_request_id[:128], "target_clamps": d.target_clamps,
            "last_known_state": d.last_known_state if d.last_known_state in m.DRIVE_STATES else "",
        })

    def publish_event(self, ev: rt.CycleEvent, cycle: int, time_ns: int) -> None:
        if not ev.axis:
            # An agent-wide event (e.g. an NMT outcome) concerns every drive: one copy each.
            for axis in self.axes:
                self.publish_event(dataclasses.replace(ev, axis=axis), cycle, time_ns)
            return
        pub = self._event_pubs.get(ev.axis)
        if pub is None:
            log.debug("event for unknown axis %r dropped: %s", ev.axis, ev)
            return
        self._event_seq[ev.axis] = self._event_seq.get(ev.axis, 0) + 1
        detail = ev.detail
        if ev.kind == "fault" and ev.error_code and describe(ev.error_code) not in detail:
            detail = f"{detail}: {describe(ev.error_code)}" if detail else describe(ev.error_code)
        try:
            _, payload = m.encode_new(m.Event, {
                "host": self.host, "axis": ev.axis, "seq": self._event_seq[ev.axis], "time_ns": time_ns,
                "cycle": cycle, "kind": ev.kind, "detail": detail[:400],
                "from_state": ev.from_state if ev.from_state in m.DRIVE_STATES else "unknown",
                "to_state": ev.to_state if ev.to_state in m.DRIVE_STATES else "unknown",
                "error_code": ev.error_code, "request_id": ev.request_id[:128], "requester": ev.requester[:128],
            })
            pub.put(payload)
            hops.stamp("pub.event")
        except m.SchemaError as exc:
            log.error("drive %s/%s: event not publishable: %s", self.host, ev.axis, exc)

    def _agent_status(self, seq: int) -> m.AgentStatus:
        snap = self._feed.latest
        st = snap.stats if snap else rt.CycleStats(cycle_us=self.s.cycle_us)
        state = self.agent_state_override or (snap.agent_state if snap else "starting")
        return m.AgentStatus(
            host=self.host, seq=seq, time_ns=snap.time_ns if snap else time.time_ns(),
            state=state if state in m.AGENT_STATES else "error", backend=self.s.backend,
            cycle_us=st.cycle_us or self.s.cycle_us, cycles=st.cycles,
            period_p50_us=st.period_p50_us, period_p99_us=st.period_p99_us, period_max_us=st.period_max_us,
            overruns=st.overruns, wkc_errors=st.wkc_errors, expected_wkc=st.expected_wkc,
            axes=list(self.axes), al_states={d.axis: d.al_state for d in snap.drives} if snap else {},
            leases=dict(self._peers.holders), groups={g: list(ms) for g, ms in self.s.groups.items()},
            instance=self._claim.instance, conflict=self._claim.conflict_text[:400],
            commands=dict(self._command_counts),
            dc={d.axis: d.dc for d in snap.drives} if snap else {},
            dc_offset_p50_us=st.dc_offset_p50_us, dc_offset_p99_us=st.dc_offset_p99_us,
        )

    # ---- queries (on gw-command) ------------------------------------------------------------

    def answer_status_query(self, query: zenoh.Query) -> None:
        """The status of every drive the query's key intersects, as of the latest snapshot."""
        with query:
            snap = self._feed.latest
            if snap is None:
                return
            qke = query.key_expr
            holders = self._peers.holders
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

    def answer_agent_query(self, query: zenoh.Query) -> None:
        """The agent status now (with the sequence number of the last one published)."""
        with query:
            query.reply(keys.agent_status(self.host), m.encode(self._agent_status(self._agent_seq)),
                        encoding=MSGPACK)
