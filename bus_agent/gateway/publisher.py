"""The gateway's publisher: drive status on change and as a heartbeat, events, agent status.

The :class:`PublisherMixin` part of :class:`bus_agent.gateway.gateway.Gateway`; runs on the
``gw-publish`` thread (and once more from ``close``). Discrete fields (:data:`CHANGE_FIELDS`) go out
within one cycle of a change; motion fields (:data:`MOTION_FIELDS`) at most every
``motion_period_s``; everything with every heartbeat.
"""

from __future__ import annotations

import dataclasses
import logging
import operator
import os
import time

from bus_agent import hops
from bus_agent import runtime as rt
from bus_agent.cycle.realtime import name_thread, set_thread_fifo
from bus_agent.gateway.base import ASKED_INDEX, BAD_STATES, CHANGE_FIELDS, COMMANDS_FIRST_MAX_S, MOTION_FIELDS, GatewayBase
from schemas import messages as m
from schemas.error_codes import describe

log = logging.getLogger("bus_agent.gateway.gateway")


# The fields compared per drive in every pass (all drives, every snapshot): one C call each.
_change_fields = operator.attrgetter(*CHANGE_FIELDS)
_motion_fields = operator.attrgetter(*MOTION_FIELDS)


def _only_asked(last: tuple, fields: tuple) -> bool:
    """True when every field that differs between two change tuples is one of ASKED_FIELDS."""
    return all(i in ASKED_INDEX for i, (a, b) in enumerate(zip(last, fields)) if a != b)


