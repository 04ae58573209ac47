"""The ``nmt`` agent op on EtherCAT (AL states) and CAN (NMT frames): docs/cia402.md section 5.

:class:`Nmt` (cycle thread only) runs one NMT command at a time (:attr:`Nmt.run`). Leaving OP
first takes the drives on the addressed slaves down by the ordered sequence; AL requests and
recovery run in the management thread; the AL states wanted and read are the
:class:`~bus_agent.cycle.slaves.SlaveHealth`'s; one terminal outcome per command.
"""

from __future__ import annotations

import logging

from bus_agent.bus.base import ALState
from bus_agent.cia402.controller import Goal
from bus_agent.cia402.states import State
from bus_agent.cycle.drive import NmtRun, Segment
from bus_agent.cycle.events import EventLog
from bus_agent.cycle.management import Management
from bus_agent.cycle.motion import MotionStage
from bus_agent.cycle.outcomes import CommandBook, send_outcome
from bus_agent.cycle.slaves import SlaveHealth
from bus_agent.cycle.stats import Statistics
from bus_agent.runtime import AgentCommand, CycleEvent, Outcome

log = logging.getLogger("bus_agent.cycle.cycle")

NMT_TARGET = {"start": ALState.OP, "stop": ALState.SAFEOP, "preop": ALState.PREOP,
              "reset_comm": ALState.PREOP, "reset_node": ALState.OP}
#: Drive states that are not down yet for an NMT command leaving OP.
_UP_STATES = (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.SWITCHED_ON, State.READY_TO_SWITCH_ON)


