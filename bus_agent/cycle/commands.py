"""Drive commands, their one outcome per axis, automatic fault reset and group reflexes.

The :class:`CommandsMixin` part of :class:`bus_agent.cycle.cycle.Cycle` (cycle thread only):
commands queued by ``Cycle.submit`` are applied at the start of a cycle; controller events end
pending commands through :data:`OUTCOME_OF_EVENT`; a group trigger gives the reacting members
their reflex goal in the same cycle.
"""

from __future__ import annotations

import logging
from typing import Iterable, Sequence

from bus_agent import hops
from bus_agent.bus.base import ALState
from bus_agent.cia402.controller import DISABLED_IN_FAULT, ControllerEvent, EventKind, Goal
from bus_agent.cia402.states import Mode, State, decode_statusword
from bus_agent.cycle.base import CycleBase
from bus_agent.cycle.drive import FAULT_STATES, UPWARD_GOALS, VALID_MODES, Drive, Pending
from bus_agent.motion.axis import MOTION_OPS
from bus_agent.runtime import AgentCommand, CycleEvent, CycleSnapshot, DriveCommand, Outcome

log = logging.getLogger("bus_agent.cycle.cycle")


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

GOAL_OF_OP = {
    "enable": Goal.ENABLED,
    "switch_on": Goal.SWITCHED_ON,
    "shutdown": Goal.READY,
    "disable": Goal.DISABLED,
    "quick_stop": Goal.QUICK_STOP,
}


