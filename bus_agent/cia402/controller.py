"""The master-side CiA 402 drive controller: statusword, goal and time in; controlword out.

Functional core of the cycle (see docs/cia402-core.md). :class:`DriveController` is pure: no
clock reads, no I/O, no logging in :meth:`DriveController.step`; times are seconds from any
monotonic origin, passed in by the caller. Cycle-safe: one instance per drive, stepped once per
cycle by the cycle thread.

Safety rules it keeps (IEC 61800-7-201 / CiA 402 state machine, transitions 0..16):
- nothing is enabled unless asked: the goal starts at DISABLED, and no goal other than ENABLED
  ever yields Enable operation (0x000F);
- a fault is reset only after :meth:`DriveController.request_fault_reset`, as a rising edge on
  controlword bit 7 the controller makes itself, with a bounded number of edges (transition 15);
- a goal that failed or timed out is never retried upward: the controller holds the current
  state (or keeps going down) until a new goal is set;
- never Enable operation from an unknown statusword.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from bus_agent.cia402.states import (
    CONTROLWORD_HALT,
    DISABLE_OPERATION,
    TRANSITIONS,
    Controlword,
    Mode,
    State,
    decode_statusword,
    transition_between,
)

__all__ = [
    "Goal",
    "GOAL_TARGETS",
    "ControllerConfig",
    "EventKind",
    "ControllerEvent",
    "ControllerOutput",
    "Step",
    "NEXT_STEP",
    "NEXT_STEP_QUICK_STOP_STAYS",
    "RAISING_TRANSITIONS",
    "KEEP_COMMAND",
    "next_step",
    "quick_stop_stays",
    "DriveController",
]

_S = State
_C = Controlword


class Goal(str, Enum):
    """What the controller drives the drive towards (values are ``schemas.messages.GOALS``)."""

    DISABLED = "disabled"        # -> switch_on_disabled (seed order: 5, 6, 7)
    READY = "ready"              # -> ready_to_switch_on (Shutdown)
    SWITCHED_ON = "switched_on"  # -> switched_on
    ENABLED = "enabled"          # -> operation_enabled
    QUICK_STOP = "quick_stop"    # -> quick_stop_active, or switch_on_disabled (0x605A 0..4)


#: The states in which each goal counts as reached.
GOAL_TARGETS: dict[Goal, frozenset[State]] = {
    Goal.DISABLED: frozenset({_S.SWITCH_ON_DISABLED}),
    Goal.READY: frozenset({_S.READY_TO_SWITCH_ON}),
    Goal.SWITCHED_ON: frozenset({_S.SWITCHED_ON}),
    Goal.ENABLED: frozenset({_S.OPERATION_ENABLED}),
    Goal.QUICK_STOP: frozenset({_S.QUICK_STOP_ACTIVE, _S.SWITCH_ON_DISABLED}),
}


@dataclass(frozen=True)
class ControllerConfig:
    """Timing and policy of one :class:`DriveController`. All durations in seconds."""

    transition_timeout_s: float = 5.0     # per goal, seed 000's 5 s
    fault_reset_retries: int = 3          # bounded rising edges on bit 7 (transition 15)
    fault_reset_low_s: float = 0.01       # bit 7 held low before each edge
    fault_reset_high_s: float = 0.05      # bit 7 held high, then check
    not_ready_grace_s: float = 0.1        # Indy7: a drive sitting in not_ready_to_switch_on gets Shutdown after this
    mode_timeout_s: float = 5.0           # 0x6061 must echo 0x6060 within this
    # Additive: 0x605A quick stop option code of the drive (CiA 402 default 2). 5..8: the drive
    # stays in quick_stop_active, so transition 16 (back to enabled) and 12 (disable voltage)
    # are commanded; otherwise the controller waits for the automatic transition 12.
    quick_stop_option_code: int = 2
    # Additive: Enable operation (4, 16) is sent only once 0x6061 echoes the requested mode, so a
    # drive never starts operating in a mode nobody confirmed.
    enable_requires_mode_echo: bool = True

    def __post_init__(self) -> None:
        for name in ("transition_timeout_s", "fault_reset_low_s", "fault_reset_high_s",
                     "not_ready_grace_s", "mode_timeout_s"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not value >= 0:
                raise ValueError(f"ControllerConfig.{name} must be a number >= 0, got {value!r}")
        if not isinstance(self.fault_reset_retries, int) or self.fault_reset_retries < 1:
            raise ValueError(
                f"ControllerConfig.fault_reset_retries must be an int >= 1, got {self.fault_reset_retries!r}")
        if not isinstance(self.quick_stop_option_code, int) or not -0x8000 <= self.quick_stop_option_code <= 0x7FFF:
            raise ValueError(
                f"ControllerConfig.quick_stop_option_code (0x605A, i16) out of range: {self.quick_stop_option_code!r}")


class EventKind(str, Enum):
    TRANSITION = "transition"            # state changed (from_state, to_state)
    GOAL_REACHED = "goal_reached"
    GOAL_FAILED = "goal_failed"          # e.g. fault while moving to enabled; reason
    GOAL_TIMEOUT = "goal_timeout"
    FAULT = "fault"                      # entered fault_reaction_active/fault
    FAULT_RESET_DONE = "fault_reset_done"
    FAULT_RESET_FAILED = "fault_reset_failed"   # retries exhausted
    MODE_CONFIRMED = "mode_confirmed"
    MODE_TIMEOUT = "mode_timeout"
    MODE_REJECTED = "mode_rejected"      # mode not in the supported set


@dataclass(frozen=True)
class ControllerEvent:
    kind: EventKind
    from_state: State = State.UNKNOWN
    to_state: State = State.UNKNOWN
    reason: str = ""


@dataclass(frozen=True)
class ControllerOutput:
    controlword: int             # 0x6040 to write this cycle (halt bit 8 OR-ed in when halt is set)
    mode_of_operation: int       # 0x6060 to write this cycle
    hold_target: bool            # True: the cycle must write target position/velocity = actual (CSP/CSV before OE)
    events: tuple[ControllerEvent, ...]


# --- The "next command toward a goal" table, derived from the transition table ----------------


@dataclass(frozen=True)
class Step:
    """The command for one (state, goal): ``transition`` is the standard transition it requests,
    None when it requests none (goal reached, or waiting for an automatic transition)."""

    command: Controlword
    transition: int | None = None


def _t(number: int, command: Controlword | None = None) -> Step:
    """Step requesting transition ``number``, with its command from :data:`TRANSITIONS`."""
    t = TRANSITIONS[number]
    chosen = t.command if command is None else command
    if chosen is None or (chosen != t.command and chosen not in t.alternatives):
        raise AssertionError(f"transition {number} is not requested by {command!r}")
    return Step(chosen, number)


def _hold(command: Controlword) -> Step:
    return Step(command, None)


_ALL_GOALS = tuple(Goal)
_D, _R, _SO, _E, _Q = Goal.DISABLED, Goal.READY, Goal.SWITCHED_ON, Goal.ENABLED, Goal.QUICK_STOP

#: (state, goal) -> next step. Down to disabled follows seed 000's order (5, 6, 7); transition 9
#: (disable voltage from operation enabled, the motor coasts) is never chosen. Up goes one
#: transition at a time (2, 3, 4) like the Indy7 sequence, not 3+4.
NEXT_STEP: dict[tuple[State, Goal], Step] = {
    # not ready: nothing to command, wait for transition 1 (the Indy7 tolerance is in the controller)
    **{(_S.NOT_READY_TO_SWITCH_ON, g): _hold(_C.DISABLE_VOLTAGE) for g in _ALL_GOALS},
    (_S.SWITCH_ON_DISABLED, _D): _hold(_C.DISABLE_VOLTAGE),
    (_S.SWITCH_ON_DISABLED, _R): _t(2),
    (_S.SWITCH_ON_DISABLED, _SO): _t(2),
    (_S.SWITCH_ON_DISABLED, _E): _t(2),
    (_S.SWITCH_ON_DISABLED, _Q): _hold(_C.QUICK_STOP),
    (_S.READY_TO_SWITCH_ON, _D): _t(7),
    (_S.READY_TO_SWITCH_ON, _R): _hold(_C.SHUTDOWN),
    (_S.READY_TO_SWITCH_ON, _SO): _t(3),
    (_S.READY_TO_SWITCH_ON, _E): _t(3),
    (_S.READY_TO_SWITCH_ON, _Q): _t(7, _C.QUICK_STOP),
    (_S.SWITCHED_ON, _D): _t(6),
    (_S.SWITCHED_ON, _R): _t(6),
    (_S.SWITCHED_ON, _SO): _hold(_C.SWITCH_ON),
    (_S.SWITCHED_ON, _E): _t(4),
    (_S.SWITCHED_ON, _Q): _t(10, _C.QUICK_STOP),
    (_S.OPERATION_ENABLED, _D): _t(5),
    (_S.OPERATION_ENABLED, _R): _t(8),
    (_S.OPERATION_ENABLED, _SO): _t(5),
    (_S.OPERATION_ENABLED, _E): _hold(_C.ENABLE_OPERATION),
    (_S.OPERATION_ENABLED, _Q): _t(11),
    # quick stop with 0x605A 0..4: the drive leaves by itself (automatic 12); hold the quick stop
    **{(_S.QUICK_STOP_ACTIVE, g): _hold(_C.QUICK_STOP) for g in _ALL_GOALS},
    # fault reaction active / fault: nothing to command (14 is automatic, 15 only on request)
    **{(_S.FAULT_REACTION_ACTIVE, g): _hold(_C.DISABLE_VOLTAGE) for g in _ALL_GOALS},
    **{(_S.FAULT, g): _hold(_C.DISABLE_VOLTAGE) for g in _ALL_GOALS},
}

#: Overrides of :data:`NEXT_STEP` when the drive stays in quick_stop_active (0x605A 5..8).
NEXT_STEP_QUICK_STOP_STAYS: dict[tuple[State, Goal], Step] = {
    (_S.QUICK_STOP_ACTIVE, _D): _t(12),
    (_S.QUICK_STOP_ACTIVE, _R): _t(12),
    (_S.QUICK_STOP_ACTIVE, _SO): _t(12),
    (_S.QUICK_STOP_ACTIVE, _E): _t(16),
    (_S.QUICK_STOP_ACTIVE, _Q): _hold(_C.QUICK_STOP),
}

#: Transitions that raise the drive toward operation; never requested after a goal failed.
RAISING_TRANSITIONS = frozenset({2, 3, 4, 16})

#: The command that keeps each state (used instead of a raising one after a failure/timeout).
KEEP_COMMAND: dict[State, Controlword] = {
    _S.NOT_READY_TO_SWITCH_ON: _C.DISABLE_VOLTAGE,
    _S.SWITCH_ON_DISABLED: _C.DISABLE_VOLTAGE,
    _S.READY_TO_SWITCH_ON: _C.SHUTDOWN,
    _S.SWITCHED_ON: _C.SWITCH_ON,
    _S.OPERATION_ENABLED: _C.ENABLE_OPERATION,
    _S.QUICK_STOP_ACTIVE: _C.QUICK_STOP,
    _S.FAULT_REACTION_ACTIVE: _C.DISABLE_VOLTAGE,
    _S.FAULT: _C.DISABLE_VOLTAGE,
}


def quick_stop_stays(option_code: int) -> bool:
    """True when 0x605A keeps the drive in quick_stop_active after stopping (codes 5..8)."""
    return 5 <= option_code <= 8


def next_step(state: State, goal: Goal, *, stays_in_quick_stop: bool = False) -> Step:
    """Next command from ``state`` toward ``goal`` (pure table look-up; UNKNOWN has no entry)."""
    if state is State.UNKNOWN:
        raise ValueError("no next step from an unknown statusword")
    if stays_in_quick_stop:
        step = NEXT_STEP_QUICK_STOP_STAYS.get((state, goal))
        if step is not None:
            return step
    return NEXT_STEP[(state, goal)]


# --- The controller ---------------------------------------------------------------------------


class _GoalPhase(Enum):
    ACTIVE = "active"
    REACHED = "reached"
    FAILED = "failed"
    TIMED_OUT = "timed_out"


class _ResetPhase(Enum):
    WAIT = "wait"  # not in Fault yet (fault reaction active, unknown): bit 7 low
    LOW = "low"    # in Fault, bit 7 low before the edge
    HIGH = "high"  # in Fault, bit 7 high after the edge


@dataclass
class _FaultReset:
    requested_s: float
    phase: _ResetPhase = _ResetPhase.WAIT
    phase_since_s: float = 0.0
    edges: int = 0
    saw_fault: bool = False


_FAULT_STATES = (State.FAULT_REACTION_ACTIVE, State.FAULT)
#: Reason of a ``disabled`` goal reached in Fault (no torque, fault not reset).
DISABLED_IN_FAULT = "already without torque: drive in fault (fault_reset clears it)"
_INDY7_GOALS = frozenset({Goal.READY, Goal.SWITCHED_ON, Goal.ENABLED})
_HOLD_TARGET_MODES = frozenset({int(Mode.CYCLIC_SYNC_POSITION), int(Mode.CYCLIC_SYNC_VELOCITY)})


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


class DriveController:
    """CiA 402 state machine, master side. Pure: no clock reads, no I/O. One per drive.

    Times are seconds from any monotonic origin. Call :meth:`step` once per cycle with the
    statusword (0x6041) and modes of operation display (0x6061) just read; write the returned
    controlword (0x6040) and modes of operation (0x6060).
    """

    def __init__(self, config: ControllerConfig = ControllerConfig(), mode: int = 8,
                 supported_modes: frozenset[int] | None = None) -> None:
        if not isinstance(config, ControllerConfig):
            raise TypeError(f"config must be a ControllerConfig, got {type(config).__name__}")
        if supported_modes is not None:
            supported_modes = frozenset(int(m) for m in supported_modes)
        self._check_mode_value(mode)
        if supported_modes is not None and mode not in supported_modes:
            raise ValueError(f"initial mode {mode} (0x6060) not in supported modes {sorted(supported_modes)}")
        self.config = config
        self.supported_modes = supported_modes
        self.state: State = State.UNKNOWN
        self.statusword: int | None = None
        self.goal: Goal = Goal.DISABLED
        self.halt: bool = False
        self.mode: int = int(mode)
        self._stays_in_qs = quick_stop_stays(config.quick_stop_option_code)
        self._phase = _GoalPhase.ACTIVE
        self._goal_deadline_s: float | None = None  # set at the first step for the initial goal
        self._state_since_s = 0.0
        self._stepped = False
        self._last_command: Controlword = Controlword.DISABLE_VOLTAGE
        self._reset: _FaultReset | None = None
        self._goal_set_during_reset = False
        self._mode_pending = True  # the initial mode is confirmed by its echo too
        self._mode_deadline_s: float | None = None
        self._pending_events: list[ControllerEvent] = []
        #: The output of the last step when the controller had settled (see :meth:`step`), keyed by
        #: the inputs it saw: (statusword, mode display, output). Dropped by every command.
        self._settled: tuple[int, int, ControllerOutput] | None = None

    #: Reuse a settled step's output when its inputs repeat (False: always step in full; tests
    #: compare both).
    reuse_settled = True

    # -- commands (applied by the cycle at a cycle start) --

    def set_goal(self, goal: Goal, now_s: float) -> None:
        """Drive toward ``goal``; (re)starts the goal deadline (transition_timeout_s)."""
        goal = Goal(goal)  # ValueError for anything not a goal, before changing anything
        self._settled = None
        self.goal = goal
        self._phase = _GoalPhase.ACTIVE
        self._goal_deadline_s = now_s + self.config.transition_timeout_s
        if self._reset is not None:
            self._goal_set_during_reset = True

    def request_fault_reset(self, now_s: float) -> None:
        """Reset a fault (transition 15) with up to ``fault_reset_retries`` rising edges on bit 7.

        The only way a fault gets reset. Reports FAULT_RESET_DONE (at once, reason "no fault",
        when the drive is not in a fault state) or FAULT_RESET_FAILED. After a reset the goal is
        DISABLED unless :meth:`set_goal` was called since this request. A request while one is
        under way is ignored (the bound on edges stays).
        """
        if self._reset is None:
            self._settled = None
            self._reset = _FaultReset(requested_s=now_s)
            self._goal_set_during_reset = False

    def request_mode(self, mode: int, now_s: float) -> None:
        """Request modes of operation ``mode`` (0x6060); MODE_CONFIRMED when 0x6061 echoes it,
        MODE_TIMEOUT after ``mode_timeout_s``, MODE_REJECTED (nothing changed) if unsupported."""
        self._check_mode_value(mode)
        self._settled = None
        if self.supported_modes is not None and mode not in self.supported_modes:
            self._pending_events.append(ControllerEvent(
                EventKind.MODE_REJECTED, self.state, self.state,
                f"mode {mode} not supported (0x6502 supports {sorted(self.supported_modes)})"))
            return
        self.mode = int(mode)
        self._mode_pending = True
        self._mode_deadline_s = now_s + self.config.mode_timeout_s

    def set_halt(self, on: bool) -> None:
        """Halt: controlword bit 8 (stop with 0x605D, stay in the current state)."""
        self._settled = None
        self.halt = bool(on)

    # -- read-only views --

    @property
    def goal_phase(self) -> str:
        """'active', 'reached', 'failed' or 'timed_out'."""
        return self._phase.value

    @property
    def settled(self) -> bool:
        """The last step settled (see :meth:`step`): while its two inputs repeat, a step returns
        the same output and changes nothing. Any command ends it."""
        return self._settled is not None

    @property
    def fault_reset_active(self) -> bool:
        return self._reset is not None

    @property
    def mode_pending(self) -> bool:
        return self._mode_pending

    # -- the cycle step --

    def step(self, statusword: int, mode_display: int, now_s: float) -> ControllerOutput:
        """One cycle: decode 0x6041, advance goal / fault reset / mode, return 0x6040 and 0x6060.

        Pure and cycle-safe. Raises ValueError (changing nothing) if statusword is not a u16.

        Settled steps are reused: once the goal is decided (reached, failed or timed out), no fault
        reset and no mode change is under way and no event waits, a step depends on nothing but
        its two inputs (no deadline is running), so while they repeat the last output is returned
        as it was (without events) and nothing else is done. Any command drops it.
        """
        settled = self._settled
        if (settled is not None and statusword == settled[0] and mode_display == settled[1]
                and type(statusword) is int and type(mode_display) is int):
            return settled[2]
        if not _is_int(statusword) or not 0 <= statusword <= 0xFFFF:
            raise ValueError(f"statusword (0x6041) must be a u16, got {statusword!r}")
        if not _is_int(mode_display):
            raise ValueError(f"mode display (0x6061) must be an int, got {mode_display!r}")
        events: list[ControllerEvent] = self._pending_events
        self._pending_events = []
        if not self._stepped:
            if self._goal_deadline_s is None:
                self._goal_deadline_s = now_s + self.config.transition_timeout_s
            if self._mode_deadline_s is None:
                self._mode_deadline_s = now_s + self.config.mode_timeout_s
        state = decode_statusword(statusword)
        self._observe(state, statusword, now_s, events)
        self._stepped = True

        reset_command = self._step_fault_reset(state, now_s, events)
        self._step_goal(state, statusword, now_s, events)
        command = reset_command if reset_command is not None else self._goal_command(state, mode_display, now_s)
        self._step_mode(mode_display, now_s, events)

        self._last_command = command
        controlword = int(command) | (CONTROLWORD_HALT if self.halt else 0)
        hold_target = self.mode in _HOLD_TARGET_MODES and (
            state is not State.OPERATION_ENABLED or mode_display != self.mode)
        if (self.reuse_settled and self._phase is not _GoalPhase.ACTIVE and self._reset is None
                and not self._mode_pending and not self._pending_events):
            # _observe leaves a repeated state alone, _step_goal acts on a decided goal only when
            # the state changes, _goal_command reads the clock only for an active goal
            self._settled = (statusword, mode_display, ControllerOutput(controlword, self.mode, hold_target, ()))
        else:
            self._settled = None
        return ControllerOutput(controlword, self.mode, hold_target, tuple(events))

    # -- internals --

    @staticmethod
    def _check_mode_value(mode: object) -> None:
        if not _is_int(mode) or not -128 <= mode <= 127:  # type: ignore[operator]
            raise ValueError(f"mode of operation (0x6060) must be an i8, got {mode!r}")

    def _observe(self, state: State, statusword: int, now_s: float, events: list[ControllerEvent]) -> None:
        previous = self.state
        self.statusword = statusword
        if state is previous and self._stepped:
            return
        self._state_since_s = now_s
        if state is previous:  # first step, still unknown: nothing changed
            return
        if not self._stepped:
            reason = ("transition 0" if state is State.NOT_READY_TO_SWITCH_ON
                      else f"first statusword 0x{statusword:04X}")
        elif state is State.UNKNOWN:
            reason = f"unknown statusword 0x{statusword:04X}"
        else:
            number = transition_between(previous, state)
            reason = f"transition {number}" if number is not None else "not a standard transition"
        events.append(ControllerEvent(EventKind.TRANSITION, previous, state, reason))
        if state in _FAULT_STATES and previous not in _FAULT_STATES:
            events.append(ControllerEvent(EventKind.FAULT, previous, state, f"statusword 0x{statusword:04X}"))
        self.state = state

    def _step_fault_reset(self, state: State, now_s: float, events: list[ControllerEvent]) -> Controlword | None:
        """Advance a requested fault reset; returns the controlword it needs, or None."""
        r = self._reset
        if r is None:
            return None
        cfg = self.config
        if state is State.FAULT:
            if not r.saw_fault or r.phase is _ResetPhase.WAIT:
                r.saw_fault = True
                r.phase, r.phase_since_s = _ResetPhase.LOW, now_s
            if r.phase is _ResetPhase.HIGH:
                if now_s - r.phase_since_s < cfg.fault_reset_high_s:
                    return Controlword.FAULT_RESET
                r.edges += 1  # the edge was held long enough and the drive is still in Fault
                if r.edges >= cfg.fault_reset_retries:
                    self._finish_reset(events, ok=False, state=state,
                                       reason=f"still in fault after {r.edges} reset edges")
                    return None
                r.phase, r.phase_since_s = _ResetPhase.LOW, now_s
            # a rising edge needs bit 7 low in the previous cycle: a level would reset nothing
            if (now_s - r.phase_since_s >= cfg.fault_reset_low_s
                    and self._last_command is not Controlword.FAULT_RESET):
                r.phase, r.phase_since_s = _ResetPhase.HIGH, now_s
                return Controlword.FAULT_RESET
            return Controlword.DISABLE_VOLTAGE
        if state in (State.FAULT_REACTION_ACTIVE, State.UNKNOWN):
            if r.phase is _ResetPhase.HIGH:
                r.edges += 1  # left Fault for something that is not a reset: count the edge
            r.phase = _ResetPhase.WAIT
            if r.edges >= cfg.fault_reset_retries or now_s - r.requested_s >= cfg.transition_timeout_s:
                self._finish_reset(events, ok=False, state=state,
                                   reason=f"still {state.value} after {r.edges} reset edges")
                return None
            return Controlword.DISABLE_VOLTAGE
        # a known state outside the fault states: the fault is gone (or there was none)
        if not r.saw_fault:
            self._finish_reset(events, ok=True, state=state, reason="no fault to reset")
            return None
        self._finish_reset(events, ok=True, state=state, reason=f"transition 15 to {state.value}",
                           now_s=now_s)
        return None

    def _finish_reset(self, events: list[ControllerEvent], *, ok: bool, state: State, reason: str,
                      now_s: float | None = None) -> None:
        kind = EventKind.FAULT_RESET_DONE if ok else EventKind.FAULT_RESET_FAILED
        assert self._reset is not None
        from_state = State.FAULT if self._reset.saw_fault else state
        events.append(ControllerEvent(kind, from_state, state, reason))
        self._reset = None
        if ok and now_s is not None and not self._goal_set_during_reset:
            # after a reset the drive sits in switch_on_disabled and stays there unless asked
            self.goal = Goal.DISABLED
            if state in GOAL_TARGETS[Goal.DISABLED]:
                self._phase = _GoalPhase.REACHED
            else:
                self._phase = _GoalPhase.ACTIVE
                self._goal_deadline_s = now_s + self.config.transition_timeout_s

    def _step_goal(self, state: State, statusword: int, now_s: float, events: list[ControllerEvent]) -> None:
        targets = GOAL_TARGETS[self.goal]
        resetting = self._reset is not None
        if self._phase is _GoalPhase.ACTIVE:
            if state in targets:
                self._phase = _GoalPhase.REACHED
                events.append(ControllerEvent(EventKind.GOAL_REACHED, state, state, self.goal.value))
            elif resetting:
                pass  # the requested reset is the way out of the fault; judge the goal after it
            elif state is State.FAULT and self.goal is Goal.DISABLED:
                # Fault is already without torque (the power stage is off): what disable is for.
                # Reached, and said so; the fault itself stays until a fault_reset command.
                self._phase = _GoalPhase.REACHED
                events.append(ControllerEvent(EventKind.GOAL_REACHED, state, state, DISABLED_IN_FAULT))
            elif state in _FAULT_STATES:
                self._fail(events, state, f"{self.goal.value}: drive in {state.value} (0x{statusword:04X})")
            elif state is State.UNKNOWN:
                self._fail(events, state, f"{self.goal.value}: unknown statusword 0x{statusword:04X}")
            elif self._goal_deadline_s is not None and now_s >= self._goal_deadline_s:
                self._phase = _GoalPhase.TIMED_OUT
                events.append(ControllerEvent(
                    EventKind.GOAL_TIMEOUT, state, state,
                    f"{self.goal.value} not reached within {self.config.transition_timeout_s} s; in {state.value}"))
        elif self._phase is _GoalPhase.REACHED and state not in targets and not resetting:
            # going further down is always fine for DISABLED; any other goal was lost
            if self.goal is not Goal.DISABLED:
                self._fail(events, state, f"{self.goal.value}: drive left for {state.value} (0x{statusword:04X})")

    def _fail(self, events: list[ControllerEvent], state: State, reason: str) -> None:
        self._phase = _GoalPhase.FAILED
        events.append(ControllerEvent(EventKind.GOAL_FAILED, state, state, reason))

    def _goal_command(self, state: State, mode_display: int, now_s: float) -> Controlword:
        if state is State.UNKNOWN:
            # keep the last command, but never Enable operation and never bit 7 from here
            last = self._last_command
            if last is Controlword.ENABLE_OPERATION:
                return DISABLE_OPERATION
            if last is Controlword.FAULT_RESET:
                return Controlword.DISABLE_VOLTAGE
            return last
        step = next_step(state, self.goal, stays_in_quick_stop=self._stays_in_qs)
        command = step.command
        active = self._phase is _GoalPhase.ACTIVE
        if (state is State.NOT_READY_TO_SWITCH_ON and active and self.goal in _INDY7_GOALS
                and now_s - self._state_since_s >= self.config.not_ready_grace_s):
            # Indy7 (seed 004): reports 0x0220 (bit 6 clear) but accepts Shutdown
            return Controlword.SHUTDOWN
        if step.transition in RAISING_TRANSITIONS:
            if not active:
                return KEEP_COMMAND[state]  # a failed/timed-out goal is not retried upward
            if (command is Controlword.ENABLE_OPERATION and self.config.enable_requires_mode_echo
                    and mode_display != self.mode):
                return KEEP_COMMAND[state]  # wait for 0x6061 to echo 0x6060
        return command

    def _step_mode(self, mode_display: int, now_s: float, events: list[ControllerEvent]) -> None:
        if not self._mode_pending:
            return
        if mode_display == self.mode:
            self._mode_pending = False
            events.append(ControllerEvent(EventKind.MODE_CONFIRMED, self.state, self.state,
                                          f"0x6061 = {mode_display}"))
        elif self._mode_deadline_s is not None and now_s >= self._mode_deadline_s:
            self._mode_pending = False
            events.append(ControllerEvent(
                EventKind.MODE_TIMEOUT, self.state, self.state,
                f"0x6061 = {mode_display}, requested {self.mode}, after {self.config.mode_timeout_s} s"))
