"""One axis's motion: the PLCopen axis state machine and the stepper that writes cyclic targets.

Functional core of the motion layer (docs/motion.md). :class:`AxisMotion` has no clock and no
I/O: the cycle tells it what it observed (:meth:`AxisMotion.observe`), hands it commands
(:meth:`AxisMotion.command`) and steps it once per cycle (:meth:`AxisMotion.step`); it answers
with the targets to write (``write``, ``target_position``, ``target_velocity``) and the commands
that finished (:class:`Finished`, exactly one per accepted command). Cycle-safe: planning runs
only when a command starts (ruckig, tens of microseconds); a step samples one trajectory.

Rules (PLCopen Part 1 semantics; the issue's safety rules):

- commands are checked against the axis state (:data:`ACCEPTS`): motion only in Operation
  enabled, nothing but ``stop`` while stopping or homing;
- one active command per axis: a new one aborts the old one, whose outcome says by what;
- a new plan starts from the set-point being written (position, velocity, acceleration), so the
  targets never jump; leaving Operation enabled drops the plan (the cycle holds the targets at
  the actual values) and ends the command: ``failed`` on a drive fault, ``aborted`` otherwise;
- software limits are checked before a move starts; a jog stops before them.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from bus_agent.motion.axis_limits import AxisLimits
from bus_agent.motion.config import HOMING_METHODS, MotionConfig
from bus_agent.motion.drive_runs import DriveRuns
from bus_agent.motion.homing import CONTROLWORD_HOMING_START, Homing
from bus_agent.motion.planner import (Kinematic, Limits, Plan, PlanError, plan_group, plan_position, plan_stop,
                                      plan_velocity)
from bus_agent.motion.profile import MODE_PP, MODE_PV, ProfileRun
from bus_agent.motion.records import (ACCEPTS, MODE_CSP, MODE_CSV, MOTION_OPS, REFUSAL, Active, AxisState, Finished,
                                      Rejected)
from bus_agent.motion.records import num as _num

__all__ = ["AxisState", "ACCEPTS", "REFUSAL", "MOTION_OPS", "Finished", "AxisMotion", "Rejected", "MODE_CSP",
           "MODE_CSV", "retime_group", "sync_limits", "SYNC_SHARE"]

_Active = Active
#: A gap between two steps longer than this many periods lost at least one frame slot: a stall
#: (counted in ``AxisMotion.stalls``; a synchronized move is re-timed after it, see step()).
STALL_GAP_PERIODS = 1.5
#: A synchronized move is planned within this share of its velocity and acceleration limits; the
#: rest lets a host that lost frame slots (a stall) re-time it to the common arrival within the
#: limits (:func:`retime_group`): it makes up lost time of about a tenth of the time in motion
#: (not in the final deceleration, whose jerk-limited ramp cannot be shortened much).
SYNC_SHARE = 0.9




class AxisMotion:
    """Motion state of one axis (see the module docstring). ``cfg`` in user units.

    Its parts: :attr:`bounds` (:class:`~bus_agent.motion.axis_limits.AxisLimits`, what a command
    may ask) and :attr:`runs` (:class:`~bus_agent.motion.drive_runs.DriveRuns`, homing and the
    drive's own PP/PV profiles)."""

    def __init__(self, cfg: MotionConfig, period_s: float) -> None:
        #: Targets take effect at the next exchange: plans are sampled one period ahead.
        self.bounds = b = AxisLimits(cfg, period_s)
        # read-only mirrors of the bounds, for the per-cycle step's short attribute reads
        self.user, self.cfg, self.scale, self.limits, self.lead_s = b.user, b.cfg, b.scale, b.limits, b.lead_s
        self.runs = DriveRuns(b.cfg, b.limits.acceleration)
        #: The last step's time while a plan runs (None when the last step ended without one),
        #: how many cycle stalls paused the profile, and how far the profile is behind the wall
        #: clock since the plan started (see step()).
        self._last_step_s: float | None = None
        self.stalls = 0
        self._lag_s = 0.0
        #: When the running plan was to arrive (wall clock, this module's seconds) and its duration
        #: as planned: a re-timed synchronized move keeps both.
        self._arrive_s = 0.0
        self._planned_s = 0.0
        #: A synchronized move fell behind (a stall): re-time its group (taken by the cycle).
        self.retime_due = False
        self.homed = False
        self.stop_latched = False
        self.active: _Active | None = None
        self.plan: Plan | None = None
        self.plan_t0 = 0.0
        self.plan_kind = ""      # move | sync | jog | decel | stop
        # what the cycle writes this cycle when ``write`` is set
        self.write = False
        self.target_position = 0
        self.target_velocity = 0
        # last observation (observe)
        self.enabled = False
        self.fault = False
        self.state = "unknown"
        self.error_code = 0
        self.position = 0
        self.velocity = 0
        self.mode = 0
        self.halted = False
        self.commanded = 0       # the position target the cycle wrote last
        self.statusword = 0
        # what homing and the drive's profiles (self.runs) ask of the cycle
        self.controlword_bits = 0            # OR-ed into 0x6040 (homing start, bit 4)
        self.mode_request: int | None = None  # modes of operation to request now (taken by the cycle)
        #: SDO downloads to make now (taken by the cycle; answered through :meth:`sdo_written`)
        self.sdo_request: tuple[tuple[int, int, bytes], ...] | None = None

    @property
    def homing(self) -> Homing | None:
        """The homing run under way (mode 6, :mod:`bus_agent.motion.homing`), or None."""
        return self.runs.homing

    @property
    def profile_run(self) -> ProfileRun | None:
        """The Profile Position / Profile Velocity run under way (the drive's own profile), or None."""
        return self.runs.profile_run

    # ---- observation ----------------------------------------------------------------------

    def observe(self, *, enabled: bool, fault: bool, state: str, error_code: int, position: int,
                velocity: int, mode: int, halted: bool, commanded: int, statusword: int = 0) -> None:
        """What the cycle saw this cycle (fresh inputs). Cycle-safe."""
        self.statusword = statusword
        self.enabled = enabled
        self.fault = fault
        self.state = state
        self.error_code = error_code
        self.position = position
        self.velocity = velocity
        self.mode = mode
        self.halted = halted
        self.commanded = commanded

    @property
    def axis_state(self) -> AxisState:
        if self.fault:
            return AxisState.ERROR_STOP
        if not self.enabled:
            return AxisState.DISABLED
        if self.stop_latched:
            return AxisState.STOPPING
        runs = self.runs
        if runs.homing is not None:
            return AxisState.HOMING
        a = self.active
        r = runs.profile_run
        if r is not None:
            return AxisState.CONTINUOUS_MOTION if r.kind == "pv" and r.replies else AxisState.DISCRETE_MOTION
        if a is not None and a.op == "jog":
            return AxisState.CONTINUOUS_MOTION
        if a is not None and a.synchronized:
            return AxisState.SYNCHRONIZED_MOTION
        if self.plan is not None:
            return AxisState.DISCRETE_MOTION
        return AxisState.STANDSTILL

    @property
    def idle(self) -> bool:
        """No plan, command, homing run, profile run or request under way: a step with the same
        observation as the last one changes nothing and finishes nothing, so the cycle may skip
        it (docs/agent-cycle.md, "Fast paths"). Cycle-safe."""
        runs = self.runs
        return (self.plan is None and self.active is None and runs.homing is None
                and runs.profile_run is None and self.mode_request is None and self.sdo_request is None)

    @property
    def request_id(self) -> str:
        return self.active.request_id if self.active is not None else ""

    # ---- commands --------------------------------------------------------------------------

    def check(self, op: str) -> None:
        """Raise Rejected when the axis state does not accept ``op``."""
        st = self.axis_state
        if op not in ACCEPTS[st]:
            raise Rejected(REFUSAL.get(st, f"{op} not accepted in axis state {st.value}"))

    def _current(self, now_s: float) -> Kinematic:
        """The set-point being written now: where a new plan starts (no jump)."""
        self._advance(now_s)
        if self.plan is not None:
            p, v, a = self.plan.sample(now_s - self.plan_t0)
            return Kinematic(p, v, a)
        if self.halted or self.mode == MODE_CSV:
            return Kinematic(float(self.position), float(self.velocity))
        return Kinematic(float(self.commanded))

    def prepare_move(self, args: Mapping[str, Any], now_s: float,
                     drive_profile: bool = False) -> tuple[Kinematic, float, Limits, list[str]]:
        """Check a move (``to`` or ``by``, optional velocity/accel/jerk): start, target in counts,
        limits and clamp notes. Raises Rejected (nothing changed)."""
        self.check("move")
        if self.mode != MODE_CSP and not (drive_profile and self.mode == MODE_PP):
            raise Rejected(f"move needs cyclic synchronous position (0x6061 = 8)"
                           f"{' or profile position (1)' if drive_profile else ''}; the drive is in mode {self.mode}")
        to, by = _num(args, "to"), _num(args, "by")
        if (to is None) == (by is None):
            raise Rejected("give exactly one of to (absolute) or by (relative)")
        if to is not None and self.cfg.require_homing and not self.homed:
            raise Rejected("not homed: this axis requires homing before absolute moves")
        notes: list[str] = []
        limits = self.bounds.requested(args, notes)
        start = self._current(now_s)
        target = to * self.scale if to is not None else start.position + (by or 0.0) * self.scale
        self.bounds.check_target(target)
        return start, target, limits, notes

    def command(self, token: Any, request_id: str, op: str, args: Mapping[str, Any], now_s: float,
                deadline_s: float) -> list[Finished]:
        """Start ``op`` (move, jog, stop) now. Returns the commands this ends: the new one when it is
        rejected or already done, the aborted one it replaces. Cycle-safe."""
        try:
            if op == "move" and self.mode == MODE_PP:
                return self._pp_move(token, request_id, args, now_s, deadline_s)
            if op == "jog" and self.mode == MODE_PV:
                return self._pv_jog(token, request_id, args, now_s, deadline_s)
            if op == "move":
                start, target, limits, notes = self.prepare_move(args, now_s)
                try:
                    plan = plan_position(start, target, limits)
                except PlanError as e:
                    raise Rejected(str(e)) from None
                return self.start_plan(token, request_id, "move", plan, now_s, deadline_s, note="; ".join(notes))
            if op == "jog":
                return self._jog(token, request_id, args, now_s, deadline_s)
            if op == "stop":
                return self._stop(token, request_id, bool(args.get("release", False)), now_s)
            raise Rejected(f"op {op!r} is not a motion op of this axis")
        except Rejected as e:
            return [Finished(token, request_id, "rejected", str(e))]

    def start_plan(self, token: Any, request_id: str, kind: str, plan: Plan, now_s: float, deadline_s: float,
                   *, note: str = "", synchronized: bool = False, end_s: float = math.inf,
                   limit_ahead: str = "") -> list[Finished]:
        """Make ``plan`` the axis's trajectory from ``now_s``; the running command is aborted."""
        ended = self.abort(f"aborted by {request_id} ({kind})", now_s, decelerate=False)
        self.plan, self.plan_t0, self.plan_kind = plan, now_s, kind
        self._last_step_s, self._lag_s = None, 0.0  # its profile time starts now (or at its start_at)
        self._arrive_s, self._planned_s = now_s + plan.duration, plan.duration
        self.active = _Active(token, request_id, "jog" if kind == "jog" else "move", deadline_s, end_s=end_s,
                              synchronized=synchronized, note=note, limit_ahead=limit_ahead)
        return ended

    def _jog(self, token: Any, request_id: str, args: Mapping[str, Any], now_s: float,
             deadline_s: float) -> list[Finished]:
        self.check("jog")
        if self.mode not in (MODE_CSP, MODE_CSV):
            raise Rejected(f"jog needs cyclic synchronous position or velocity (0x6061 = 8 or 9); "
                           f"the drive is in mode {self.mode}")
        velocity, lim, notes = self.bounds.jog_velocity(args)
        speed = abs(velocity)
        start = self._current(now_s)
        c = self.cfg
        limit = c.max_position if velocity > 0 else c.min_position
        if limit is not None and (start.position - limit) * velocity >= 0:
            raise Rejected(f"at the software limit {'max' if velocity > 0 else 'min'}_position "
                           f"{limit / self.scale:g}: jog the other way")
        # Run for for_s (default: the command's deadline less the time to stop from that speed).
        end_s = self.bounds.jog_end(args, now_s, deadline_s, plan_stop(Kinematic(0.0, velocity), lim).duration)
        try:
            if limit is not None and self.mode == MODE_CSP:
                # CSP with a software limit ahead: a position plan to the limit at the jog speed
                # never passes it (it ends at rest there).
                plan = plan_position(start, limit, Limits(speed, lim.acceleration, lim.jerk))
                plan.final_velocity = 0.0
                stop_at = f"{'max' if velocity > 0 else 'min'}_position {limit / self.scale:g}"
            else:
                plan = plan_velocity(start, velocity, lim)
                stop_at = ""
        except PlanError as e:
            raise Rejected(str(e)) from None
        return self.start_plan(token, request_id, "jog", plan, now_s, deadline_s, note="; ".join(notes),
                               end_s=end_s, limit_ahead=stop_at)

    def _stop(self, token: Any, request_id: str, release: bool, now_s: float) -> list[Finished]:
        if release:
            was = self.stop_latched
            self.stop_latched = False
            return [Finished(token, request_id, "done", "stop released" if was else "no stop to release")]
        ended = self.abort(f"aborted by {request_id} (stop)", now_s, decelerate=True)
        self.stop_latched = True
        if self.runs.profile_run is not None and self.enabled:
            self.active = _Active(token, request_id, "stop", math.inf)
            return ended
        if self.plan is None or not self.enabled:
            return ended + [Finished(token, request_id, "done", "at rest; motion refused until released")]
        self.plan_kind = "stop"
        self.active = _Active(token, request_id, "stop", math.inf)
        return ended

    def abort(self, reason: str, now_s: float, *, decelerate: bool = True, outcome: str = "aborted") -> list[Finished]:
        """End the running command with ``outcome``; with ``decelerate`` (and still enabled) the
        axis comes to rest on its profile from the set-point being written, else the plan is dropped."""
        ended: list[Finished] = []
        if self.runs.abort_homing(outcome, reason):
            return ended  # homing ends with bit 4 low and the previous mode restored; its reply comes then
        a = self.active
        if a is not None:
            self.active = None
            ended.append(Finished(a.token, a.request_id, outcome, reason))
        if self.runs.profile_run is not None:
            if decelerate:
                self._profile_stop(now_s)
            return ended
        if not decelerate:
            return ended  # the caller replaces or drops the plan
        if self.enabled and not self.halted and self.plan is not None:
            start = self._current(now_s)
            self.plan, self.plan_t0, self.plan_kind = plan_stop(start, self.limits), now_s, "decel"
        else:
            self.plan = None
        return ended

    def lose(self, reason: str, now_s: float) -> list[Finished]:
        """The drive is lost or leaves Operation enabled: abort and forget the plan."""
        if self.runs.homing is not None and self.active is not None:
            # lost: nothing reaches the drive; the previous mode is requested for its return
            self.controlword_bits = 0
            self.mode_request = self.runs.lose_homing()
            a, self.active = self.active, None
            return [Finished(a.token, a.request_id, "aborted", reason)]
        ended = self.abort(reason, now_s, decelerate=False)
        self.plan = None
        self.runs.end_profile()
        self.controlword_bits = 0
        return ended

    # ---- homing and the drive's own profiles (self.runs) -------------------------------------

    def start_home(self, token: Any, request_id: str, args: Mapping[str, Any], now_s: float, deadline_s: float,
                   previous_mode: int) -> list[Finished]:
        """Start homing in mode 6 (``method``: default the axis's configured one). The cycle then
        writes :attr:`sdo_request` by SDO and reports with :meth:`sdo_written`."""
        try:
            self.check("home")
            if self.plan is not None or self.active is not None:
                raise Rejected(f"home needs the axis at standstill (it is in {self.axis_state.value}): "
                               "halt or wait for the running command first")
            method = args.get("method", self.cfg.homing.method)
            if method not in HOMING_METHODS:
                raise Rejected(f"homing method {method!r} is not a supported 0x6098 method "
                               "(1..14, 17..30, 33, 34, 35, 37)")
        except Rejected as e:
            return [Finished(token, request_id, "rejected", str(e))]
        self.sdo_request = self.runs.start_home(int(method), previous_mode, now_s, deadline_s)
        self.active = _Active(token, request_id, "home", deadline_s)
        return []

    def sdo_written(self, error: str) -> list[Finished]:
        """The SDO downloads of :attr:`sdo_request` finished (``error``: why one was refused)."""
        failed = self.runs.sdo_written(error)
        if failed is None:
            return []
        failure, replies = failed
        a, self.active = self.active, None
        return [Finished(a.token, a.request_id, "failed", failure)] if a is not None and replies else []

    def _start_profile(self, token: Any, request_id: str, op: str, run_kind: str, now_s: float, deadline_s: float,
                       limits: Limits, **kw: Any) -> list[Finished]:
        ended = self.abort(f"aborted by {request_id} ({op})", now_s, decelerate=False)
        self.plan = None
        writes = self.runs.start_profile(run_kind, now_s, deadline_s, limits, **kw)
        if writes:
            self.sdo_request = writes
        self.active = _Active(token, request_id, op, deadline_s)
        return ended

    def _pp_move(self, token: Any, request_id: str, args: Mapping[str, Any], now_s: float,
                 deadline_s: float) -> list[Finished]:
        _start, target, limits, notes = self.prepare_move(args, now_s, drive_profile=True)
        return self._start_profile(token, request_id, "move", "pp", now_s, deadline_s, limits,
                                   target=float(round(target)), note="; ".join(notes))

    def _pv_jog(self, token: Any, request_id: str, args: Mapping[str, Any], now_s: float,
                deadline_s: float) -> list[Finished]:
        self.check("jog")
        velocity, lim, notes = self.bounds.jog_velocity(args)
        if self.bounds.limit_ahead(self.position, velocity, lim):
            raise Rejected(f"too close to the software limit {'max' if velocity > 0 else 'min'}_position to jog "
                           "that way: jog the other way")
        speed = abs(velocity)
        end_s = self.bounds.jog_end(args, now_s, deadline_s, speed / lim.acceleration)
        return self._start_profile(token, request_id, "jog", "pv", now_s, deadline_s,
                                   Limits(speed, lim.acceleration, lim.jerk), velocity=velocity, end_s=end_s,
                                   note="; ".join(notes))

    def _profile_stop(self, now_s: float) -> None:
        self.runs.stop_profile(now_s, enabled=self.enabled, position=self.position, velocity=self.velocity)

    def _step_profile(self, r: ProfileRun, now_s: float) -> list[Finished]:
        st = self.runs.step_profile(r, now_s, statusword=self.statusword, position=self.position,
                                    velocity=self.velocity, bounds=self.bounds)
        self.write = True
        if r.kind == "pp":
            self.target_position = int(round(r.target))
        else:
            self.target_position = self.position
            self.target_velocity = r.target_velocity
        self.controlword_bits = st.controlword_bits
        a = self.active
        if not st.outcome or a is None or not (r.replies or a.op == "stop"):
            return []
        self.active = None
        if a.op == "stop":
            return [Finished(a.token, a.request_id, "done", "at rest; motion refused until released")]
        return [Finished(a.token, a.request_id, st.outcome, st.reason)]

    def _step_homing(self, h: Homing, now_s: float) -> list[Finished]:
        hs = self.runs.step_homing(h, now_s, statusword=self.statusword, mode=self.mode, enabled=self.enabled,
                                   fault=self.fault, state=self.state, error_code=self.error_code)
        # the targets follow the actual values throughout (no jump when the previous mode returns)
        self.write = True
        self.target_position = self.position
        self.target_velocity = 0
        self.controlword_bits = CONTROLWORD_HOMING_START if hs.start_bit else 0
        if hs.request_mode is not None:
            self.mode_request = hs.request_mode
        if not hs.outcome:
            return []
        self.homed = h.homed
        a, self.active = self.active, None
        return [Finished(a.token, a.request_id, hs.outcome, hs.reason)] if a is not None else []

    # ---- the cycle step -------------------------------------------------------------------

    def step(self, now_s: float) -> list[Finished]:
        """Sample the plan for this cycle's targets and decide outcomes. Call after :meth:`observe`.

        The profile advances one period per step, whatever the time since the last one (see
        :meth:`_advance`): a stalled cycle never catches up at once. A synchronized move that
        fell behind by more than a frame slot sets :attr:`retime_due`: the cycle re-times its
        group (:func:`retime_group`) to keep the common arrival within the axis limits. The output stage (bus_agent.motion.output_stage) keeps
        the limits on the wire whatever this writes."""
        self._advance(now_s)
        if self._lag_s > STALL_GAP_PERIODS * self.lead_s and self.plan_kind == "sync":
            self.retime_due = True
        ended = self._step(now_s)
        self._last_step_s = now_s if self.plan is not None else None
        return ended

    def catch_up(self, now_s: float) -> float:
        """Advance the running profile to ``now_s`` (see :meth:`_advance`) and forget the lag
        it fell behind by, as a re-timed group move starts afresh; the arrival time planned when
        the move started (monotonic seconds). For :func:`retime_group`."""
        self.retime_due = False
        self._lag_s = 0.0
        self._advance(now_s)
        return self._arrive_s

    def _advance(self, now_s: float) -> None:
        """Advance the running profile by one period since the last step (idempotent within a
        cycle). The drive takes one target per period: a frame late by jitter or a stall (slots
        without frames, the drive held the last target) continues from where the last target
        left off, so the step on the wire is one period's worth, not velocity x gap. The profile
        falls behind the wall clock by what the stall lost (``_lag_s``; jitter averages out on
        the loop's drift-free deadlines). Only a plan that ran at the last step advances: one a
        command started since then begins at its own start time (the cycle may skip the steps of
        an idle axis, see :attr:`idle`)."""
        last = self._last_step_s
        if last is None or self.plan is None or now_s <= last:
            return
        gap = now_s - last
        self._last_step_s = now_s
        if last < self.plan_t0:
            return  # not under way yet (a synchronized start_at): its start is a wall-clock time
        self.plan_t0 += gap - self.lead_s
        self._lag_s += gap - self.lead_s
        if gap > STALL_GAP_PERIODS * self.lead_s:
            self.stalls += 1

    def _step(self, now_s: float) -> list[Finished]:
        runs = self.runs
        if runs.homing is not None:
            return self._step_homing(runs.homing, now_s)
        self.controlword_bits = 0
        if runs.profile_run is not None and self.enabled and not self.halted:
            return self._step_profile(runs.profile_run, now_s)
        if not self.enabled:
            self.write = False
            runs.end_profile()
            if self.active is None and self.plan is None:
                return []
            if self.fault:
                return self.abort(f"drive fault 0x{self.error_code:04X} in {self.state}", now_s,
                                  decelerate=False, outcome="failed") + self._drop()
            why = "quick stop" if self.state == "quick_stop_active" else f"drive left operation_enabled ({self.state})"
            return self.abort(why, now_s, decelerate=False) + self._drop()
        if self.halted:
            # controlword bit 8: the drive stops on its own ramp (0x605D); follow it, no jump on release
            halted = self.abort("halt (controlword bit 8)", now_s, decelerate=False) + self._drop()
            runs.end_profile()
            self.write = True
            self.target_position = self.position
            self.target_velocity = 0
            return halted
        plan = self.plan
        if plan is None:
            self.write = False
            return []
        t = now_s - self.plan_t0 + self.lead_s
        p, v, _ = plan.sample(t)
        self.write = True
        self.target_position = int(round(p))
        self.target_velocity = int(round(v))
        a = self.active
        if a is not None and a.op == "move" and now_s >= a.deadline_s:
            return self.abort(f"not in position within the timeout ({plan.target / self.scale:g} {self.user.unit})",
                              now_s, outcome="timeout")
        if a is not None and a.op == "jog" and self.plan_kind == "jog":
            if now_s >= a.end_s:
                self.plan, self.plan_t0, self.plan_kind = plan_stop(self._current(now_s), self.limits), now_s, "jog_end"
                return []
            if self.mode == MODE_CSV:
                a.limit_stop = self.bounds.limit_ahead(self.position, plan.final_velocity)
                if a.limit_stop:
                    self.plan, self.plan_t0 = plan_stop(self._current(now_s), self.limits), now_s
                    self.plan_kind = "jog_end"
                    return []
            if t < plan.duration or math.isnan(plan.target):
                return []  # a velocity plan keeps going until its end time
            a.limit_stop = a.limit_ahead  # a position plan to the limit: it ends there, at rest
            self.plan_kind = "jog_end"
        if t < plan.duration:
            return []
        at_rest = abs(self.velocity) <= self.cfg.velocity_window
        if a is None:
            if at_rest or t >= plan.duration + self.cfg.settle_s:
                self.plan = None  # the last target stays written (held by the cycle)
            return []
        if a.op == "stop":
            if at_rest:
                self.active = None
                self.plan = None
                return [Finished(a.token, a.request_id, "done", "at rest; motion refused until released")]
            return []
        if a.op == "jog":
            if at_rest:
                self.active = None
                self.plan = None
                if a.limit_stop:
                    return [Finished(a.token, a.request_id, "aborted", f"stopped at the software limit {a.limit_stop}")]
                return [Finished(a.token, a.request_id, "done", "jog ended" + (f"; {a.note}" if a.note else ""))]
            return []
        err = abs(self.position - plan.target)
        if err <= self.cfg.position_window and at_rest:
            self.active = None
            self.plan = None
            return [Finished(a.token, a.request_id, "done", a.note, self._planned_s)]
        if t >= plan.duration + self.cfg.settle_s:
            self.active = None
            self.plan = None
            return [Finished(a.token, a.request_id, "failed",
                             f"not in the position window {self.cfg.position_window / abs(self.scale):g} "
                             f"{self.user.unit} {self.cfg.settle_s:g} s after the profile ended "
                             f"(error {err / abs(self.scale):g}, velocity {self.velocity / abs(self.scale):g})")]
        return []

    def _drop(self) -> list[Finished]:
        self.plan = None
        return []


def retime_group(members: list[AxisMotion], now_s: float) -> None:
    """Re-time the synchronized move of ``members`` (the axes of one group move on this host)
    that fell behind the wall clock after a stall: each is planned again from the set-point
    being written to its target, all to one duration (:func:`plan_group`): the planned arrival
    when every axis's limits allow it (a move's own velocity was the group's choice, so an axis
    may go up to its axis limit), else the earliest arrival the slowest allows. Never a jump:
    the new plans start from the set-points. Cycle-safe (ruckig, once per stall)."""
    runs = []
    arrivals = []
    for m in members:
        arrive_s = m.catch_up(now_s)
        plan = m.plan
        if plan is not None and m.plan_kind == "sync" and not math.isnan(plan.target) \
                and 0.0 < now_s - m.plan_t0 < plan.duration:
            runs.append(m)
            arrivals.append(arrive_s)
    if not runs:
        return
    starts = [Kinematic(*m.plan.sample(now_s - m.plan_t0)) for m in runs]  # type: ignore[union-attr]
    arrive = max(arrivals)
    try:
        plans = plan_group(starts, [m.plan.target for m in runs], [m.limits for m in runs],  # type: ignore[union-attr]
                           max(arrive - now_s, 0.0))
    except PlanError:
        return  # keep the paused profiles: they arrive later, together and within the limits
    for m, p in zip(runs, plans):
        m.plan, m.plan_t0 = p, now_s


def sync_limits(limits: Limits) -> Limits:
    """The limits a synchronized move is planned with (:data:`SYNC_SHARE` of velocity and
    acceleration; jerk as given)."""
    return Limits(limits.velocity * SYNC_SHARE, limits.acceleration * SYNC_SHARE, limits.jerk)
