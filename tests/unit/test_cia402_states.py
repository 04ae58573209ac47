"""Statusword decoding (all 65,536 values), the transition table and allowed controlwords."""

from __future__ import annotations

import re

import pytest

from bus_agent.cia402.states import (
    AUTOMATIC_TRANSITIONS,
    DISABLE_OPERATION,
    STATE_KEEP_COMMANDS,
    STATUSWORD_OF_STATE,
    STATUSWORD_PATTERNS,
    TRANSITIONS,
    Controlword,
    State,
    allowed_controlwords,
    decode_statusword,
    transition_between,
)


def test_every_statusword_decodes_to_its_single_matching_pattern():
    counts = {s: 0 for s in State}
    for statusword in range(0x10000):
        matches = [state for mask, value, state in STATUSWORD_PATTERNS if statusword & mask == value]
        assert len(matches) <= 1, f"0x{statusword:04X} matches {matches}"
        expected = matches[0] if matches else State.UNKNOWN
        assert decode_statusword(statusword) is expected, f"0x{statusword:04X}"
        counts[expected] += 1
    # each pattern fixes 5 (mask 0x004F) or 6 (mask 0x006F) bits
    assert counts[State.NOT_READY_TO_SWITCH_ON] == 2048
    assert counts[State.SWITCH_ON_DISABLED] == 2048
    assert counts[State.FAULT] == 2048
    assert counts[State.FAULT_REACTION_ACTIVE] == 2048
    for state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED,
                  State.QUICK_STOP_ACTIVE):
        assert counts[state] == 1024
    assert sum(counts.values()) == 0x10000
    assert counts[State.UNKNOWN] == 0x10000 - 4 * 2048 - 4 * 1024


# The standard's tables as printed (IEC 61800-7-201 / CiA 402, "state coding" of the statusword
# and "command coding" of the controlword), copied as text, bit 15 first, x = don't care. These
# are independent oracles: nothing below reads the masks and values of the code under test.
STANDARD_STATUSWORD_TABLE = {
    "xxxx xxxx x0xx 0000": State.NOT_READY_TO_SWITCH_ON,
    "xxxx xxxx x1xx 0000": State.SWITCH_ON_DISABLED,
    "xxxx xxxx x01x 0001": State.READY_TO_SWITCH_ON,
    "xxxx xxxx x01x 0011": State.SWITCHED_ON,
    "xxxx xxxx x01x 0111": State.OPERATION_ENABLED,
    "xxxx xxxx x00x 0111": State.QUICK_STOP_ACTIVE,
    "xxxx xxxx x0xx 1111": State.FAULT_REACTION_ACTIVE,
    "xxxx xxxx x0xx 1000": State.FAULT,
}
#: Controlword bits 7 (fault reset), 3 (enable operation), 2 (quick stop, active low), 1 (enable
#: voltage), 0 (switch on) of each command, and the transitions it triggers.
STANDARD_CONTROLWORD_TABLE = {
    "shutdown": ("0x110", (2, 6, 8)),
    "switch_on": ("00111", (3,)),
    "disable_voltage": ("0xx0x", (7, 9, 10, 12)),
    "quick_stop": ("0x01x", (7, 10, 11)),
    "disable_operation": ("00111", (5,)),
    "enable_operation": ("01111", (4, 16)),
}


_STANDARD_ROWS = [(re.compile(pattern.replace(" ", "").replace("x", ".")), state)
                  for pattern, state in STANDARD_STATUSWORD_TABLE.items()]


def _standard_state(statusword: int) -> State:
    """The state the standard's table gives for ``statusword`` (UNKNOWN if no row matches)."""
    bits = format(statusword, "016b")
    rows = [state for pattern, state in _STANDARD_ROWS if pattern.fullmatch(bits)]
    assert len(rows) <= 1, f"0x{statusword:04X}: the table is not a partition: {rows}"
    return rows[0] if rows else State.UNKNOWN


def test_every_statusword_decodes_as_the_standards_table_says():
    # the 8 defined states cover 4 x 2048 + 4 x 1024 = 12,288 statuswords; bit 7 (warning) and
    # bits 8-15 never change the state
    counts = {s: 0 for s in State}
    for statusword in range(0x10000):
        expected = _standard_state(statusword)
        assert decode_statusword(statusword) is expected, f"0x{statusword:04X}: expected {expected}"
        counts[expected] += 1
    assert counts[State.UNKNOWN] == 0x10000 - 12288