class PublisherMixin(GatewayBase):
    """Snapshots and events of the cycle turned into puts."""

    def _publish_loop(self) -> None:
        name_thread("gw-publish")
        self._publish_fifo = set_thread_fifo(self.s.rt_priority, f"gw-publish of {self.host}")
        while not self._stop.is_set():
            now = time.monotonic()
            held = self._held_until
            wait = max(0.0, min(self._next_heartbeat_s, self._next_agent_s, *held.values()) - now)
            self._wake.wait(wait)
            self._wake.clear()
            if self._stop.is_set():
                break
            try:
                self._publish_once(publish_thread=True)
            except Exception:  # keep publishing; the log says what broke
                log.exception("gateway %s: publish failed", self.host)
            finally:
                self._publish_realtime_again()

    def _commands_first(self, until_s: float) -> None:
        """Let the command thread finish what it is doing (replies, a query's validation) before
        the next put, until ``until_s`` at most. Both threads need the GIL, and a put or a reply
        gives it up while zenoh works: a publish pass (a put per changed drive and per event, all
        16 drives in every cycle of an enable) took it back each time and held a 16-drive reply
        batch up by milliseconds. Waiting on an event sleeps without the GIL."""
        if not self._commands_idle.is_set() and not self._stop.is_set():
            self._commands_idle.wait(max(0.0, until_s - time.monotonic()))

    def _publish_normal_priority(self) -> None:
        """The rest of this pass under normal scheduling (SCHED_OTHER); the loop goes back to
        SCHED_FIFO before it waits, so the next pass wakes, and the status of a drive in fault
        goes out, at real-time priority. A whole pass of an enable (a put per changed drive and
        per event, every cycle) under SCHED_FIFO kept every normal thread of the machine off the
        CPU while it ran: zenoh's own threads, which send the command replies, and any client on
        the host. The replies reached the client only after the pass (docs/agent-gateway.md,
        "Where the time goes"). Two system calls per pass."""
        if self._publish_fifo and not self._publish_normal:
            try:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
                self._publish_normal = True
            except OSError as exc:
                log.debug("gw-publish: SCHED_OTHER refused: %s", exc)

    def _publish_realtime_again(self) -> None:
        """Back to SCHED_FIFO after :meth:`_publish_normal_priority`, before the thread waits."""
        if self._publish_normal:
            self._publish_normal = not set_thread_fifo(self.s.rt_priority, f"gw-publish of {self.host}")

    def _publish_once(self, final: bool = False, publish_thread: bool = False) -> None:
        with self._pub_lock:
            snap = self._latest
            now = time.monotonic()
            until_s = now + (0.0 if final else COMMANDS_FIRST_MAX_S)
            heartbeat = final or now >= self._next_heartbeat_s
            if heartbeat:
                self._next_heartbeat_s = now + self.s.heartbeat_s
            holders = self._lease_holders
            if snap is not None:
                # A drive in fault or lost first and without waiting for the command thread: group
                # members on other hosts react to this status (docs/agent-gateway.md, reflexes).
                for d in snap.drives:
                    if d.lost or d.state in BAD_STATES:
                        self._maybe_publish_status(snap, d, holders.get(d.axis, ""), now, heartbeat)
            if publish_thread:
                self._publish_normal_priority()
            if snap is not None:
                for d in snap.drives:
                    if not (d.lost or d.state in BAD_STATES):
                        self._commands_first(until_s)
                        self._maybe_publish_status(snap, d, holders.get(d.axis, ""), now, heartbeat)
            while self._events:
                self._commands_first(until_s)
                ev, cycle, time_ns = self._events.popleft()
                self._publish_event(ev, cycle, time_ns)
            if final or now >= self._next_agent_s:
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
        if not bad or not self._pub_lock.acquire(blocking=False):
            return
        try:
            now = time.monotonic()
            holders = self._lease_holders
            for d in bad:
                self._maybe_publish_status(snap, d, holders.get(d.axis, ""), now, False)
        finally:
            self._pub_lock.release()

    def _maybe_publish_status(self, snap: rt.CycleSnapshot, d: rt.DriveSnapshot, holder: str, now: float,
                              heartbeat: bool) -> None:
        axis = d.axis
        pub = self._status_pubs.get(axis)
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
            self._held_until.pop(axis, None)  # a held change undone meanwhile: nothing to publish
            if motion == self._last_motion.get(axis):  # no motion publication pending either
                self._settled[axis] = (d, holder)
            return
        self._settled.pop(axis, None)
        if changed and not (moved or heartbeat) and last is not None and _only_asked(last, fields):
            # What the agent asked changed, the drive has not answered yet: the status waits for
            # the answer (the next statusword) to carry both, bounded; the publish loop wakes then.
            until = self._held_until.setdefault(axis, now + self._hold_s)
            if now < until:
                return
        self._held_until.pop(axis, None)
        self._status_seq[axis] = self._status_seq.get(axis, 0) + 1
        try:
            msg, payload = self._status_encoded(snap, d, holder, self._status_seq[axis])
        except m.SchemaError as exc:
            log.error("drive %s/%s: status not publishable: %s", self.host, axis, exc)
            return
        pub.put(payload)
        hops.stamp("pub.bad" if d.lost or d.state in BAD_STATES else "pub.status")
        self._published[axis] = msg
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

    def _publish_event(self, ev: rt.CycleEvent, cycle: int, time_ns: int) -> None:
        if not ev.axis:
            # An agent-wide event (e.g. an NMT outcome) concerns every drive: one copy each.
            for axis in self.axes:
                self._publish_event(dataclasses.replace(ev, axis=axis), cycle, time_ns)
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
        snap = self._latest
        st = snap.stats if snap else rt.CycleStats(cycle_us=self.s.cycle_us)
        state = self.agent_state_override or (snap.agent_state if snap else "starting")
        return m.AgentStatus(
            host=self.host, seq=seq, time_ns=snap.time_ns if snap else time.time_ns(),
            state=state if state in m.AGENT_STATES else "error", backend=self.s.backend,
            cycle_us=st.cycle_us or self.s.cycle_us, cycles=st.cycles,
            period_p50_us=st.period_p50_us, period_p99_us=st.period_p99_us, period_max_us=st.period_max_us,
            overruns=st.overruns, wkc_errors=st.wkc_errors, expected_wkc=st.expected_wkc,
            axes=list(self.axes), al_states={d.axis: d.al_state for d in snap.drives} if snap else {},
            leases=dict(self._lease_holders), groups={g: list(ms) for g, ms in self.s.groups.items()},
            instance=self.instance, conflict=self._conflict_text[:400], commands=dict(self._command_counts),
            dc={d.axis: d.dc for d in snap.drives} if snap else {},
            dc_offset_p50_us=st.dc_offset_p50_us, dc_offset_p99_us=st.dc_offset_p99_us,
        )
