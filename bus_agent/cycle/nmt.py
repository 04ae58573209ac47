"""The ``nmt`` agent op on EtherCAT (AL states) and CAN (NMT frames): docs/cia402.md section 5.

The :class:`NmtMixin` part of :class:`bus_agent.cycle.cycle.Cycle` (cycle thread only). Leaving
OP first takes the drives on the addressed slaves down by the ordered sequence; AL requests and
recovery run in the management thread; one terminal outcome per command.
"""

from __future__ import annotations

import logging

from bus_agent.bus.base import ALState
from bus_agent.cia402.controller import Goal
from bus_agent.cia402.states import State
from bus_agent.cycle.base import CycleBase
from bus_agent.cycle.drive import NmtRun
from bus_agent.runtime import AgentCommand, CycleEvent, Outcome

log = logging.getLogger("bus_agent.cycle.cycle")

NMT_TARGET = {"start": ALState.OP, "stop": ALState.SAFEOP, "preop": ALState.PREOP,
              "reset_comm": ALState.PREOP, "reset_node": ALState.OP}


class NmtMixin(CycleBase):
    """NMT commands stepped once per cycle."""

    def _apply_agent(self, cmd: AgentCommand, now_ns: int) -> None:
        if cmd.op != "nmt":
            self._outcome(cmd, Outcome(axis="", outcome="rejected", reason=f"agent op {cmd.op!r} unknown"))
            return
        command = cmd.args.get("command")
        if command not in NMT_TARGET:
            self._outcome(cmd, Outcome(axis="", outcome="rejected",
                                       reason=f"nmt command {command!r} is not one of {', '.join(NMT_TARGET)}"))
            return
        axis = cmd.args.get("axis")
        if axis is not None and axis != "":
            d = self._by_axis.get(axis)
            if d is None:
                self._outcome(cmd, Outcome(axis="", outcome="rejected", reason=f"no axis {axis!r} on {self.config.host}"))
                return
            slaves: tuple[int, ...] = (d.slave,)
        else:
            slaves = tuple(range(len(self.slaves)))
        if self._nmt is not None:
            self._finish_nmt("failed", f"superseded by {cmd.request_id}", now_ns)
        start_ns = cmd.received_ns or now_ns
        down_s = max([d.cfg.policy.transition_timeout_s for d in self.drives if d.slave in slaves] or [1.0])
        self._nmt = NmtRun(cmd=cmd, command=command, slaves=slaves, phase="bring_down", start_cycle=self.cycles,
                         start_ns=start_ns, deadline_ns=start_ns + int(cmd.timeout_s * 1e9),
                         down_deadline_ns=now_ns + int(down_s * 1e9))
        if command != "start":
            # Leaving OP: drives on these slaves are first taken down by the ordered sequence.
            for d in self.drives:
                if d.slave in slaves:
                    if d.pending is not None:
                        self._resolve(d, "failed", f"nmt {command} ({cmd.request_id})", now_ns)
                    self._motion_abort(d, f"nmt {command} ({cmd.request_id})", now_ns)
                    d.ctrl.set_halt(False)
                    d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
        else:
            self._enter_nmt_recover(self._nmt)
        self._nmt.ticket = self._mgmt.tickets
        self._mgmt.kick()

    def _enter_nmt_recover(self, n: NmtRun) -> None:
        n.phase = "recover"
        for s in n.slaves:
            self._desired_al[s] = ALState.OP
            self._epoch[s] = self._epoch.get(s, 0) + 1
        self._update_recover_set()

    def _step_nmt(self, now_ns: int) -> None:
        n = self._nmt
        assert n is not None
        if now_ns >= n.deadline_ns:
            self._finish_nmt("timeout", f"nmt {n.command} not done within {n.cmd.timeout_s:g} s ({n.phase})", now_ns)
            return
        mgmt = self._mgmt
        if n.phase == "bring_down":
            up = [d for d in self.drives if d.slave in n.slaves and not d.lost
                  and d.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.SWITCHED_ON,
                                  State.READY_TO_SWITCH_ON)]
            if up and now_ns < n.down_deadline_ns:
                return
            if up:
                n.note = f"; drives not down in time: {', '.join(d.axis for d in up)}"
            for s in n.slaves:
                self._desired_al[s] = NMT_TARGET[n.command] if n.command in ("stop", "preop") else ALState.INIT
            if n.command in ("stop", "preop"):
                target = NMT_TARGET[n.command]
                for s in n.slaves:
                    if self._al_status[s].state != target:
                        n.ticket = mgmt.request_state(s, target)
                n.phase = "to_target"
            else:
                for s in n.slaves:
                    n.ticket = mgmt.request_state(s, ALState.INIT, nmt=n.command)  # CAN: reset node / comm.
                n.phase = "to_init"
            return
        if self._al_ticket < n.ticket:
            return  # no AL status read since the last request was written
        states = [self._al_status[s] for s in n.slaves]
        if n.phase == "to_init":
            if all(st.state == ALState.INIT for st in states):
                if n.command == "reset_comm":
                    for s in n.slaves:
                        self._desired_al[s] = ALState.PREOP
                        n.ticket = mgmt.request_state(s, ALState.PREOP)
                    n.phase = "to_target"
                else:  # reset_node: full reconfiguration back to OP (management thread)
                    self._enter_nmt_recover(n)
            return
        if n.phase == "to_target":
            target = self._desired_al[n.slaves[0]]
            if all(st.state == target and not st.error for st in states):
                self._finish_nmt("done", f"AL {target.wire_name}{n.note}", now_ns)
            return
        if n.phase == "recover":
            # The management thread recovers the slaves (recover set); reports set _al_status.
            if all(self._al_status[s].state == ALState.OP and not self._al_status[s].error for s in n.slaves):
                for d in self.drives:
                    if d.slave in n.slaves:
                        d.lost = False
                        d.al = self._al_status[d.slave]
                self._finish_nmt("done", f"AL op; goals stay disabled{n.note}", now_ns)
                self._update_recover_set()

    def _finish_nmt(self, outcome: str, reason: str, now_ns: int) -> None:
        n = self._nmt
        if n is None:
            return
        self._nmt = None
        if outcome != "done":
            # Leave the AL states where they are, and watch them from now on.
            for s in n.slaves:
                self._desired_al[s] = self._al_status[s].state if outcome != "failed" else self._desired_al[s]
        log.info("host %s: nmt %s %s: %s", self.config.host, n.command, outcome, reason)
        self._events.append(CycleEvent(axis="", kind="al_state", detail=f"nmt {n.command} {outcome}: {reason}",
                                       request_id=n.cmd.request_id))
        self._outcome(n.cmd, Outcome(axis="", outcome=outcome, reason=reason,
                                     elapsed_s=max(0.0, (now_ns - n.start_ns) / 1e9),
                                     cycles=self.cycles - n.start_cycle))