def test_controlword_commands_follow_the_standards_table():
    values = {"shutdown": Controlword.SHUTDOWN, "switch_on": Controlword.SWITCH_ON,
              "disable_voltage": Controlword.DISABLE_VOLTAGE, "quick_stop": Controlword.QUICK_STOP,
              "disable_operation": DISABLE_OPERATION, "enable_operation": Controlword.ENABLE_OPERATION}
    for name, (pattern, transitions) in STANDARD_CONTROLWORD_TABLE.items():
        bits = format(values[name], "016b")
        low = bits[-8] + bits[-4:]  # bits 7, 3, 2, 1, 0
        assert all(p in ("x", b) for p, b in zip(pattern, low)), (name, low, pattern)
        assert values[name] & 0xFF70 == 0, name  # nothing else set
        for n in transitions:
            t = TRANSITIONS[n]
            assert values[name] in (t.command, *t.alternatives), (name, n, t)
    assert TRANSITIONS[15].command & 0x0080  # fault reset: bit 7 (its rising edge)


@pytest.mark.parametrize("statusword, state", [
    (0x0220, State.NOT_READY_TO_SWITCH_ON),  # seed 004 calls it "switch on disabled"; bit 6 is clear
    (0x0221, State.READY_TO_SWITCH_ON),
    (0x0233, State.SWITCHED_ON),
    (0x0237, State.OPERATION_ENABLED),
    (0x0250, State.SWITCH_ON_DISABLED),
    (0x0217, State.QUICK_STOP_ACTIVE),
    (0x021F, State.FAULT_REACTION_ACTIVE),
    (0x0218, State.FAULT),
    (0x0001, State.UNKNOWN),
    (0x0061, State.UNKNOWN),
])
def test_indy7_and_sample_statuswords(statusword, state):
    assert decode_statusword(statusword) is state


def test_state_statuswords_round_trip():
    for state, low_bits in STATUSWORD_OF_STATE.items():
        assert decode_statusword(low_bits) is state
        assert decode_statusword(low_bits | 0x0010 | 0x0200) is state


def test_transition_table_is_numbered_and_consistent():
    assert [t.number for t in TRANSITIONS] == list(range(17))
    for t in TRANSITIONS:
        automatic = t.number in AUTOMATIC_TRANSITIONS
        assert (t.command is None) == automatic, t
        assert (t.from_state is None) == (t.number in (0, 13)), t
    assert TRANSITIONS[12].automatic_too
    assert TRANSITIONS[5].command is Controlword.SWITCH_ON  # disable operation = 0x0007
    assert TRANSITIONS[15].command is Controlword.FAULT_RESET
    assert {t.number for t in TRANSITIONS if t.command is Controlword.SHUTDOWN} == {2, 6, 8}
    assert {t.number for t in TRANSITIONS if t.command is Controlword.ENABLE_OPERATION} == {4, 16}
    assert {t.number for t in TRANSITIONS
            if t.command is Controlword.DISABLE_VOLTAGE} == {7, 9, 10, 12}
    assert {t.number for t in TRANSITIONS
            if Controlword.QUICK_STOP in (t.command, *t.alternatives)} == {7, 10, 11}


def test_transition_between():
    for t in TRANSITIONS:
        if t.from_state is not None:
            assert transition_between(t.from_state, t.to_state) == t.number
    assert transition_between(State.OPERATION_ENABLED, State.FAULT_REACTION_ACTIVE) == 13
    assert transition_between(State.SWITCH_ON_DISABLED, State.FAULT_REACTION_ACTIVE) == 13
    assert transition_between(State.NOT_READY_TO_SWITCH_ON, State.READY_TO_SWITCH_ON) is None
    assert transition_between(State.UNKNOWN, State.FAULT_REACTION_ACTIVE) is None
    assert transition_between(State.SWITCH_ON_DISABLED, State.OPERATION_ENABLED) is None


def test_allowed_controlwords_cover_transitions_and_keep_commands():
    for t in TRANSITIONS:
        if t.from_state is not None and t.command is not None:
            assert t.command in allowed_controlwords(t.from_state)
            assert set(t.alternatives) <= allowed_controlwords(t.from_state)
    for state, keep in STATE_KEEP_COMMANDS.items():
        assert keep <= allowed_controlwords(state)
    assert allowed_controlwords(State.NOT_READY_TO_SWITCH_ON) == {Controlword.DISABLE_VOLTAGE}
    assert allowed_controlwords(State.FAULT_REACTION_ACTIVE) == {Controlword.DISABLE_VOLTAGE}
    assert allowed_controlwords(State.FAULT) == {Controlword.DISABLE_VOLTAGE, Controlword.FAULT_RESET}
    assert Controlword.ENABLE_OPERATION not in allowed_controlwords(State.SWITCH_ON_DISABLED)
    assert Controlword.ENABLE_OPERATION in allowed_controlwords(State.READY_TO_SWITCH_ON)  # 3+4
    assert Controlword.SHUTDOWN not in allowed_controlwords(State.QUICK_STOP_ACTIVE)
    unknown = allowed_controlwords(State.UNKNOWN)
    assert Controlword.ENABLE_OPERATION not in unknown and Controlword.FAULT_RESET not in unknown
    for state in State:
        if state is not State.FAULT:
            assert Controlword.FAULT_RESET not in allowed_controlwords(state)
