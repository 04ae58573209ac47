"""Slave health: AL states, the working counter, lost and found slaves.

:class:`SlaveHealth` (cycle thread only) checks each cycle's working counter, applies the
management thread's reports (AL status, SDO results, returned slaves) and keeps the AL state
wanted of each slave. A slave not in its wanted AL state is lost (a missing answer only after
:data:`NO_ANSWER_CONFIRM_CYCLES`); its drives get goal DISABLED and their groups react. A slave
brought back to OP by the management thread is found only once the working counter has proven
its process data for several cycles (:mod:`bus_agent.cycle.found`), with its goal still DISABLED;
until then its drives stay lost.
"""

from __future__ import annotations

import logging
from typing import Sequence

from bus_agent.bus.base import ALState, Bus, SlaveALStatus, al_status_text
from bus_agent.cia402.controller import Goal
from bus_agent.cia402.states import decode_statusword
from bus_agent.cycle.drive import FAULT_STATES, Drive, NmtRun, Segment
from bus_agent.cycle.events import EventLog
from bus_agent.cycle.found import FoundConfirmation
from bus_agent.cycle.management import Management
from bus_agent.cycle.motion import MotionStage
from bus_agent.cycle.outcomes import CommandBook
from bus_agent.cycle.stats import Statistics

log = logging.getLogger("bus_agent.cycle.cycle")

#: A slave that does not answer the AL status read is lost only when it still does not answer
#: this many cycles later (a later poll): a few dropped or late frames are not a lost slave.
NO_ANSWER_CONFIRM_CYCLES = 8


