"""The cycle's side of the motion layer: motion ops in, targets out, one outcome per command.

:class:`MotionStage` (cycle thread only). The motion logic itself is pure and lives in
:mod:`bus_agent.motion`; this part only routes commands to each drive's
:class:`~bus_agent.motion.axis.AxisMotion`, copies its targets into the drive's output record
(the cycle's ``target_position``/``target_velocity``) through the drive's output stage
(:func:`write_targets`), and turns its :class:`~bus_agent.motion.axis.Finished` records into
command outcomes (through the :class:`~bus_agent.cycle.outcomes.CommandBook`).
"""

from __future__ import annotations

from typing import Callable, Sequence

from bus_agent.cia402.states import State
from bus_agent.cycle.drive import Drive, Segment
from bus_agent.cycle.management import Management, SdoJob
from bus_agent.cycle.outcomes import CommandBook, send_outcome
from bus_agent.cycle.stats import Statistics
from bus_agent.motion.axis import MODE_CSP, MODE_CSV, Finished, Rejected, retime_group, sync_limits
from bus_agent.motion.homing import MODE_HOMING
from bus_agent.motion.profile import MODE_PP, MODE_PV
from bus_agent.motion.planner import PlanError, plan_group
from bus_agent.runtime import DriveCommand, Outcome


_FAULTS = (State.FAULT, State.FAULT_REACTION_ACTIVE)
_ENABLED = State.OPERATION_ENABLED


