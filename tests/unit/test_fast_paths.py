"""The cycle's fast paths give the same results as the full work they skip.

- ``DriveController`` reusing a settled step (``reuse_settled``) against one that always steps in
  full, over random command and statusword sequences that repeat inputs often;
- the statusword lookup table against the standard's (mask, value) patterns.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from bus_agent.cia402.controller import ControllerConfig, DriveController, Goal
from bus_agent.cia402.states import STATUSWORD_OF_STATE, STATUSWORD_PATTERNS, State, decode_statusword

# a few statuswords per state (bit 4 and bits 8+ vary), so that inputs repeat often
_sw = st.builds(lambda low, extra: low | extra, st.sampled_from(sorted(STATUSWORD_OF_STATE.values())),
                st.sampled_from([0x0000, 0x0010, 0x0210, 0x0610]))
_step = st.tuples(st.just("step"), st.one_of(_sw, st.integers(0, 0xFFFF)),
                  st.sampled_from([None, None, 0, 8, 9]), st.sampled_from([0.0, 0.001, 0.001, 0.05, 0.3, 6.0]))
_repeat = st.tuples(st.just("repeat"), st.integers(1, 30), st.sampled_from([0.001, 0.1, 2.0]))
_cmd = st.one_of(
    st.tuples(st.just("goal"), st.sampled_from(list(Goal))),
    st.tuples(st.just("halt"), st.booleans()),
    st.tuples(st.just("mode"), st.sampled_from([1, 3, 8, 9, 10])),
    st.tuples(st.just("reset")),
)
_configs = st.builds(ControllerConfig, transition_timeout_s=st.sampled_from([0.2, 1.0]),
                     mode_timeout_s=st.sampled_from([0.2, 1.0]), fault_reset_retries=st.integers(1, 3),
                     fault_reset_low_s=st.sampled_from([0.0, 0.01]), fault_reset_high_s=st.sampled_from([0.0, 0.05]),
                     not_ready_grace_s=st.sampled_from([0.0, 0.1]))


def _view(c: DriveController) -> tuple:
    return (c.state, c.goal, c.goal_phase, c.halt, c.mode, c.mode_pending, c.fault_reset_active, c.statusword)


@settings(max_examples=150, deadline=None)
@given(_configs, st.sampled_from([None, frozenset({8, 9}), frozenset({1, 3, 8, 9, 10})]),
       st.lists(st.one_of(_step, _step, _repeat, _cmd), min_size=1, max_size=80))
def test_a_settled_step_reused_equals_a_full_step(config, modes, actions):
    fast = DriveController(config, supported_modes=modes)
    full = DriveController(config, supported_modes=modes)
    full.reuse_settled = False
    t = 0.0
    last = (0, 0)
    for a in actions:
        if a[0] in ("step", "repeat"):
            if a[0] == "step":
                sw, md, dt = a[1], a[2], a[3]
                last = (sw, fast.mode if md is None else md)
                steps = 1
            else:
                steps, dt = a[1], a[2]
            for _ in range(steps):
                t += dt
                assert fast.step(*last, t) == full.step(*last, t)
                assert _view(fast) == _view(full)
        elif a[0] == "goal":
            fast.set_goal(a[1], t)
            full.set_goal(a[1], t)
        elif a[0] == "halt":
            fast.set_halt(a[1])
            full.set_halt(a[1])
        elif a[0] == "mode":
            fast.request_mode(a[1], t)
            full.request_mode(a[1], t)
        else:
            fast.request_fault_reset(t)
            full.request_fault_reset(t)


def test_a_settled_controller_reuses_its_output_and_any_command_drops_it():
    c = DriveController(ControllerConfig(), mode=8)
    c.set_goal(Goal.ENABLED, 0.0)
    t = 0.0
    for sw in (0x0250, 0x0231, 0x0233, 0x0237):
        t += 0.001
        c.step(sw, 8, t)
    out = c.step(0x0237, 8, t + 0.001)  # goal reached in the step before: settled now
    assert out.events == () and out.controlword == 0x000F
    assert c.step(0x0237, 8, t + 10.0) is out          # same inputs, any time: the same output
    assert c.step(0x0233, 8, t + 10.0) is not out      # new inputs: a full step (goal lost)
    c2 = DriveController(ControllerConfig(), mode=8)
    c2.set_goal(Goal.DISABLED, 0.0)
    first = c2.step(0x0250, 8, 0.0)
    assert first.events  # goal reached, mode confirmed
    again = c2.step(0x0250, 8, 0.001)
    assert c2.step(0x0250, 8, 0.002) is again
    c2.set_halt(True)
    halted = c2.step(0x0250, 8, 0.003)
    assert halted is not again and halted.controlword & 0x0100
    c2.request_mode(9, 0.004)
    assert c2.step(0x0250, 8, 0.005).mode_of_operation == 9


def test_the_statusword_table_equals_the_standards_patterns():
    for sw in range(0x10000):
        expected = next((s for mask, value, s in STATUSWORD_PATTERNS if sw & mask == value), State.UNKNOWN)
        assert decode_statusword(sw) is expected