class CommandsMixin(CycleBase):
    """Commands in, one outcome per addressed axis out; auto reset; reflexes."""

    def _drain_inbox_rejecting(self, reason: str, now_ns: int) -> None:
        with self._inbox_lock:
            cmds = list(self._inbox)
            self._inbox.clear()
        for cmd in cmds:
            if isinstance(cmd, AgentCommand):
                self._outcome(cmd, Outcome(axis="", outcome="rejected", reason=reason))
            else:
                for axis in cmd.axes:
                    d = self._by_axis.get(axis)
                    self._outcome(cmd, Outcome(axis=axis, outcome="rejected", reason=reason,
                                               state=d.state.value if d and not d.lost else "unknown"))

    def _apply_inbox(self, now_ns: int) -> bool:
        """Apply the queued commands; True when there were any."""
        if not self._inbox:
            return False
        with self._inbox_lock:
            cmds = list(self._inbox)
            self._inbox.clear()
        for cmd in cmds:
            try:
                if isinstance(cmd, AgentCommand):
                    self._apply_agent(cmd, now_ns)
                else:
                    self._apply_drive(cmd, now_ns)
            except Exception as e:  # a bad command must not stop the loop
                log.exception("host %s: command %s failed", self.config.host, getattr(cmd, "request_id", "?"))
                if isinstance(cmd, AgentCommand):
                    self._outcome(cmd, Outcome(axis="", outcome="rejected", reason=f"internal error: {e}"))
        return True

    def _refusal(self, d: Drive) -> str:
        """Why no command can act on ``d`` now ('' if one can)."""
        if d.lost:
            return f"slave {d.slave} lost (AL {d.al.state.wire_name})"
        want = self._desired_al.get(d.slave, ALState.OP)
        if want != ALState.OP or (self._nmt is not None and d.slave in self._nmt.slaves):
            return f"slave {d.slave} not operational (AL {d.al.state.wire_name}, nmt in progress or stopped)"
        return ""

    def _apply_drive(self, cmd: DriveCommand, now_ns: int) -> None:
        hops.stamp("cy.apply")
        now_s = now_ns / 1e9
        start_ns = cmd.received_ns or now_ns
        deadline = start_ns + int(cmd.timeout_s * 1e9)
        if cmd.op == "move" and (cmd.args.get("sync") or cmd.args.get("targets") is not None):
            self._group_move(cmd, now_ns)
            return
        seen: set[str] = set()
        for axis in cmd.axes:
            if axis in seen:
                continue
            seen.add(axis)
            d = self._by_axis.get(axis)
            if d is None:
                self._outcome(cmd, Outcome(axis=axis, outcome="rejected", reason=f"no axis {axis!r} on {self.config.host}"))
                continue
            why = self._refusal(d)
            if why:
                self._reply(d, cmd, "rejected", why, now_ns, start_ns)
                continue
            op = cmd.op
            kind = None
            if op in MOTION_OPS:
                self._motion_command(d, cmd, now_ns)
                continue
            if op in GOAL_OF_OP and GOAL_OF_OP[op] is not Goal.ENABLED:
                # Still following the profile (decelerating) until the drive leaves Operation enabled.
                self._motion_abort(d, f"{op} ({cmd.request_id})", now_ns)
            if op in GOAL_OF_OP:
                d.ctrl.set_goal(GOAL_OF_OP[op], now_s)
                kind = "goal"
            elif op == "fault_reset":
                if d.state in FAULT_STATES or decode_statusword(d.inputs.statusword) in FAULT_STATES:
                    d.ctrl.request_fault_reset(now_s)
                    d.auto_attempts = 0
                    kind = "fault_reset"
                else:
                    # Idempotent: the aim (no fault) holds already. See docs/agent-cycle.md.
                    self._supersede(d, cmd, now_ns)
                    self._reply(d, cmd, "done", "not in fault: nothing to reset", now_ns, start_ns)
                    continue
            elif op == "set_mode":
                mode = cmd.args.get("mode")
                if not isinstance(mode, int) or isinstance(mode, bool) or mode not in VALID_MODES:
                    self._reply(d, cmd, "rejected", f"mode {mode!r} is not a CiA 402 mode (0x6060)", now_ns, start_ns)
                    continue
                sup = d.ctrl.supported_modes
                if sup is not None and mode not in sup:
                    # Known from 0x6502 at start-up: rejected now, nothing sent, nothing superseded.
                    self._reply(d, cmd, "rejected", f"mode {mode} ({Mode(mode).name.lower()}) is not supported by the "
                                f"drive (0x6502: modes {sorted(sup)})", now_ns, start_ns)
                    continue
                if d.motion.plan is not None or d.motion.homing is not None:
                    self._reply(d, cmd, "rejected", f"axis in motion ({d.motion.axis_state.value}): halt or stop it "
                                "before changing the mode", now_ns, start_ns)
                    continue
                d.ctrl.request_mode(mode, now_s)
                kind = "mode"
            elif op == "halt":
                on = cmd.args.get("on", True)
                if not isinstance(on, bool):
                    self._reply(d, cmd, "rejected", f"halt 'on' must be a boolean, got {on!r}", now_ns, start_ns)
                    continue
                if on:
                    self._motion_abort(d, f"halt ({cmd.request_id})", now_ns)
                d.ctrl.set_halt(on)  # controlword bit 8, written this cycle
                self._reply(d, cmd, "done", f"halt {'on' if on else 'off'}", now_ns, start_ns)
                continue
            else:
                self._reply(d, cmd, "rejected", f"op {op!r} is not a drive command of the cycle", now_ns, start_ns)
                continue
            self._supersede(d, cmd, now_ns)
            d.pending = Pending(cmd=cmd, kind=kind, start_cycle=self.cycles, start_ns=start_ns, deadline_ns=deadline)

    def _supersede(self, d: Drive, cmd: DriveCommand, now_ns: int) -> None:
        if d.pending is not None:
            self._resolve(d, "failed", f"superseded by {cmd.request_id}", now_ns)

    def _reply(self, d: Drive, cmd: DriveCommand, outcome: str, reason: str, now_ns: int, start_ns: int,
               start_cycle: int | None = None, duration_s: float = 0.0) -> None:
        # a lost drive's state and error code are unknown: its inputs are old
        state, error_code = ("unknown", 0) if d.lost else (d.state.value, d.inputs.error_code)
        o = Outcome(axis=d.axis, outcome=outcome, state=state, error_code=error_code,
                    reason=reason, elapsed_s=max(0.0, (now_ns - start_ns) / 1e9),
                    cycles=self.cycles - (start_cycle if start_cycle is not None else self.cycles),
                    duration_s=duration_s)
        self._event(d.axis, "outcome", f"{cmd.op} {outcome}" + (f": {reason}" if reason else ""),
                    to_state=state, error_code=error_code, request_id=cmd.request_id)
        self._outcome(cmd, o)
        hops.stamp("cy.outcome")

    def _resolve(self, d: Drive, outcome: str, reason: str, now_ns: int) -> None:
        p = d.pending
        if p is None:
            return
        d.pending = None
        self._reply(d, p.cmd, outcome, reason, now_ns, p.start_ns, p.start_cycle)

    @staticmethod
    def _outcome(cmd: DriveCommand | AgentCommand, outcome: Outcome) -> None:
        try:
            cmd.on_outcome(outcome)
        except Exception:
            log.exception("on_outcome callback of %s failed", cmd.request_id)

    def _controller_events(self, d: Drive, evs: Sequence[ControllerEvent], prev: State, now_ns: int) -> None:
        p = d.pending
        for ev in evs:
            k = ev.kind
            if k == EventKind.TRANSITION:
                self._event(d.axis, "transition", ev.reason, from_state=ev.from_state.value,
                            to_state=ev.to_state.value)
            elif k == EventKind.FAULT:
                self._event(d.axis, "fault", ev.reason or f"error code 0x{d.inputs.error_code:04X}",
                            from_state=ev.from_state.value, to_state=ev.to_state.value,
                            error_code=d.inputs.error_code)
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
                self._resolve(d, outcome, reason, now_ns)

    def _auto_reset(self, d: Drive, now_ns: int) -> None:
        a = d.cfg.policy.auto_reset
        if not a.enabled:
            return
        if d.state != State.FAULT:
            if d.auto_attempts and now_ns - d.last_fault_ns > a.window_s * 1e9:
                d.auto_attempts = 0
                d.auto_exhausted = False
            return
        if d.pending is not None:
            return
        if d.auto_attempts >= a.max_attempts:
            if not d.auto_exhausted:
                d.auto_exhausted = True
                self._event(d.axis, "warning", f"auto fault reset: {a.max_attempts} attempts exhausted, "
                            "waiting for a fault_reset command", error_code=d.inputs.error_code)
            return
        wait_s = min(a.backoff_s * (2 ** d.auto_attempts), a.backoff_max_s)
        if now_ns - d.fault_since_ns >= wait_s * 1e9:
            d.auto_attempts += 1
            d.fault_since_ns = now_ns
            d.ctrl.request_fault_reset(now_ns / 1e9)
            self._event(d.axis, "warning", f"auto fault reset attempt {d.auto_attempts}/{a.max_attempts}",
                        error_code=d.inputs.error_code)

    def _reflex(self, group: str, origin_axis: str | None, reason: str, now_ns: int) -> None:
        goal = Goal.QUICK_STOP if self.config.reflex == "quick_stop" else Goal.DISABLED
        for axis in self.groups.reacting(group, origin_axis):
            d = self._by_axis[axis]
            if d.lost:
                continue
            if d.pending is not None:
                self._resolve(d, "failed", f"group {group} reflex: {reason}", now_ns)
            self._motion_abort(d, f"group {group} reflex: {reason}", now_ns)
            d.ctrl.set_goal(goal, now_ns / 1e9)
            self._event(axis, "reflex", f"group {group}: {goal.value} ({reason})", from_state=d.state.value)

    def _express(self, now_ns: int) -> None:
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
        frame. It is not a cycle: no period, statistics, DC step (the PI sees only the
        scheduled frames; docs/agent-cycle.md, Timing) or management work. Its events go out at
        once in a snapshot stamped before the exchange, numbered as the last cycle. Cycle thread."""
        events = self._events = []
        reacting: dict[str, None] = {}
        while self._triggers:
            g, reason = self._triggers.popleft()
            self._reflex(g, None, f"remote: {reason}", now_ns)
            reacting.update(dict.fromkeys(self.groups.reacting(g)))
        now_s = now_ns / 1e9
        bus = self.bus
        changed = False
        for axis in reacting:
            d = self._by_axis[axis]
            if d.lost:
                continue
            out = d.ctrl.step(d.inputs.statusword, d.inputs.modes_of_operation_display, now_s)
            if out.events:
                self._controller_events(d, out.events, d.state, now_ns)
            cw = out.controlword | d.motion.controlword_bits
            if cw != d.controlword:
                o = d.out
                o.controlword = d.controlword = cw
                bus.set_outputs(d.slave, o)
                changed = True
        time_ns = self._wall_ns()  # the reflex's time: when it was applied, before the frame
        if changed and self._express_allowed(reacting):
            bus.exchange()  # first: the snapshot can wait a frame's round trip, the drive not
            hops.stamp("cy.express")
            self.express_exchanges += 1
        snap = CycleSnapshot(cycle=self.cycles, time_ns=time_ns, drives=self._drive_snapshots(),
                             events=tuple(events), stats=self._stats, agent_state=self.state)
        self._express_events += events
        self.latest = snap
        sink = self.snapshot_sink
        if sink is not None:
            sink(snap)

    def _express_allowed(self, reacting: Iterable[str]) -> bool:
        """An extra exchange may go out now: the bus has one (not CANopen, whose exchange sends a
        SYNC) and no drive but the ``reacting`` ones follows a trajectory (see :meth:`_express`)."""
        if not getattr(self.bus, "express_exchange", False):
            return False
        reacting = set(reacting)
        return not any(d.motion.plan is not None for d in self.drives if not d.lost and d.axis not in reacting)

    def _express_after_cycle(self, reacting: dict[str, int]) -> None:
        """Reflexes applied by the cycle itself: a local member's fault or loss, or remote
        triggers that came during the spin or the cycle's work (not in the sleep). Their outputs
        go out in an extra exchange right after the cycle, not with the next scheduled frame a
        period later. ``reacting``: the reacting axes and their controlwords before the cycle;
        nothing is sent when none changed."""
        if not any(self._by_axis[a].controlword != cw for a, cw in reacting.items() if not self._by_axis[a].lost):
            return
        if self._express_allowed(reacting):
            self.bus.exchange()
            hops.stamp("cy.express")
            self.express_exchanges += 1

    def _event(self, axis: str, kind: str, detail: str = "", *, from_state: str = "unknown",
               to_state: str = "unknown", error_code: int = 0, request_id: str = "") -> None:
        self._events.append(CycleEvent(axis=axis, kind=kind, detail=detail, from_state=from_state,
                                       to_state=to_state, error_code=error_code, request_id=request_id))
