"""The CiA 402 controllers of the cycle's drives: inputs in, one step each, outputs out.

:class:`Controllers` (cycle thread only) reads each drive's inputs from the process image,
spots new faults on the fresh statusword (reflex origins), steps every drive's
:class:`~bus_agent.cia402.controller.DriveController` and its motion, and writes the outputs
through the output stage. It keeps which drives are not at rest (``busy``: the fast path steps
only those and the ones whose inputs changed; docs/agent-cycle.md, "Fast paths") and which are
armed (``armed``: the spin before a deadline matters).
"""

from __future__ import annotations

from typing import Callable, Sequence

from bus_agent import hops
from bus_agent.bus.base import Bus
from bus_agent.cia402.states import State, decode_statusword
from bus_agent.cycle.drive import ARMED_STATES, FAULT_STATES, UPWARD_GOALS, Drive, Segment
from bus_agent.cycle.events import EventLog
from bus_agent.cycle.management import Management, SdoJob
from bus_agent.cycle.motion import MotionStage, write_targets
from bus_agent.cycle.outcomes import CommandBook


class Controllers:
    """Stepping the drives' controllers; the busy and armed sets; automatic fault reset."""

    def __init__(self, bus: Bus, seg: Segment, mgmt: Management, book: CommandBook, motion: MotionStage,
                 events: EventLog) -> None:
        self._bus = bus
        self._seg = seg
        self._mgmt = mgmt
        self._book = book
        self._motion = motion
        self._events = events
        #: Skip the per-drive work of drives at rest (docs/agent-cycle.md, "Fast paths"); False:
        #: every drive is stepped in full every cycle (tests compare both).
        self.fast_paths = True
        #: Indices of the drives that are not at rest: stepped every cycle (see :meth:`_at_rest`).
        self.busy: set[int] = set()
        #: Indices of the drives that make the spin matter (maintained for the drives stepped).
        self.armed: set[int] = set()
        self._drives_of_slave: dict[int, tuple[int, ...]] = {}
        # Optional bus hooks: which slaves' inputs changed in the last exchange; (CANopen and
        # pysoem, bus.emergency.EmergencyLog) emergencies as (slave, error code, register, text),
        # the text of the last one per slave as {slave: (error code, text)}; a bus with mailboxes
        # (pysoem) has the management thread read them.
        self._inputs_changed: Callable[[], Sequence[int] | None] | None = getattr(bus, "inputs_changed", None)
        self._take_emergencies: Callable[[], list[tuple[int, int, int, str]]] | None = \
            getattr(bus, "take_emergencies", None)
        self.error_texts: dict[int, tuple[int, str]] = getattr(bus, "error_texts", {})
        self._reads_mailbox = getattr(bus, "poll_mailbox", None) is not None

    def start(self) -> None:
        """The drives are configured: every one is stepped in full until it is at rest."""
        drives = self._seg.drives
        self.busy.clear()
        self.busy.update(range(len(drives)))
        of_slave: dict[int, list[int]] = {}
        for d in drives:
            of_slave.setdefault(d.slave, []).append(d.index)
        self._drives_of_slave = {s: tuple(ix) for s, ix in of_slave.items()}

    def changed_slaves(self) -> Sequence[int] | None:
        """The slaves whose inputs changed in the last exchange (fast path); None: unknown."""
        hook = self._inputs_changed
        return hook() if hook is not None and self.fast_paths else None

    def select(self, changed: Sequence[int]) -> Sequence[Drive]:
        """The drives to step in a cycle without commands, reflexes or management reports: those
        whose inputs changed (``changed``: slave positions) and those not at rest, in
        configuration order."""
        busy = self.busy
        if not changed:
            if not busy:
                return ()
            idx = busy
        else:
            idx = set(busy)
            of_slave = self._drives_of_slave
            for pos in changed:
                idx.update(of_slave.get(pos, ()))
        drives = self._seg.drives
        return [drives[k] for k in sorted(idx)]

    def read_inputs(self, work: Sequence[Drive]) -> None:
        """Each drive's inputs from this cycle's process image."""
        inputs = self._bus.inputs
        for d in work:
            i = d.inputs = inputs(d.slave)
            if d.sdo_mode_display:
                i.modes_of_operation_display = d.mode_display_sdo

    def take_emergencies(self) -> None:
        """The bus's emergencies since the last cycle: events, and the error code of a drive in
        fault whose 0x603F is not mapped."""
        take = self._take_emergencies
        if take is None:
            return
        drives = self._seg.drives
        for slave, code, register, text in take():
            for d in drives:
                if d.slave == slave:
                    self._events.event(d.axis, "emcy", f"EMCY 0x{code:04X} {text} (error register "
                                       f"0x{register:02X})", error_code=code)
                    d.last_emcy_code = code if code & 0xFF00 else 0
                    if d.sdo_error_code and d.state in FAULT_STATES and code & 0xFF00 and (
                            not d.error_code_readable or not d.error_code_sdo):
                        d.error_code_sdo = d.inputs.error_code = code  # 0x603F not mapped: the EMCY's
                        self.busy.add(d.index)  # published by the next cycle's step

    def new_faults(self, work: Sequence[Drive], now_ns: int) -> list[tuple[str, str]]:
        """Reflex origins on the fresh statusword, before any controller step (so the other
        members get their new goal in this very cycle): ``(group, reason)`` of each drive that
        entered Fault."""
        origins: list[tuple[str, str]] = []
        mgmt = self._mgmt
        for d in work:
            if d.lost:
                continue
            st = decode_statusword(d.inputs.statusword)
            if d.sdo_error_code:
                # 0x603F not mapped: read by SDO, else the last EMCY's (docs/agent-cycle.md)
                if st not in FAULT_STATES:
                    d.error_code_sdo = 0  # out of fault: no error code applies
                    if d.state in FAULT_STATES:
                        d.last_emcy_code = 0  # that fault's EMCY is not the next one's
                elif d.state not in FAULT_STATES:
                    d.error_code_sdo = d.last_emcy_code
                d.inputs.error_code = d.error_code_sdo
            if st in FAULT_STATES and d.state not in FAULT_STATES:
                if d.sdo_error_code and d.error_code_readable:
                    mgmt.sdo(SdoJob(d.slave, "error_code", deadline_ns=now_ns + 1_000_000_000))  # 0x603F not mapped
                elif self._reads_mailbox:
                    mgmt.sdo(SdoJob(d.slave, "mailbox"))  # the fault's EMCY (the SDO read above gets it too)
                for g in self._seg.groups.of_axis(d.axis):
                    origins.append((g, f"{self._seg.host}/{d.axis} fault 0x{d.inputs.error_code:04X}"))
                d.fault_since_ns = now_ns
                d.last_fault_ns = now_ns
            elif st in FAULT_STATES:
                d.last_fault_ns = now_ns
        if origins:
            hops.stamp("cy.fault")
        return origins

    def step(self, work: Sequence[Drive], now_ns: int) -> None:
        """Step every drive of ``work``: controller, motion, outputs into the process image."""
        now_s = now_ns / 1e9
        bus = self._bus
        set_outputs = bus.set_outputs
        mgmt = self._mgmt
        busy, armed = self.busy, self.armed
        auto_reset = self._auto_reset
        motion_step = self._motion.step
        controller_events = self._book.controller_events
        at_rest = self._at_rest
        for d in work:
            if d.lost:
                # Outputs of a lost slave: disable voltage and hold; applied if it comes back.
                o = d.out
                o.controlword = 0
                o.target_position = d.target_position = d.inputs.position_actual
                o.target_velocity = d.target_velocity = 0
                o.target_torque = d.target_torque = 0
                d.controlword = 0
                set_outputs(d.slave, o)
                busy.add(d.index)
                armed.discard(d.index)
                continue
            auto_reset(d, now_ns)
            out = d.ctrl.step(d.inputs.statusword, d.inputs.modes_of_operation_display, now_s)
            d.state = d.ctrl.state if d.ctrl.state is not None else decode_statusword(d.inputs.statusword)
            targets = (d.target_position, d.target_velocity, d.target_torque)
            idle = d.motion.idle
            if d.state in ARMED_STATES or not idle or d.ctrl.goal in UPWARD_GOALS:
                armed.add(d.index)
            else:
                armed.discard(d.index)
            motion_step(d, out.hold_target, now_ns)
            o = d.out
            o.controlword = d.controlword = out.controlword | d.motion.controlword_bits
            o.modes_of_operation = out.mode_of_operation
            if out.mode_of_operation != d.mode_written and (d.sdo_mode or d.sdo_mode_display):
                # 0x6060 or 0x6061 not mapped: written and/or read back by SDO (management thread);
                # the controller waits for the echo of 0x6061 as with PDOs
                d.mode_written = out.mode_of_operation
                mgmt.sdo(SdoJob(d.slave, "mode", out.mode_of_operation, written=not d.sdo_mode,
                                deadline_ns=now_ns + int(d.cfg.policy.transition_timeout_s * 1e9)))
            if out.hold_target:
                # CSP/CSV/CST before Operation enabled: no stale target (a jump or a following
                # error on enable). Velocity and torque are held at zero.
                d.target_position = d.inputs.position_actual
                d.target_velocity = 0
                d.target_torque = 0
            write_targets(d, out.hold_target)  # through the output stage: the axis limits on the wire
            set_outputs(d.slave, o)
            if out.events:
                controller_events(d, out.events, now_ns)
            elif idle and at_rest(d, targets):
                busy.discard(d.index)
                continue
            busy.add(d.index)

    def _at_rest(self, d: Drive, targets_before: tuple[int, int, int]) -> bool:
        """True when a full step of ``d`` (just made, without controller events, its motion idle
        before it) would repeat itself exactly while its inputs do not change and no command,
        reflex or report reaches it: the cycle may then skip it. The controller settled (its
        output depends on the two inputs only), the motion is idle (:attr:`AxisMotion.idle`), the
        targets did not move (the motion observes them), the output stage wrote them as given (a
        limited target still catches up), no command pending, no automatic fault reset running
        (its backoff reads the clock), no emergency text that may change."""
        if d.pending is not None or not d.ctrl.settled or not d.motion.idle or not d.stage.settled:
            return False
        if (d.target_position, d.target_velocity, d.target_torque) != targets_before:
            return False
        if d.cfg.policy.auto_reset.enabled and (d.state is State.FAULT or d.auto_attempts):
            return False
        return not (d.inputs.error_code and self.error_texts)

    def _auto_reset(self, d: Drive, now_ns: int) -> None:
        """The automatic fault reset (``[policy.auto_reset]``): attempts with a backoff."""
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
                self._events.event(d.axis, "warning", f"auto fault reset: {a.max_attempts} attempts exhausted, "
                                   "waiting for a fault_reset command", error_code=d.inputs.error_code)
            return
        wait_s = min(a.backoff_s * (2 ** d.auto_attempts), a.backoff_max_s)
        if now_ns - d.fault_since_ns >= wait_s * 1e9:
            d.auto_attempts += 1
            d.fault_since_ns = now_ns
            d.ctrl.request_fault_reset(now_ns / 1e9)
            self._events.event(d.axis, "warning", f"auto fault reset attempt {d.auto_attempts}/{a.max_attempts}",
                               error_code=d.inputs.error_code)
