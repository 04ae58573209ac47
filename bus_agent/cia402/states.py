"""CiA 402 states, statusword decoding and controlword commands (IEC 61800-7-201 / CiA 402).

Tables from the standard as data. Shared by the master-side controller and the device-side
drive model. Pure; cycle-safe.
"""

from __future__ import annotations

from enum import Enum, IntEnum
from typing import NamedTuple


class State(str, Enum):
    """The eight states of the drive state machine, plus UNKNOWN for undefined statuswords.

    Values are the wire names used in ``schemas.messages.DRIVE_STATES``.
    """

    NOT_READY_TO_SWITCH_ON = "not_ready_to_switch_on"
    SWITCH_ON_DISABLED = "switch_on_disabled"
    READY_TO_SWITCH_ON = "ready_to_switch_on"
    SWITCHED_ON = "switched_on"
    OPERATION_ENABLED = "operation_enabled"
    QUICK_STOP_ACTIVE = "quick_stop_active"
    FAULT_REACTION_ACTIVE = "fault_reaction_active"
    FAULT = "fault"
    UNKNOWN = "unknown"


#: Statusword (0x6041) decoding: (mask, value) per state. The patterns are disjoint.
STATUSWORD_PATTERNS: tuple[tuple[int, int, State], ...] = (
    (0x004F, 0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x004F, 0x0040, State.SWITCH_ON_DISABLED),
    (0x006F, 0x0021, State.READY_TO_SWITCH_ON),
    (0x006F, 0x0023, State.SWITCHED_ON),
    (0x006F, 0x0027, State.OPERATION_ENABLED),
    (0x006F, 0x0007, State.QUICK_STOP_ACTIVE),
    (0x004F, 0x000F, State.FAULT_REACTION_ACTIVE),
    (0x004F, 0x0008, State.FAULT),
)

#: The low bits (mask 0x006F) a device reports in each state; bit 4 (voltage enabled) is
#: added by the device. Used by the drive model to build its statusword.
STATUSWORD_OF_STATE: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021,
    State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027,
    State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: 0x0008,
}


def _pattern_match(statusword: int) -> State:
    for mask, value, state in STATUSWORD_PATTERNS:
        if statusword & mask == value:
            return state
    return State.UNKNOWN


#: The bits any pattern looks at (0x006F), and the state of every combination of them: the
#: patterns above compiled once into a lookup table (112 entries), so decoding is one index.
_DECODE_MASK = 0
for _mask, _value, _state in STATUSWORD_PATTERNS:
    _DECODE_MASK |= _mask
_STATE_BY_BITS: tuple[State, ...] = tuple(_pattern_match(bits) for bits in range(_DECODE_MASK + 1))


def decode_statusword(statusword: int) -> State:
    """Map a statusword to its state, or ``State.UNKNOWN`` when no pattern matches.
    One table lookup over the bits the patterns use; cycle-safe."""
    return _STATE_BY_BITS[statusword & _DECODE_MASK]


class StatuswordBit(IntEnum):
    READY_TO_SWITCH_ON = 0
    SWITCHED_ON = 1
    OPERATION_ENABLED = 2
    FAULT = 3
    VOLTAGE_ENABLED = 4
    QUICK_STOP = 5
    SWITCH_ON_DISABLED = 6
    WARNING = 7
    REMOTE = 9
    TARGET_REACHED = 10
    INTERNAL_LIMIT_ACTIVE = 11
    OPERATION_MODE_SPECIFIC_12 = 12
    OPERATION_MODE_SPECIFIC_13 = 13


class Controlword(IntEnum):
    """Controlword (0x6040) command values (bits 7,3,2,1,0). Halt is bit 8, OR-ed in separately."""

    DISABLE_VOLTAGE = 0x0000       # transitions 7, 9, 10, 12
    QUICK_STOP = 0x0002            # transitions 7, 10, 11
    SHUTDOWN = 0x0006              # transitions 2, 6, 8
    SWITCH_ON = 0x0007             # transition 3 (also "disable operation", transition 5)
    ENABLE_OPERATION = 0x000F      # transitions 4, 16 (and 3+4 from Ready to switch on)
    FAULT_RESET = 0x0080           # transition 15, on the rising edge of bit 7


DISABLE_OPERATION = Controlword.SWITCH_ON  # same bits, transition 5
CONTROLWORD_HALT = 0x0100
CONTROLWORD_FAULT_RESET_BIT = 0x0080