class MotionStage:
    """Motion commands and per-cycle motion steps of the cycle's drives."""

    def __init__(self, seg: Segment, book: CommandBook, mgmt: Management, stats: Statistics,
                 wall_ns: Callable[[], int]) -> None:
        self._seg = seg
        self._book = book
        self._mgmt = mgmt
        self._stats = stats
        self._wall_ns = wall_ns

    # ---- commands ------------------------------------------------------------------------------

    def command(self, d: Drive, cmd: DriveCommand, now_ns: int) -> None:
        """move / jog / stop / home for one axis (a ``sync`` move goes through :meth:`group_move`)."""
        m = d.motion
        now_s = now_ns / 1e9
        start_ns = cmd.received_ns or now_ns
        deadline_s = (start_ns + int(cmd.timeout_s * 1e9)) / 1e9
        token = (cmd, self._stats.cycles)
        if cmd.op == "home":
            sup = d.ctrl.supported_modes
            if sup is not None and MODE_HOMING not in sup:
                self._book.reply(d, cmd, "rejected", f"homing (mode 6) is not supported by the drive (0x6502: "
                                 f"modes {sorted(sup)})", now_ns, start_ns)
                return
            ended = m.start_home(token, cmd.request_id, cmd.args, now_s, deadline_s, d.ctrl.mode)
            self._requests(d, now_ns)
            self.finished(d, ended, now_ns)
            return
        ended = m.command(token, cmd.request_id, cmd.op, cmd.args, now_s, deadline_s)
        self._requests(d, now_ns)
        if m.active is not None and m.active.token is token:
            d.ctrl.set_halt(False)  # a new move after a halt: PLCopen MC_Halt may be overridden
        self.finished(d, ended, now_ns)

    def group_move(self, cmd: DriveCommand, now_ns: int, refusal: Callable[[Drive], str]) -> None:
        """A synchronised move of the axes of one query: all start in the same cycle (or at
        ``start_at_ns``) and arrive together. Any axis refusing refuses the whole group
        (``refusal``: why no command can act on a drive now, '' if one can)."""
        args = cmd.args
        targets = args.get("targets")
        start_ns = cmd.received_ns or now_ns
        deadline_s = (start_ns + int(cmd.timeout_s * 1e9)) / 1e9
        now_s = now_ns / 1e9
        axes = list(dict.fromkeys(cmd.axes))
        drives: list[Drive] = []
        prepared = []
        refused: dict[str, str] = {}
        by_axis = self._seg.by_axis
        reply = self._book.reply
        for axis in axes:
            d = by_axis.get(axis)
            if d is None:
                refused[axis] = f"no axis {axis!r} here"
                send_outcome(cmd, Outcome(axis=axis, outcome="rejected", reason=refused[axis]))
                continue
            why = refusal(d)
            if why:
                refused[axis] = why
                drives.append(d)
                continue
            one = {k: v for k, v in args.items() if k not in ("targets", "sync", "prepare", "duration_s", "start_at_ns")}
            if targets is not None:
                if axis not in targets:
                    refused[axis] = "no target for this axis in targets"
                    drives.append(d)
                    continue
                one = {k: v for k, v in one.items() if k not in ("to", "by")} | {"to": targets[axis]}
            try:
                prepared.append(d.motion.prepare_move(one, now_s))
            except Rejected as e:
                refused[axis] = str(e)
            drives.append(d)
        plans = []
        if not refused:
            try:
                plans = plan_group([p[0] for p in prepared], [p[1] for p in prepared],
                                   [sync_limits(p[2]) for p in prepared],
                                   float(args.get("duration_s") or 0.0))
            except PlanError as e:
                refused = {d.axis: str(e) for d in drives}
        if refused:
            for d in drives:
                why = refused.get(d.axis) or "group move refused: " + "; ".join(f"{a}: {r}" for a, r in refused.items())
                reply(d, cmd, "rejected", why, now_ns, start_ns)
            return
        duration = max((p.duration for p in plans), default=0.0)
        if args.get("prepare"):
            for d in drives:
                reply(d, cmd, "done", f"prepared: minimum duration {duration:.6f} s", now_ns, start_ns,
                      duration_s=duration)
            return
        t0_s = now_s
        start_at = args.get("start_at_ns")
        if start_at:
            t0_s = now_s + (int(start_at) - self._wall_ns()) / 1e9
            if t0_s < now_s:
                late = now_s - t0_s
                for d in drives:
                    reply(d, cmd, "rejected", f"start_at_ns is {late * 1e3:.3f} ms in the past", now_ns, start_ns)
                return
        token_cycle = self._stats.cycles
        for d, plan, prep in zip(drives, plans, prepared):
            d.ctrl.set_halt(False)
            ended = d.motion.start_plan((cmd, token_cycle), cmd.request_id, "sync", plan, t0_s, deadline_s,
                                        note="; ".join(prep[3]), synchronized=True)
            self.finished(d, ended, now_ns)

    def _retime(self, d: Drive, now_ns: int) -> None:
        """``d``'s synchronized move fell behind after a stall: re-time it with the other axes of
        the same group move here (one command, :meth:`group_move`), so they keep arriving
        together (see :func:`~bus_agent.motion.axis.retime_group`). The drives stepped later in
        this cycle sample the new plans already; those stepped before continue from them."""
        a = d.motion.active
        cmd = a.token[0] if a is not None else None
        members = [x.motion for x in self._seg.drives if not x.lost and x.motion.active is not None
                   and x.motion.active.token[0] is cmd] if cmd is not None else [d.motion]
        retime_group(members or [d.motion], now_ns / 1e9)

    def abort(self, d: Drive, reason: str, now_ns: int, *, drop: bool = False) -> None:
        """End the running motion command of ``d`` (aborted); ``drop``: forget the plan too (the
        drive is leaving Operation enabled or is lost), else decelerate on the profile."""
        m = d.motion
        ended = m.lose(reason, now_ns / 1e9) if drop else m.abort(reason, now_ns / 1e9)
        self._requests(d, now_ns)
        self.finished(d, ended, now_ns)

    def _requests(self, d: Drive, now_ns: int) -> None:
        """What the axis's motion asks of the cycle: a mode (homing: 6, then the previous mode
        back), SDO downloads (homing or profile parameters: on the management thread, since
        mailbox round trips never run on the cycle thread; answered through
        ``SlaveHealth.apply_reports``)."""
        m = d.motion
        if m.mode_request is not None:
            d.ctrl.request_mode(m.mode_request, now_ns / 1e9)
            m.mode_request = None
        if m.sdo_request is not None:
            self._mgmt.sdo(SdoJob(d.slave, "write", writes=m.sdo_request))
            m.sdo_request = None

    def finished(self, d: Drive, ended: Sequence[Finished], now_ns: int) -> None:
        """Outcomes of the motion commands that ended."""
        for f in ended:
            cmd, start_cycle = f.token
            self._book.reply(d, cmd, f.outcome, f.reason, now_ns, cmd.received_ns or now_ns, start_cycle,
                             duration_s=f.duration_s)

    # ---- per cycle -----------------------------------------------------------------------------

    def step(self, d: Drive, hold_target: bool, now_ns: int) -> None:
        """Observe, step, and copy the axis's targets into the drive's output record. Cycle-safe."""
        i = d.inputs
        m = d.motion
        state = d.state
        m.observe(enabled=state is State.OPERATION_ENABLED, fault=state in _FAULTS, state=state.value,
                  error_code=i.error_code, position=i.position_actual, velocity=i.velocity_actual,
                  mode=i.modes_of_operation_display, halted=d.ctrl.halt, commanded=d.target_position,
                  statusword=i.statusword)
        ended = m.step(now_ns / 1e9)
        if m.retime_due:
            self._retime(d, now_ns)
        if m.mode_request is not None or m.sdo_request is not None:
            self._requests(d, now_ns)
        if m.write and not hold_target:
            if m.runs.homing is not None or m.mode == MODE_HOMING:
                d.target_position = m.target_position
                d.target_velocity = 0
            elif m.mode == MODE_CSV:
                d.target_velocity = m.target_velocity
                d.target_position = i.position_actual
            elif m.mode in (MODE_CSP, MODE_PP):
                d.target_position = m.target_position
            elif m.mode == MODE_PV:
                d.target_velocity = m.target_velocity
        if m.mode == MODE_PV and m.runs.profile_run is None:
            d.target_velocity = 0  # no stale 0x60FF in profile velocity (a jump on the next enable)
        if ended:
            self.finished(d, ended, now_ns)

def write_targets(d: Drive, hold_target: bool) -> None:
    """Copy the drive's targets into its output record through its output stage
    (:class:`~bus_agent.motion.output_stage.OutputStage`): the single point every target passes
    on its way to the wire, whoever produced it. The stage limits 0x607A in CSP and 0x60FF in
    CSV while the drive is in Operation enabled and not halted (it follows the drive's mode as
    0x6061 reports it: that is how the drive reads the targets); otherwise it follows them.
    ``d.target_*`` stay what the producers asked for, so a limited target catches up with them.
    Cycle thread."""
    st = d.stage
    mode = (d.inputs.modes_of_operation_display
            if d.state is _ENABLED and not hold_target and not d.ctrl.halt else 0)
    st.step(mode, d.target_position, d.target_velocity)
    o = d.out
    o.target_position = st.position
    o.target_velocity = st.velocity
    o.target_torque = d.target_torque


def following_error(d: Drive) -> int:
    """Target position written last minus the actual position (CSP in Operation enabled), else 0."""
    if d.state is State.OPERATION_ENABLED and d.inputs.modes_of_operation_display == MODE_CSP:
        return d.out.target_position - d.inputs.position_actual
    return 0