class SlaveHealth:
    """AL status, working counter, SDO results, lost and found slaves."""

    def __init__(self, bus: Bus, seg: Segment, mgmt: Management, book: CommandBook, motion: MotionStage,
                 events: EventLog, stats: Statistics, period_ns: int) -> None:
        self._bus = bus
        self._seg = seg
        self._mgmt = mgmt
        self._book = book
        self._motion = motion
        self._events = events
        self._stats = stats
        self._period_ns = period_ns
        #: The AL state wanted of each slave (OP, or the target of an NMT command).
        self.desired_al: dict[int, ALState] = {}
        #: The last AL status read of each slave (by position).
        self.al_status: list[SlaveALStatus] = []
        #: Recovery epoch per slave: a report of an older recovery is stale.
        self.epoch: dict[int, int] = {}
        #: The management request number the last AL status read came after.
        self.al_ticket = 0
        #: Are the lost drives' slaves to be brought back (while the agent runs)?
        self.running = False
        self._found = FoundConfirmation()
        self._no_answer_since: dict[int, int] = {}
        self._lost_origins: list[tuple[str, str]] = []
        self._al_poll_ok = True
        self._wkc_was_bad = False
        self._last_wkc = 0
        self._all_op_wanted: bool | None = None   # cached while no NMT command runs

    def start(self, slaves: int) -> None:
        """The segment is in OP: every slave wanted and read in OP."""
        self.desired_al = {i: ALState.OP for i in range(slaves)}
        self.al_status = [SlaveALStatus(ALState.OP, False, 0)] * slaves
        for d in self._seg.drives:
            d.al = self.al_status[d.slave]

    def wanted_changed(self) -> None:
        """The wanted AL states may have changed (an NMT command ran or was applied)."""
        self._all_op_wanted = None

    def check_wkc(self, wkc: int, nmt: NmtRun | None) -> bool:
        """This cycle's working counter: counted when wrong while every slave is wanted in OP;
        a new error has the management thread read the AL status at once, and its polling is
        fast while anything is wrong. True when the counter is wrong."""
        self._last_wkc = wkc
        all_op_wanted = self._all_op_wanted
        if all_op_wanted is None:
            all_op_wanted = self._all_op_wanted = nmt is None and all(
                s == ALState.OP for s in self.desired_al.values())
        wkc_bad = wkc != self._bus.expected_wkc
        if wkc_bad and all_op_wanted:
            self._stats.wkc_errors += 1
        mgmt = self._mgmt
        if wkc_bad and self._al_poll_ok and not self._wkc_was_bad:
            mgmt.kick()  # a new working counter error: look at the AL status now
        self._wkc_was_bad = wkc_bad
        fast = wkc_bad or nmt is not None or not self._al_poll_ok or bool(self._no_answer_since)
        if fast != mgmt.fast:
            mgmt.fast = fast
            mgmt.wake()
        return wkc_bad

    def refusal(self, d: Drive, nmt: NmtRun | None) -> str:
        """Why no command can act on ``d`` now ('' if one can)."""
        if d.lost:
            return f"slave {d.slave} lost (AL {d.al.state.wire_name})"
        want = self.desired_al.get(d.slave, ALState.OP)
        if want != ALState.OP or (nmt is not None and d.slave in nmt.slaves):
            return f"slave {d.slave} not operational (AL {d.al.state.wire_name}, nmt in progress or stopped)"
        return ""

    def take_lost_origins(self) -> list[tuple[str, str]]:
        """The group triggers ``(group, reason)`` of the drives lost since the last call."""
        origins = self._lost_origins
        if origins:
            self._lost_origins = []
        return origins

    @property
    def losing(self) -> bool:
        """Drives were lost since the last :meth:`take_lost_origins` whose groups must react."""
        return bool(self._lost_origins)

    # ---- the management thread's reports ---------------------------------------------------------

    def apply_reports(self, now_ns: int, nmt: NmtRun | None) -> None:
        """Reports of the management thread, in the order they were made."""
        reports = self._mgmt.reports
        while reports:
            r = reports.popleft()
            if r[0] == "al":
                self._apply_al(r[1], r[2], now_ns, nmt)
            elif r[0] == "sdo":
                self._apply_sdo(r[1], r[2], r[3], r[4], r[5], now_ns)
            else:
                self._apply_returned(r[1], r[2])

    def _apply_sdo(self, slave: int, what: str, value: int | None, error: str, definite: bool, now_ns: int) -> None:
        """A result of an SDO job (objects the drive does not map)."""
        for d in self._seg.drives:
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
                    self._events.event(d.axis, "fault", f"0x603F = 0x{value:04X} (read by SDO: not in the PDO "
                                       "mapping)", to_state=d.state.value, error_code=value)
                d.error_code_sdo = value
            elif what == "written":
                self._motion.finished(d, d.motion.sdo_written(error), now_ns)
            elif what == "mode_write" and d.pending is not None and d.pending.kind == "mode":
                self._book.resolve(d, "failed", f"0x6060 = {d.mode_written} by SDO refused: {error}", now_ns)
            elif error:
                log.warning("axis %s: SDO %s: %s", d.axis, what, error)

    def _apply_al(self, statuses: Sequence[SlaveALStatus] | None, ticket: int, now_ns: int,
                  nmt: NmtRun | None) -> None:
        self.al_ticket = ticket
        al_status = self.al_status
        drives = self._seg.drives
        if statuses is None:
            statuses = [SlaveALStatus(ALState.NONE, False, 0)] * len(self._seg.slaves)
        ok = True
        nmt_slaves = nmt.slaves if nmt is not None else ()
        for pos, st in enumerate(statuses):
            old = al_status[pos] if pos < len(al_status) else None
            if pos < len(al_status):
                al_status[pos] = st
            if old is not None and (old.state != st.state or old.error != st.error):
                for d in drives:
                    if d.slave == pos:
                        self._events.event(
                            d.axis, "al_state", f"slave {pos} AL {old.state.wire_name} -> {st.state.wire_name}"
                            + (" (no answer)" if st.state == ALState.NONE else "")
                            + (f" error 0x{st.status_code:04X} {al_status_text(st.status_code)}" if st.error else ""),
                            error_code=st.status_code if st.error else 0)
            want = self.desired_al.get(pos, ALState.OP)
            if st.state != want or st.error:
                ok = False
            if st.state != ALState.NONE:
                self._no_answer_since.pop(pos, None)
        confirm_ns = NO_ANSWER_CONFIRM_CYCLES * self._period_ns
        lost_now = False
        for d in drives:
            d.al = al_status[d.slave]
            want = self.desired_al.get(d.slave, ALState.OP)
            gone = d.al.state != want or (d.al.error and want == ALState.OP)
            if gone and d.lost and self._found.waiting(d.slave):
                # back in OP, not yet proven by the working counter, and gone again: recover anew
                self._found.cancel(d.slave)
                self.epoch[d.slave] = self.epoch.get(d.slave, 0) + 1
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
            self.update_recover_set(nmt)

    def _mark_lost(self, d: Drive, now_ns: int) -> None:
        st = d.al
        why = (f"slave {d.slave} AL {st.state.wire_name}"
               + (f" error 0x{st.status_code:04X} {al_status_text(st.status_code)}" if st.error else "")
               + f", working counter {self._last_wkc}/{self._bus.expected_wkc}")
        d.lost = True
        d.lost_reason = f"lost: {why}"
        self._no_answer_since.pop(d.slave, None)
        self.epoch[d.slave] = self.epoch.get(d.slave, 0) + 1
        host = self._seg.host
        log.warning("drive %s/%s lost: %s", host, d.axis, why)
        self._events.event(d.axis, "lost", why, from_state=d.state.value, error_code=st.status_code if st.error else 0)
        if d.pending is not None:
            self._book.resolve(d, "failed", f"slave lost: {why}", now_ns)
        self._motion.abort(d, f"slave lost: {why}", now_ns, drop=True)
        # Never re-enabled without a new command once it returns.
        d.ctrl.set_halt(False)
        d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
        for g in self._seg.groups.of_axis(d.axis):
            self._lost_origins.append((g, f"{host}/{d.axis} lost ({why})"))

    def update_recover_set(self, nmt: NmtRun | None) -> None:
        """Tell the management thread which slaves to bring back to OP: lost ones wanted in OP
        (while running) and those of an NMT command in its recover phase."""
        keys: set[tuple[int, int]] = set()
        epoch = self.epoch
        if self.running:
            for d in self._seg.drives:
                if d.lost and self.desired_al.get(d.slave) == ALState.OP:
                    keys.add((d.slave, epoch.get(d.slave, 0)))
        if nmt is not None and nmt.phase == "recover":
            for s in nmt.slaves:
                st = self.al_status[s]
                if st.state != ALState.OP or st.error:
                    keys.add((s, epoch.get(s, 0)))
        fs = frozenset(keys)
        mgmt = self._mgmt
        if fs != mgmt.recover_set:
            mgmt.recover_set = fs
            mgmt.wake()

    def _apply_returned(self, slave: int, epoch: int) -> None:
        """A slave of the recover set is back in OP: it waits for the working counter's proof
        (:meth:`confirm_found`); its drives stay lost until then."""
        if epoch != self.epoch.get(slave, 0):
            return  # lost again since that recovery began
        self.al_status[slave] = SlaveALStatus(ALState.OP, False, 0)
        self._no_answer_since.pop(slave, None)
        for other in self._seg.drives:
            if other.slave == slave:
                other.al = self.al_status[slave]
        self._found.returned(slave, epoch)

    def confirm_found(self, wkc: int, now_ns: int, nmt: NmtRun | None) -> bool:
        """Once per cycle: while a returned slave waits, it is found when its process data is
        proven (:class:`bus_agent.cycle.found.FoundConfirmation`), with fresh inputs and goal
        DISABLED. True when a slave was found."""
        if not self._found:
            return False
        drives = self._seg.drives
        lost_slaves = {d.slave for d in drives if d.lost}
        found = self._found.step(wkc, self._bus.expected_wkc, lost_slaves, self.al_status)
        for slave in found:
            for other in drives:
                if other.slave != slave or not other.lost:
                    continue
                other.lost = False
                other.lost_reason = ""
                other.inputs = self._bus.inputs(slave)  # read in this cycle's proven exchange
                other.state = decode_statusword(other.inputs.statusword)
                other.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
                log.info("drive %s/%s found: slave %d in OP, process data valid for %d cycles, goal disabled",
                         self._seg.host, other.axis, slave, self._found.confirm_cycles)
                self._events.event(other.axis, "found", f"slave {slave} back in OP with valid process data "
                                   f"for {self._found.confirm_cycles} cycles; goal stays disabled",
                                   to_state=other.state.value)
            self.update_recover_set(nmt)
        return bool(found)