class Mode(IntEnum):
    """Modes of operation, 0x6060 / 0x6061, and their bit in 0x6502 (supported drive modes)."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10

    @property
    def supported_bit(self) -> int:
        """Bit of this mode in 0x6502."""
        return {1: 0, 3: 2, 4: 3, 6: 5, 7: 6, 8: 7, 9: 8, 10: 9}[int(self)]


CYCLIC_MODES = frozenset({Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_VELOCITY, Mode.CYCLIC_SYNC_TORQUE})


# --- Transition table (IEC 61800-7-201 / CiA 402, drive state machine) -----------------------


class Transition(NamedTuple):
    """One numbered transition of the drive state machine.

    ``from_state`` is None for transition 0 (power-on: no state yet) and 13 (from any state).
    ``command`` is the controlword (0x6040) that requests it, None for the automatic transitions
    0, 1, 13 and 14; ``alternatives`` are other commands the standard defines for it (quick stop
    in 7 and 10). Transition 12 also happens automatically when a quick stop with 0x605A 0..4
    completes (``automatic_too``).
    """

    number: int
    from_state: State | None
    to_state: State
    command: Controlword | None
    alternatives: tuple[Controlword, ...] = ()
    automatic_too: bool = False


_S = State
_C = Controlword

#: The 17 standard transitions, indexed by number (TRANSITIONS[n].number == n).
TRANSITIONS: tuple[Transition, ...] = (
    Transition(0, None, _S.NOT_READY_TO_SWITCH_ON, None),
    Transition(1, _S.NOT_READY_TO_SWITCH_ON, _S.SWITCH_ON_DISABLED, None),
    Transition(2, _S.SWITCH_ON_DISABLED, _S.READY_TO_SWITCH_ON, _C.SHUTDOWN),
    Transition(3, _S.READY_TO_SWITCH_ON, _S.SWITCHED_ON, _C.SWITCH_ON),
    Transition(4, _S.SWITCHED_ON, _S.OPERATION_ENABLED, _C.ENABLE_OPERATION),
    Transition(5, _S.OPERATION_ENABLED, _S.SWITCHED_ON, DISABLE_OPERATION),
    Transition(6, _S.SWITCHED_ON, _S.READY_TO_SWITCH_ON, _C.SHUTDOWN),
    Transition(7, _S.READY_TO_SWITCH_ON, _S.SWITCH_ON_DISABLED, _C.DISABLE_VOLTAGE, (_C.QUICK_STOP,)),
    Transition(8, _S.OPERATION_ENABLED, _S.READY_TO_SWITCH_ON, _C.SHUTDOWN),
    Transition(9, _S.OPERATION_ENABLED, _S.SWITCH_ON_DISABLED, _C.DISABLE_VOLTAGE),
    Transition(10, _S.SWITCHED_ON, _S.SWITCH_ON_DISABLED, _C.DISABLE_VOLTAGE, (_C.QUICK_STOP,)),
    Transition(11, _S.OPERATION_ENABLED, _S.QUICK_STOP_ACTIVE, _C.QUICK_STOP),
    Transition(12, _S.QUICK_STOP_ACTIVE, _S.SWITCH_ON_DISABLED, _C.DISABLE_VOLTAGE, (), True),
    Transition(13, None, _S.FAULT_REACTION_ACTIVE, None),
    Transition(14, _S.FAULT_REACTION_ACTIVE, _S.FAULT, None),
    Transition(15, _S.FAULT, _S.SWITCH_ON_DISABLED, _C.FAULT_RESET),
    Transition(16, _S.QUICK_STOP_ACTIVE, _S.OPERATION_ENABLED, _C.ENABLE_OPERATION),
)

#: Transitions the drive makes by itself (the master only observes them).
AUTOMATIC_TRANSITIONS = frozenset({0, 1, 13, 14})


def transition_between(from_state: State, to_state: State) -> int | None:
    """Number of the standard transition from ``from_state`` to ``to_state``, or None.

    Transition 13 (fault detected) matches from any state except the two fault states;
    transition 0 (power-on) has no from-state and is never returned here.
    """
    for t in TRANSITIONS:
        if t.to_state is not to_state or t.number == 0:
            continue
        if t.from_state is from_state:
            return t.number
        if t.number == 13 and from_state not in (
            State.FAULT_REACTION_ACTIVE, State.FAULT, State.UNKNOWN
        ):
            return t.number
    return None


#: The command that keeps each state (no transition): where the standard defines no command in a
#: state (not ready, fault reaction active, fault), Disable voltage is the neutral one.
STATE_KEEP_COMMANDS: dict[State, frozenset[Controlword]] = {
    _S.NOT_READY_TO_SWITCH_ON: frozenset({_C.DISABLE_VOLTAGE}),
    _S.SWITCH_ON_DISABLED: frozenset({_C.DISABLE_VOLTAGE, _C.QUICK_STOP}),
    _S.READY_TO_SWITCH_ON: frozenset({_C.SHUTDOWN}),
    _S.SWITCHED_ON: frozenset({_C.SWITCH_ON}),
    _S.OPERATION_ENABLED: frozenset({_C.ENABLE_OPERATION}),
    _S.QUICK_STOP_ACTIVE: frozenset({_C.QUICK_STOP}),
    _S.FAULT_REACTION_ACTIVE: frozenset({_C.DISABLE_VOLTAGE}),
    _S.FAULT: frozenset({_C.DISABLE_VOLTAGE}),
}


def allowed_controlwords(state: State) -> frozenset[Controlword]:
    """Controlword commands (bits 7,3,2,1,0 of 0x6040) the standard defines for ``state``.

    The commands that request a transition out of ``state``, the command that keeps it
    (:data:`STATE_KEEP_COMMANDS`), and Switch on + Enable operation (3+4) in Ready to switch on.
    UNKNOWN is no standard state: anything except Enable operation and Fault reset.
    """
    if state is State.UNKNOWN:
        return frozenset(Controlword) - {_C.ENABLE_OPERATION, _C.FAULT_RESET}
    allowed = set(STATE_KEEP_COMMANDS[state])
    for t in TRANSITIONS:
        if t.from_state is state and t.command is not None:
            allowed.add(t.command)
            allowed.update(t.alternatives)
    if state is State.READY_TO_SWITCH_ON:
        allowed.add(_C.ENABLE_OPERATION)  # 3+4
    return frozenset(allowed)


#: Mask of the command bits (7, 3, 2, 1, 0) of the controlword.
CONTROLWORD_COMMAND_MASK = 0x008F
