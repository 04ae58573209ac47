"""Group reflexes: the reacting members' goal when a group is triggered, and express exchanges.

:class:`Reflexes` (cycle thread only) gives the reacting local members of a triggered group the
configured reflex goal (``[agent] reflex``: quick stop or disable), by a local origin (a member's
fault or loss, found by the cycle) or a remote trigger (:class:`~bus_agent.cycle.triggers.TriggerInbox`).
Its outputs go out at once in an *express* exchange where that is safe (:meth:`Reflexes.express`,
:meth:`Reflexes.express_after_cycle`) rather than with the next scheduled frame.
"""

from __future__ import annotations

from typing import Iterable

from bus_agent import hops
from bus_agent.bus.base import Bus
from bus_agent.cia402.controller import Goal
from bus_agent.cycle.drive import Segment
from bus_agent.cycle.events import EventLog
from bus_agent.cycle.motion import MotionStage
from bus_agent.cycle.outcomes import CommandBook
from bus_agent.cycle.triggers import TriggerInbox
from bus_agent.runtime import CycleEvent


class Reflexes:
    """The reflexes of the local group members and the express exchanges that carry them."""

    def __init__(self, bus: Bus, seg: Segment, triggers: TriggerInbox, book: CommandBook, motion: MotionStage,
                 events: EventLog, goal: Goal) -> None:
        self._bus = bus
        self._seg = seg
        self._triggers = triggers
        self._book = book
        self._motion = motion
        self._events = events
        self._goal = goal
        #: Express exchanges made so far (``Cycle.express_exchanges``).
        self.exchanges = 0
        self._express_events: list[CycleEvent] = []
        self._seen = 0  # exchanges at the last take_express

    def reflex(self, group: str, origin_axis: str | None, reason: str, now_ns: int) -> None:
        """``group`` triggered: every reacting member (all local ones but the origin) gets the
        reflex goal; its pending command fails and its motion is aborted."""
        goal = self._goal
        by_axis = self._seg.by_axis
        for axis in self._seg.groups.reacting(group, origin_axis):
            d = by_axis[axis]
            if d.lost:
                continue
            if d.pending is not None:
                self._book.resolve(d, "failed", f"group {group} reflex: {reason}", now_ns)
            self._motion.abort(d, f"group {group} reflex: {reason}", now_ns)
            d.ctrl.set_goal(goal, now_ns / 1e9)
            self._events.event(axis, "reflex", f"group {group}: {goal.value} ({reason})", from_state=d.state.value)

    def apply(self, local: Iterable[tuple[str, str]], now_ns: int) -> dict[str, int]:
        """The cycle's reflexes: the remote triggers queued (taken) and the ``local`` origins
        ``(group, "host/axis why")``. Returns the reacting axes and their controlwords before."""
        reacting: dict[str, int] = {}  # the reflexes' reacting drives: their controlwords now
        queue = self._triggers.queue
        by_axis = self._seg.by_axis
        groups = self._seg.groups
        while queue:
            g, reason = queue.popleft()
            self.reflex(g, None, f"remote: {reason}", now_ns)
            for axis in groups.reacting(g):
                reacting.setdefault(axis, by_axis[axis].controlword)
        for g, reason in local:
            origin_axis = reason.split("/", 1)[1].split(" ", 1)[0]
            self.reflex(g, origin_axis, reason, now_ns)
            for axis in groups.reacting(g, origin_axis):
                reacting.setdefault(axis, by_axis[axis].controlword)
        return reacting

    def express(self, now_ns: int) -> bool:
        """Remote group triggers that arrived between two cycles, applied at once (the loop
        wakes for them): each reacting drive's controller is stepped on its last inputs with the
        reflex's goal, and one extra exchange hands the new controlwords to the bus now, rather
        than with the frame after the next deadline (about one period later).

        The frame carries the process image as the last cycle left it for the next deadline: the
        new controlwords, and every other output as computed for the next frame. So it is sent
        only while no other drive follows a trajectory (``motion.plan``): a drive at rest gets
        the same targets twice, a moving one would get its next target a period early and then
        again (a step in its velocity). Nor on a bus without ``express_exchange`` (CANopen: the
        exchange sends a SYNC). Otherwise the reflex is applied now and goes out with the next
        frame. It is not a cycle: no period, statistics, DC step (the PI sees only the scheduled
        frames; docs/agent-cycle.md, Timing) or management work. True when the controlwords
        changed and may go out: the caller stamps the time and calls :meth:`exchange`."""
        queue = self._triggers.queue
        reacting: dict[str, None] = {}
        groups = self._seg.groups
        while queue:
            g, reason = queue.popleft()
            self.reflex(g, None, f"remote: {reason}", now_ns)
            reacting.update(dict.fromkeys(groups.reacting(g)))
        now_s = now_ns / 1e9
        bus = self._bus
        by_axis = self._seg.by_axis
        changed = False
        for axis in reacting:
            d = by_axis[axis]
            if d.lost:
                continue
            out = d.ctrl.step(d.inputs.statusword, d.inputs.modes_of_operation_display, now_s)
            if out.events:
                self._book.controller_events(d, out.events, now_ns)
            cw = out.controlword | d.motion.controlword_bits
            if cw != d.controlword:
                o = d.out
                o.controlword = d.controlword = cw
                bus.set_outputs(d.slave, o)
                changed = True
        return changed and self._allowed(reacting)

    def exchange(self) -> None:
        """The express exchange itself."""
        self._bus.exchange()  # first: the snapshot can wait a frame's round trip, the drive not
        hops.stamp("cy.express")
        self.exchanges += 1

    def published(self, events: list[CycleEvent]) -> None:
        """The events of an express reflex, published at once; the next cycle's flight
        recording gets them too."""
        self._express_events += events

    def take_express(self) -> tuple[bool, list[CycleEvent]]:
        """At the start of a cycle: did an express reflex run since the last cycle (it changed
        goals, and its exchange the inputs), and its events (taken)."""
        events = self._express_events
        expressed = bool(events) or self.exchanges != self._seen
        self._seen = self.exchanges
        if events:
            self._express_events = []
        return expressed, events

    def _allowed(self, reacting: Iterable[str]) -> bool:
        """An extra exchange may go out now: the bus has one (not CANopen, whose exchange sends a
        SYNC) and no drive but the ``reacting`` ones follows a trajectory (see :meth:`express`)."""
        if not getattr(self._bus, "express_exchange", False):
            return False
        reacting = set(reacting)
        return not any(d.motion.plan is not None for d in self._seg.drives if not d.lost and d.axis not in reacting)

    def express_after_cycle(self, reacting: dict[str, int]) -> None:
        """Reflexes applied by the cycle itself: a local member's fault or loss, or remote
        triggers that came during the spin or the cycle's work (not in the sleep). Their outputs
        go out in an extra exchange right after the cycle, not with the next scheduled frame a
        period later. ``reacting``: the reacting axes and their controlwords before the cycle;
        nothing is sent when none changed."""
        by_axis = self._seg.by_axis
        if not any(by_axis[a].controlword != cw for a, cw in reacting.items() if not by_axis[a].lost):
            return
        if self._allowed(reacting):
            self.exchange()