class Nmt:
    """NMT commands, stepped once per cycle."""

    def __init__(self, seg: Segment, health: SlaveHealth, book: CommandBook, motion: MotionStage,
                 mgmt: Management, events: EventLog, stats: Statistics) -> None:
        self._seg = seg
        self._health = health
        self._book = book
        self._motion = motion
        self._mgmt = mgmt
        self._events = events
        self._stats = stats
        #: The NMT command in progress, if any.
        self.run: NmtRun | None = None

    def apply(self, cmd: AgentCommand, now_ns: int) -> None:
        """An agent command (``nmt``; anything else is rejected)."""
        if cmd.op != "nmt":
            send_outcome(cmd, Outcome(axis="", outcome="rejected", reason=f"agent op {cmd.op!r} unknown"))
            return
        command = cmd.args.get("command")
        if command not in NMT_TARGET:
            send_outcome(cmd, Outcome(axis="", outcome="rejected",
                                      reason=f"nmt command {command!r} is not one of {', '.join(NMT_TARGET)}"))
            return
        seg = self._seg
        axis = cmd.args.get("axis")
        if axis is not None and axis != "":
            d = seg.by_axis.get(axis)
            if d is None:
                send_outcome(cmd, Outcome(axis="", outcome="rejected", reason=f"no axis {axis!r} on {seg.host}"))
                return
            slaves: tuple[int, ...] = (d.slave,)
        else:
            slaves = tuple(range(len(seg.slaves)))
        if self.run is not None:
            self.finish("failed", f"superseded by {cmd.request_id}", now_ns)
        start_ns = cmd.received_ns or now_ns
        down_s = max([d.cfg.policy.transition_timeout_s for d in seg.drives if d.slave in slaves] or [1.0])
        n = self.run = NmtRun(cmd=cmd, command=command, slaves=slaves, phase="bring_down",
                              start_cycle=self._stats.cycles, start_ns=start_ns,
                              deadline_ns=start_ns + int(cmd.timeout_s * 1e9),
                              down_deadline_ns=now_ns + int(down_s * 1e9))
        if command != "start":
            # Leaving OP: drives on these slaves are first taken down by the ordered sequence.
            for d in seg.drives:
                if d.slave in slaves:
                    if d.pending is not None:
                        self._book.resolve(d, "failed", f"nmt {command} ({cmd.request_id})", now_ns)
                    self._motion.abort(d, f"nmt {command} ({cmd.request_id})", now_ns)
                    d.ctrl.set_halt(False)
                    d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
        else:
            self._enter_recover(n)
        n.ticket = self._mgmt.tickets
        self._mgmt.kick()

    def _enter_recover(self, n: NmtRun) -> None:
        n.phase = "recover"
        health = self._health
        for s in n.slaves:
            health.desired_al[s] = ALState.OP
            health.epoch[s] = health.epoch.get(s, 0) + 1
        health.update_recover_set(n)

    def step(self, now_ns: int) -> None:
        """Once per cycle while a command runs: its next phase when the last one is done."""
        n = self.run
        assert n is not None
        if now_ns >= n.deadline_ns:
            self.finish("timeout", f"nmt {n.command} not done within {n.cmd.timeout_s:g} s ({n.phase})", now_ns)
            return
        mgmt = self._mgmt
        health = self._health
        desired, al_status = health.desired_al, health.al_status
        if n.phase == "bring_down":
            up = [d for d in self._seg.drives if d.slave in n.slaves and not d.lost and d.state in _UP_STATES]
            if up and now_ns < n.down_deadline_ns:
                return
            if up:
                n.note = f"; drives not down in time: {', '.join(d.axis for d in up)}"
            for s in n.slaves:
                desired[s] = NMT_TARGET[n.command] if n.command in ("stop", "preop") else ALState.INIT
            if n.command in ("stop", "preop"):
                target = NMT_TARGET[n.command]
                for s in n.slaves:
                    if al_status[s].state != target:
                        n.ticket = mgmt.request_state(s, target)
                n.phase = "to_target"
            else:
                for s in n.slaves:
                    n.ticket = mgmt.request_state(s, ALState.INIT, nmt=n.command)  # CAN: reset node / comm.
                n.phase = "to_init"
            return
        if health.al_ticket < n.ticket:
            return  # no AL status read since the last request was written
        states = [al_status[s] for s in n.slaves]
        if n.phase == "to_init":
            if all(st.state == ALState.INIT for st in states):
                if n.command == "reset_comm":
                    for s in n.slaves:
                        desired[s] = ALState.PREOP
                        n.ticket = mgmt.request_state(s, ALState.PREOP)
                    n.phase = "to_target"
                else:  # reset_node: full reconfiguration back to OP (management thread)
                    self._enter_recover(n)
            return
        if n.phase == "to_target":
            target = desired[n.slaves[0]]
            if all(st.state == target and not st.error for st in states):
                self.finish("done", f"AL {target.wire_name}{n.note}", now_ns)
            return
        if n.phase == "recover":
            # The management thread recovers the slaves (recover set); reports set the AL status.
            if all(al_status[s].state == ALState.OP and not al_status[s].error for s in n.slaves):
                for d in self._seg.drives:
                    if d.slave in n.slaves:
                        d.lost = False
                        d.al = al_status[d.slave]
                self.finish("done", f"AL op; goals stay disabled{n.note}", now_ns)
                health.update_recover_set(None)

    def finish(self, outcome: str, reason: str, now_ns: int) -> None:
        """End the running command (if any) with ``outcome``."""
        n = self.run
        if n is None:
            return
        self.run = None
        health = self._health
        if outcome != "done":
            # Leave the AL states where they are, and watch them from now on.
            for s in n.slaves:
                health.desired_al[s] = health.al_status[s].state if outcome != "failed" else health.desired_al[s]
        health.wanted_changed()
        log.info("host %s: nmt %s %s: %s", self._seg.host, n.command, outcome, reason)
        self._events.append(CycleEvent(axis="", kind="al_state", detail=f"nmt {n.command} {outcome}: {reason}",
                                       request_id=n.cmd.request_id))
        send_outcome(n.cmd, Outcome(axis="", outcome=outcome, reason=reason,
                                    elapsed_s=max(0.0, (now_ns - n.start_ns) / 1e9),
                                    cycles=self._stats.cycles - n.start_cycle))
