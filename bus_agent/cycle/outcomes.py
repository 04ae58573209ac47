"""The command book: the inbox of commands, the pending ones and their one outcome per axis.

:class:`CommandBook` takes commands from ``Cycle.submit`` (any thread) into a bounded inbox that
the cycle drains at the start of a cycle; it answers every addressed axis exactly once: at once
(rejected, done), when a controller event ends the pending command (:data:`OUTCOME_OF_EVENT`),
or when its deadline passes. Cycle thread only, but for :meth:`CommandBook.submit`.
"""

from __future__ import annotations

import collections
import logging
import threading
from typing import Iterable, Mapping, Sequence

from bus_agent import hops
from bus_agent.cia402.controller import DISABLED_IN_FAULT, ControllerEvent, EventKind, Goal
from bus_agent.cycle.drive import UPWARD_GOALS, Drive
from bus_agent.cycle.events import EventLog
from bus_agent.cycle.stats import Statistics
from bus_agent.runtime import AgentCommand, DriveCommand, Outcome

log = logging.getLogger("bus_agent.cycle.cycle")

#: Bounded inbox: submit() returns False beyond this many waiting commands.
INBOX_MAX = 256

#: (pending command kind, controller event) -> (terminal outcome, reason when the event has none).
OUTCOME_OF_EVENT: dict[tuple[str, EventKind], tuple[str, str]] = {
    ("goal", EventKind.GOAL_REACHED): ("done", ""),
    ("goal", EventKind.GOAL_FAILED): ("failed", "goal failed"),
    ("goal", EventKind.GOAL_TIMEOUT): ("timeout", "transition deadline passed"),
    ("mode", EventKind.MODE_CONFIRMED): ("done", ""),
    ("mode", EventKind.MODE_REJECTED): ("rejected", "mode not supported (0x6502)"),
    ("mode", EventKind.MODE_TIMEOUT): ("timeout", "0x6061 did not echo the mode"),
    ("fault_reset", EventKind.FAULT_RESET_DONE): ("done", ""),
    ("fault_reset", EventKind.FAULT_RESET_FAILED): ("failed", "fault reset retries exhausted"),
}


def send_outcome(cmd: DriveCommand | AgentCommand, outcome: Outcome) -> None:
    """Call the command's ``on_outcome``; a failing callback is logged, never raised."""
    try:
        cmd.on_outcome(outcome)
    except Exception:
        log.exception("on_outcome callback of %s failed", cmd.request_id)


class CommandBook:
    """Inbox, pending commands and outcomes of one cycle."""

    def __init__(self, events: EventLog, stats: Statistics) -> None:
        self._inbox: collections.deque[DriveCommand | AgentCommand] = collections.deque()
        self._lock = threading.Lock()
        self._events = events
        self._stats = stats  # its cycle count: an outcome's ``cycles``

    # ---- the inbox --------------------------------------------------------------------------------

    def submit(self, cmd: DriveCommand | AgentCommand) -> bool:
        """Queue ``cmd``; False when the inbox is full. Thread-safe, non-blocking."""
        with self._lock:
            if len(self._inbox) >= INBOX_MAX:
                return False
            self._inbox.append(cmd)
        return True

    def take(self) -> list[DriveCommand | AgentCommand]:
        """The queued commands, oldest first; the inbox is empty after."""
        if not self._inbox:
            return []
        with self._lock:
            cmds = list(self._inbox)
            self._inbox.clear()
        return cmds

    def reject_all(self, reason: str, by_axis: Mapping[str, Drive]) -> None:
        """Answer every queued command ``rejected`` (the agent is stopping)."""
        for cmd in self.take():
            if isinstance(cmd, AgentCommand):
                send_outcome(cmd, Outcome(axis="", outcome="rejected", reason=reason))
            else:
                for axis in cmd.axes:
                    d = by_axis.get(axis)
                    send_outcome(cmd, Outcome(axis=axis, outcome="rejected", reason=reason,
                                              state=d.state.value if d and not d.lost else "unknown"))

    # ---- outcomes ---------------------------------------------------------------------------------

    def reply(self, d: Drive, cmd: DriveCommand, outcome: str, reason: str, now_ns: int, start_ns: int,
              start_cycle: int | None = None, duration_s: float = 0.0) -> None:
        """The outcome of ``cmd`` for ``d``'s axis, with its event."""
        # a lost drive's state and error code are unknown: its inputs are old
        state, error_code = ("unknown", 0) if d.lost else (d.state.value, d.inputs.error_code)
        cycles = self._stats.cycles
        o = Outcome(axis=d.axis, outcome=outcome, state=state, error_code=error_code,
                    reason=reason, elapsed_s=max(0.0, (now_ns - start_ns) / 1e9),
                    cycles=cycles - (start_cycle if start_cycle is not None else cycles),
                    duration_s=duration_s)
        self._events.event(d.axis, "outcome", f"{cmd.op} {outcome}" + (f": {reason}" if reason else ""),
                           to_state=state, error_code=error_code, request_id=cmd.request_id)
        send_outcome(cmd, o)
        hops.stamp("cy.outcome")

    def resolve(self, d: Drive, outcome: str, reason: str, now_ns: int) -> None:
        """End ``d``'s pending command (if any) with ``outcome``."""
        p = d.pending
        if p is None:
            return
        d.pending = None
        self.reply(d, p.cmd, outcome, reason, now_ns, p.start_ns, p.start_cycle)

    def supersede(self, d: Drive, cmd: DriveCommand, now_ns: int) -> None:
        if d.pending is not None:
            self.resolve(d, "failed", f"superseded by {cmd.request_id}", now_ns)

    def controller_events(self, d: Drive, evs: Sequence[ControllerEvent], now_ns: int) -> None:
        """A controller step's events: published, and the end of ``d``'s pending command."""
        p = d.pending
        event = self._events.event
        for ev in evs:
            k = ev.kind
            if k == EventKind.TRANSITION:
                event(d.axis, "transition", ev.reason, from_state=ev.from_state.value, to_state=ev.to_state.value)
            elif k == EventKind.FAULT:
                event(d.axis, "fault", ev.reason or f"error code 0x{d.inputs.error_code:04X}",
                      from_state=ev.from_state.value, to_state=ev.to_state.value, error_code=d.inputs.error_code)
            if k in (EventKind.GOAL_TIMEOUT, EventKind.GOAL_FAILED) and d.ctrl.goal in UPWARD_GOALS:
                # The controller gave up (it never retries upward): withdraw the goal, so that the
                # published goal says what the drive is held to and a late answer enables nothing.
                d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
            if p is None or d.pending is not p:
                continue
            terminal = OUTCOME_OF_EVENT.get((p.kind, k))
            if terminal is not None:
                outcome, default_reason = terminal
                if outcome == "done":
                    reason = ev.reason if ev.reason == DISABLED_IN_FAULT else ""
                else:
                    reason = ev.reason or default_reason
                self.resolve(d, outcome, reason, now_ns)

    def deadlines(self, work: Iterable[Drive], now_ns: int) -> None:
        """Pending commands of the drives stepped whose deadline passed: timeout."""
        for d in work:
            pend = d.pending
            if pend is not None and now_ns >= pend.deadline_ns:
                if pend.kind == "goal" and d.ctrl.goal in UPWARD_GOALS:
                    # Nobody waits for this goal any more: do not pursue it.
                    d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
                self.resolve(d, "timeout", f"{pend.cmd.op} not done within {pend.cmd.timeout_s:g} s", now_ns)
