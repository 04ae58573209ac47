"""AL state of the slaves, lost and found: the management thread's reports applied in the cycle.

The :class:`SlavesMixin` part of :class:`bus_agent.cycle.cycle.Cycle` (cycle thread only). A
slave not in its wanted AL state is lost (a missing answer only after
:data:`NO_ANSWER_CONFIRM_CYCLES`); its drives get goal DISABLED and their groups react. A slave
brought back to OP by the management thread is found only once the working counter has proven
its process data for several cycles (:mod:`bus_agent.cycle.found`), with its goal still DISABLED;
until then its drives stay lost.
"""

from __future__ import annotations

import logging
from typing import Sequence

from bus_agent.bus.base import ALState, SlaveALStatus, al_status_text
from bus_agent.cia402.controller import Goal
from bus_agent.cia402.states import decode_statusword
from bus_agent.cycle.base import CycleBase
from bus_agent.cycle.drive import FAULT_STATES, Drive

log = logging.getLogger("bus_agent.cycle.cycle")

#: A slave that does not answer the AL status read is lost only when it still does not answer
#: this many cycles later (a later poll): a few dropped or late frames are not a lost slave.
NO_ANSWER_CONFIRM_CYCLES = 8


class SlavesMixin(CycleBase):
    """AL status, SDO results, lost and found slaves."""

    def _apply_reports(self, now_ns: int) -> None:
        """Reports of the management thread, in the order they were made."""
        reports = self._mgmt.reports
        while reports:
            r = reports.popleft()
            if r[0] == "al":
                self._apply_al(r[1], r[2], now_ns)
            elif r[0] == "sdo":
                self._apply_sdo(r[1], r[2], r[3], r[4], r[5], now_ns)
            else:
                self._apply_returned(r[1], r[2], now_ns)

    def _apply_sdo(self, slave: int, what: str, value: int | None, error: str, definite: bool, now_ns: int) -> None:
        """A result of an SDO job (objects the drive does not map)."""
        for d in self.drives:
            if d.slave != slave:
                continue
            if what == "error_code" and value is None and definite and d.error_code_readable:
                # 0x603F refused (0x06020000: the drive has no such object): from now on the
                # error code is the drive's last emergency's
                d.error_code_readable = False
                log.warning("axis %s: 0x603F not readable (%s): error codes from the drive's emergencies",
                            d.axis, error)
                if d.state in FAULT_STATES and d.last_emcy_code and d.error_code_sdo != d.last_emcy_code:
                    d.error_code_sdo = d.last_emcy_code
                continue
            if what == "mode_display" and value is not None:
                d.mode_display_sdo = value
            elif what == "error_code" and value is not None:
                if value and d.state in FAULT_STATES:  # once per fault: its job reads once
                    self._event(d.axis, "fault", f"0x603F = 0x{value:04X} (read by SDO: not in the PDO mapping)",
                                to_state=d.state.value, error_code=value)
                d.error_code_sdo = value
            elif what == "written":
                self._motion_finished(d, d.motion.sdo_written(error), now_ns)
            elif what == "mode_write" and d.pending is not None and d.pending.kind == "mode":
                self._resolve(d, "failed", f"0x6060 = {d.mode_written} by SDO refused: {error}", now_ns)
            elif error:
                log.warning("axis %s: SDO %s: %s", d.axis, what, error)

    def _apply_al(self, statuses: Sequence[SlaveALStatus] | None, ticket: int, now_ns: int) -> None:
        self._last_al_poll = self.cycles
        self._al_ticket = ticket
        if statuses is None:
            statuses = [SlaveALStatus(ALState.NONE, False, 0)] * len(self.slaves)
        ok = True
        nmt_slaves = self._nmt.slaves if self._nmt is not None else ()
        for pos, st in enumerate(statuses):
            old = self._al_status[pos] if pos < len(self._al_status) else None
            if pos < len(self._al_status):
                self._al_status[pos] = st
            if old is not None and (old.state != st.state or old.error != st.error):
                for d in self.drives:
                    if d.slave == pos:
                        self._event(d.axis, "al_state", f"slave {pos} AL {old.state.wire_name} -> {st.state.wire_name}"
                                    + (" (no answer)" if st.state == ALState.NONE else "")
                                    + (f" error 0x{st.status_code:04X} {al_status_text(st.status_code)}" if st.error else ""),
                                    error_code=st.status_code if st.error else 0)
            want = self._desired_al.get(pos, ALState.OP)
            if st.state != want or st.error:
                ok = False
            if st.state != ALState.NONE:
                self._no_answer_since.pop(pos, None)
        confirm_ns = NO_ANSWER_CONFIRM_CYCLES * self.period_ns
        lost_now = False
        for d in self.drives:
            d.al = self._al_status[d.slave]
            want = self._desired_al.get(d.slave, ALState.OP)
            gone = d.al.state != want or (d.al.error and want == ALState.OP)
            if gone and d.lost and self._found.waiting(d.slave):
                # back in OP, not yet proven by the working counter, and gone again: recover anew
                self._found.cancel(d.slave)
                self._epoch[d.slave] = self._epoch.get(d.slave, 0) + 1
                lost_now = True
            if gone and not d.lost and d.slave not in nmt_slaves:
                if d.al.state == ALState.NONE:
                    # No answer: lost only if a later read confirms it (not a dropped frame).
                    since = self._no_answer_since.setdefault(d.slave, now_ns)
                    if now_ns - since < confirm_ns:
                        continue
                self._mark_lost(d, now_ns)
                lost_now = True
        self._al_poll_ok = ok
        if lost_now:
            self._update_recover_set()

    def _mark_lost(self, d: Drive, now_ns: int) -> None:
        st = d.al
        why = (f"slave {d.slave} AL {st.state.wire_name}"
               + (f" error 0x{st.status_code:04X} {al_status_text(st.status_code)}" if st.error else "")
               + f", working counter {self._last_wkc}/{self.bus.expected_wkc}")
        d.lost = True
        d.lost_reason = f"lost: {why}"
        self._no_answer_since.pop(d.slave, None)
        self._epoch[d.slave] = self._epoch.get(d.slave, 0) + 1
        log.warning("drive %s/%s lost: %s", self.config.host, d.axis, why)
        self._event(d.axis, "lost", why, from_state=d.state.value, error_code=st.status_code if st.error else 0)
        if d.pending is not None:
            self._resolve(d, "failed", f"slave lost: {why}", now_ns)
        self._motion_abort(d, f"slave lost: {why}", now_ns, drop=True)
        # Never re-enabled without a new command once it returns.
        d.ctrl.set_halt(False)
        d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
        for g in self.groups.of_axis(d.axis):
            self._lost_origins.append((g, f"{self.config.host}/{d.axis} lost ({why})"))

    def _update_recover_set(self) -> None:
        """Tell the management thread which slaves to bring back to OP: lost ones wanted in OP
        (while running) and those of an NMT command in its recover phase."""
        keys: set[tuple[int, int]] = set()
        if self.state == "running":
            for d in self.drives:
                if d.lost and self._desired_al.get(d.slave) == ALState.OP:
                    keys.add((d.slave, self._epoch.get(d.slave, 0)))
        n = self._nmt
        if n is not None and n.phase == "recover":
            for s in n.slaves:
                st = self._al_status[s]
                if st.state != ALState.OP or st.error:
                    keys.add((s, self._epoch.get(s, 0)))
        fs = frozenset(keys)
        if fs != self._mgmt.recover_set:
            self._mgmt.recover_set = fs
            self._mgmt.wake()

    def _apply_returned(self, slave: int, epoch: int, now_ns: int) -> None:
        """A slave of the recover set is back in OP: it waits for the working counter's proof
        (:meth:`_confirm_found`); its drives stay lost until then."""
        if epoch != self._epoch.get(slave, 0):
            return  # lost again since that recovery began
        self._al_status[slave] = SlaveALStatus(ALState.OP, False, 0)
        self._no_answer_since.pop(slave, None)
        for other in self.drives:
            if other.slave == slave:
                other.al = self._al_status[slave]
        self._found.returned(slave, epoch)

    def _confirm_found(self, wkc: int, now_ns: int) -> bool:
        """Once per cycle while a returned slave waits: found when its process data is proven
        (:class:`bus_agent.cycle.found.FoundConfirmation`), with fresh inputs and goal DISABLED.
        True when a slave was found."""
        lost_slaves = {d.slave for d in self.drives if d.lost}
        found = self._found.step(wkc, self.bus.expected_wkc, lost_slaves, self._al_status)
        for slave in found:
            for other in self.drives:
                if other.slave != slave or not other.lost:
                    continue
                other.lost = False
                other.lost_reason = ""
                other.inputs = self.bus.inputs(slave)  # read in this cycle's proven exchange
                other.state = decode_statusword(other.inputs.statusword)
                other.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
                log.info("drive %s/%s found: slave %d in OP, process data valid for %d cycles, goal disabled",
                         self.config.host, other.axis, slave, self._found.confirm_cycles)
                self._event(other.axis, "found", f"slave {slave} back in OP with valid process data "
                            f"for {self._found.confirm_cycles} cycles; goal stays disabled",
                            to_state=other.state.value)
            self._update_recover_set()
        return bool(found)
