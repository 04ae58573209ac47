"""Drive and agent commands applied at the start of a cycle.

:class:`Commands` (cycle thread only) takes the commands queued in the
:class:`~bus_agent.cycle.outcomes.CommandBook` and applies them: a goal, a mode, a fault reset or
halt to a drive's controller (its outcome when the controller reports it), a motion op to the
:class:`~bus_agent.cycle.motion.MotionStage`, an agent (``nmt``) command to
:class:`~bus_agent.cycle.nmt.Nmt`. Every addressed axis gets exactly one outcome.
"""

from __future__ import annotations

import logging
from typing import Sequence

from bus_agent import hops
from bus_agent.cia402.controller import Goal
from bus_agent.cia402.states import Mode, decode_statusword
from bus_agent.cycle.drive import FAULT_STATES, VALID_MODES, Drive, Pending, Segment
from bus_agent.cycle.motion import MotionStage
from bus_agent.cycle.nmt import Nmt
from bus_agent.cycle.outcomes import CommandBook, send_outcome
from bus_agent.cycle.slaves import SlaveHealth
from bus_agent.cycle.stats import Statistics
from bus_agent.motion.axis import MOTION_OPS
from bus_agent.runtime import AgentCommand, DriveCommand, Outcome

log = logging.getLogger("bus_agent.cycle.cycle")

GOAL_OF_OP = {
    "enable": Goal.ENABLED,
    "switch_on": Goal.SWITCHED_ON,
    "shutdown": Goal.READY,
    "disable": Goal.DISABLED,
    "quick_stop": Goal.QUICK_STOP,
}


class Commands:
    """Applying the queued commands."""

    def __init__(self, seg: Segment, book: CommandBook, motion: MotionStage, health: SlaveHealth, nmt: Nmt,
                 stats: Statistics) -> None:
        self._seg = seg
        self._book = book
        self._motion = motion
        self._health = health
        self._nmt = nmt
        self._stats = stats

    def refusal(self, d: Drive) -> str:
        """Why no command can act on ``d`` now ('' if one can)."""
        return self._health.refusal(d, self._nmt.run)

    def apply(self, cmds: Sequence[DriveCommand | AgentCommand], now_ns: int) -> None:
        """Apply ``cmds`` (taken from the command book), in order."""
        for cmd in cmds:
            try:
                if isinstance(cmd, AgentCommand):
                    self._nmt.apply(cmd, now_ns)
                else:
                    self._apply_drive(cmd, now_ns)
            except Exception as e:  # a bad command must not stop the loop
                log.exception("host %s: command %s failed", self._seg.host, getattr(cmd, "request_id", "?"))
                if isinstance(cmd, AgentCommand):
                    send_outcome(cmd, Outcome(axis="", outcome="rejected", reason=f"internal error: {e}"))

    def _apply_drive(self, cmd: DriveCommand, now_ns: int) -> None:
        hops.stamp("cy.apply")
        now_s = now_ns / 1e9
        start_ns = cmd.received_ns or now_ns
        deadline = start_ns + int(cmd.timeout_s * 1e9)
        if cmd.op == "move" and (cmd.args.get("sync") or cmd.args.get("targets") is not None):
            self._motion.group_move(cmd, now_ns, self.refusal)
            return
        book = self._book
        reply = book.reply
        seen: set[str] = set()
        for axis in cmd.axes:
            if axis in seen:
                continue
            seen.add(axis)
            d = self._seg.by_axis.get(axis)
            if d is None:
                send_outcome(cmd, Outcome(axis=axis, outcome="rejected", reason=f"no axis {axis!r} on {self._seg.host}"))
                continue
            why = self.refusal(d)
            if why:
                reply(d, cmd, "rejected", why, now_ns, start_ns)
                continue
            op = cmd.op
            kind = None
            if op in MOTION_OPS:
                self._motion.command(d, cmd, now_ns)
                continue
            if op in GOAL_OF_OP and GOAL_OF_OP[op] is not Goal.ENABLED:
                # Still following the profile (decelerating) until the drive leaves Operation enabled.
                self._motion.abort(d, f"{op} ({cmd.request_id})", now_ns)
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
                    book.supersede(d, cmd, now_ns)
                    reply(d, cmd, "done", "not in fault: nothing to reset", now_ns, start_ns)
                    continue
            elif op == "set_mode":
                mode = cmd.args.get("mode")
                if not isinstance(mode, int) or isinstance(mode, bool) or mode not in VALID_MODES:
                    reply(d, cmd, "rejected", f"mode {mode!r} is not a CiA 402 mode (0x6060)", now_ns, start_ns)
                    continue
                sup = d.ctrl.supported_modes
                if sup is not None and mode not in sup:
                    # Known from 0x6502 at start-up: rejected now, nothing sent, nothing superseded.
                    reply(d, cmd, "rejected", f"mode {mode} ({Mode(mode).name.lower()}) is not supported by the "
                          f"drive (0x6502: modes {sorted(sup)})", now_ns, start_ns)
                    continue
                if d.motion.plan is not None or d.motion.homing is not None:
                    reply(d, cmd, "rejected", f"axis in motion ({d.motion.axis_state.value}): halt or stop it "
                          "before changing the mode", now_ns, start_ns)
                    continue
                d.ctrl.request_mode(mode, now_s)
                kind = "mode"
            elif op == "halt":
                on = cmd.args.get("on", True)
                if not isinstance(on, bool):
                    reply(d, cmd, "rejected", f"halt 'on' must be a boolean, got {on!r}", now_ns, start_ns)
                    continue
                if on:
                    self._motion.abort(d, f"halt ({cmd.request_id})", now_ns)
                d.ctrl.set_halt(on)  # controlword bit 8, written this cycle
                reply(d, cmd, "done", f"halt {'on' if on else 'off'}", now_ns, start_ns)
                continue
            else:
                reply(d, cmd, "rejected", f"op {op!r} is not a drive command of the cycle", now_ns, start_ns)
                continue
            book.supersede(d, cmd, now_ns)
            d.pending = Pending(cmd=cmd, kind=kind, start_cycle=self._stats.cycles, start_ns=start_ns,
                                deadline_ns=deadline)
