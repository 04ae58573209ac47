"""Hypothesis properties of DriveController over arbitrary statuswords, goals and commands.

(a) no goal other than ENABLED ever yields Enable operation (bits 0-3 set, bit 7 clear);
(b) bit 7 (fault reset) is set only while a requested fault reset is under way, and only in Fault;
(c) every controlword is one the standard defines for the decoded state (allowed_controlwords),
    Shutdown in not_ready_to_switch_on only under the documented Indy7 tolerance.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from bus_agent.cia402.controller import ControllerConfig, DriveController, EventKind, Goal
from bus_agent.cia402.states import (
    CONTROLWORD_COMMAND_MASK,
    STATUSWORD_OF_STATE,
    Controlword,
    State,
    allowed_controlwords,
    decode_statusword,
)

EXAMPLES = 400
GRACE_S = 0.1

# statuswords: every state's pattern with random extra bits, the Indy7 values, and raw u16s
_state_sw = st.builds(
    lambda low, extra: low | (extra & 0xFF90),
    st.sampled_from(sorted(STATUSWORD_OF_STATE.values())),
    st.integers(0, 0xFFFF),
)
statuswords = st.one_of(_state_sw, _state_sw, st.sampled_from([0x0220, 0x0221, 0x0233, 0x0237]),
                        st.integers(0, 0xFFFF))
dts = st.one_of(st.sampled_from([0.0, 0.001, 0.01, 0.05, 0.1, 6.0]), st.floats(0.0, 0.3))
# None: 0x6061 echoes the controller's requested mode
mode_displays = st.one_of(st.none(), st.sampled_from([0, 1, 3, 8, 9, 10]))

step_action = st.tuples(st.just("step"), statuswords, mode_displays, dts)
other_actions = st.one_of(
    st.tuples(st.just("goal"), st.sampled_from(list(Goal))),
    st.tuples(st.just("halt"), st.booleans()),
    st.tuples(st.just("mode"), st.sampled_from([1, 3, 6, 8, 9, 10])),
)
reset_action = st.tuples(st.just("reset"))


def _sequences(with_reset: bool):
    options = [step_action, step_action, step_action, other_actions]
    if with_reset:
        options.append(reset_action)
    return st.lists(st.one_of(*options), min_size=1, max_size=120)


configs = st.builds(
    ControllerConfig,
    transition_timeout_s=st.sampled_from([0.2, 1.0, 5.0]),
    fault_reset_retries=st.integers(1, 4),
    fault_reset_low_s=st.sampled_from([0.0, 0.01]),
    fault_reset_high_s=st.sampled_from([0.0, 0.05]),
    not_ready_grace_s=st.just(GRACE_S),
    mode_timeout_s=st.sampled_from([0.2, 5.0]),
    quick_stop_option_code=st.integers(0, 8),
    enable_requires_mode_echo=st.booleans(),
)


def _drive(config, actions, check):
    """Apply ``actions``; call ``check(controller, decoded_state, controlword, ctx)`` per step."""
    c = DriveController(config, supported_modes=frozenset({1, 3, 8, 9, 10}))
    now = 0.0
    ctx = {"reset_open": False, "state": None, "since": 0.0, "now": 0.0}
    for action in actions:
        kind = action[0]
        if kind == "goal":
            c.set_goal(action[1], now)
        elif kind == "halt":
            c.set_halt(action[1])
        elif kind == "mode":
            c.request_mode(action[1], now)
        elif kind == "reset":
            ctx["reset_open"] = True
            c.request_fault_reset(now)
        else:
            _, statusword, display, dt = action
            now += dt
            state = decode_statusword(statusword)
            if state is not ctx["state"]:
                ctx["state"], ctx["since"] = state, now
            ctx["now"] = now
            out = c.step(statusword, c.mode if display is None else display, now)
            check(c, state, out.controlword, ctx)
            if any(e.kind in (EventKind.FAULT_RESET_DONE, EventKind.FAULT_RESET_FAILED) for e in out.events):
                ctx["reset_open"] = False
            assert out.mode_of_operation == c.mode
            assert 0 <= out.controlword <= 0xFFFF


@settings(max_examples=EXAMPLES, deadline=None)
@given(configs, _sequences(with_reset=True))
def test_a_only_goal_enabled_yields_enable_operation(config, actions):
    def check(c, state, controlword, ctx):
        if c.goal is not Goal.ENABLED:
            assert controlword & CONTROLWORD_COMMAND_MASK != 0x000F, (c.goal, state, hex(controlword))
    _drive(config, actions, check)


@settings(max_examples=EXAMPLES, deadline=None)
@given(configs, _sequences(with_reset=True))
def test_b_no_fault_reset_without_request(config, actions):
    def check(c, state, controlword, ctx):
        if controlword & 0x0080:
            assert ctx["reset_open"], "bit 7 set without request_fault_reset"
            assert state is State.FAULT
    _drive(config, actions, check)


@settings(max_examples=EXAMPLES, deadline=None)
@given(configs, _sequences(with_reset=False))
def test_b_never_bit_7_when_no_reset_is_ever_requested(config, actions):
    def check(c, state, controlword, ctx):
        assert not controlword & 0x0080
    _drive(config, actions, check)


@settings(max_examples=EXAMPLES, deadline=None)
@given(configs, _sequences(with_reset=True))
def test_c_only_controlwords_the_standard_defines_for_the_state(config, actions):
    def check(c, state, controlword, ctx):
        command = controlword & CONTROLWORD_COMMAND_MASK
        allowed = set(allowed_controlwords(state))
        if (state is State.NOT_READY_TO_SWITCH_ON
                and c.goal in (Goal.READY, Goal.SWITCHED_ON, Goal.ENABLED)
                and ctx["now"] - ctx["since"] >= GRACE_S):
            allowed.add(Controlword.SHUTDOWN)  # documented Indy7 tolerance
        assert command in allowed, (state, c.goal, hex(controlword))
        assert controlword & ~(CONTROLWORD_COMMAND_MASK | 0x0100) == 0  # only command bits and halt
        assert bool(controlword & 0x0100) == c.halt
    _drive(config, actions, check)
