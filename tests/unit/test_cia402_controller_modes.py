"""DriveController: modes (echo, timeouts, refusals), the hold target, halt, unknown statuswords,
the Indy7 tolerance, bad input, and a closed loop against the drive model. Pure: times are passed in."""

from __future__ import annotations

import pytest

from bus_agent.cia402.controller import (
    RAISING_TRANSITIONS,
    ControllerConfig,
    ControllerOutput,
    DriveController,
    EventKind,
    Goal,
)
from bus_agent.cia402.states import decode_statusword
from tests.unit.cia402_rig import CW, DT, S, in_state, kinds, sw


# --- modes -------------------------------------------------------------------------------------


def test_mode_change_confirmed_by_echo():
    c = DriveController(mode=8)
    out = c.step(sw(S.SWITCH_ON_DISABLED), 8, 0.0)
    assert EventKind.MODE_CONFIRMED in kinds(out) and out.mode_of_operation == 8
    c.request_mode(9, 1.0)
    out = c.step(sw(S.SWITCH_ON_DISABLED), 8, 1.0)
    assert out.mode_of_operation == 9 and EventKind.MODE_CONFIRMED not in kinds(out)
    out = c.step(sw(S.SWITCH_ON_DISABLED), 9, 1.1)
    assert [e for e in out.events if e.kind is EventKind.MODE_CONFIRMED][0].reason == "0x6061 = 9"
    assert not kinds(c.step(sw(S.SWITCH_ON_DISABLED), 9, 1.2))


def test_mode_timeout_once():
    c = DriveController(ControllerConfig(mode_timeout_s=0.5), mode=8)
    c.step(sw(S.SWITCH_ON_DISABLED), 8, 0.0)
    c.request_mode(1, 1.0)
    assert not kinds(c.step(sw(S.SWITCH_ON_DISABLED), 8, 1.4))
    assert kinds(c.step(sw(S.SWITCH_ON_DISABLED), 8, 1.5)) == [EventKind.MODE_TIMEOUT]
    assert not kinds(c.step(sw(S.SWITCH_ON_DISABLED), 8, 9.0))


def test_mode_rejected_changes_nothing():
    c = DriveController(mode=8, supported_modes=frozenset({1, 8, 9}))
    c.step(sw(S.SWITCH_ON_DISABLED), 8, 0.0)
    c.request_mode(10, 1.0)
    out = c.step(sw(S.SWITCH_ON_DISABLED), 8, 1.0)
    assert kinds(out) == [EventKind.MODE_REJECTED] and out.mode_of_operation == 8 and c.mode == 8
    with pytest.raises(ValueError):
        c.request_mode(300, 1.0)
    with pytest.raises(ValueError):
        DriveController(mode=10, supported_modes=frozenset({8}))
    assert c.mode == 8


def test_enable_operation_waits_for_the_mode_echo():
    c, out = in_state(S.SWITCHED_ON, Goal.ENABLED, mode_display=1)
    assert out.controlword == CW.SWITCH_ON
    assert c.step(sw(S.SWITCHED_ON), 8, DT).controlword == CW.ENABLE_OPERATION
    c2 = DriveController(ControllerConfig(enable_requires_mode_echo=False))
    c2.set_goal(Goal.ENABLED, 0.0)
    assert c2.step(sw(S.SWITCHED_ON), 1, 0.0).controlword == CW.ENABLE_OPERATION


# --- hold target, halt -------------------------------------------------------------------------


@pytest.mark.parametrize("mode", [8, 9])
def test_hold_target_in_csp_csv_until_operation_enabled(mode):
    c = DriveController(mode=mode)
    c.set_goal(Goal.ENABLED, 0.0)
    for i, state in enumerate([S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON]):
        assert c.step(sw(state), mode, i * DT).hold_target
    assert not c.step(sw(S.OPERATION_ENABLED), mode, 3 * DT).hold_target
    # a mode switch while enabled: hold again until 0x6061 echoes
    other = 9 if mode == 8 else 8
    c.request_mode(other, 4 * DT)
    assert c.step(sw(S.OPERATION_ENABLED), mode, 4 * DT).hold_target
    assert not c.step(sw(S.OPERATION_ENABLED), other, 5 * DT).hold_target
    assert c.step(sw(S.QUICK_STOP_ACTIVE), other, 6 * DT).hold_target


@pytest.mark.parametrize("mode", [1, 3, 10])
def test_no_hold_target_outside_csp_csv(mode):
    c = DriveController(mode=mode)
    assert not c.step(sw(S.SWITCHED_ON), mode, 0.0).hold_target


def test_halt_bit_8():
    c, out = in_state(S.OPERATION_ENABLED, Goal.ENABLED)
    assert out.controlword == 0x000F
    c.set_halt(True)
    out = c.step(sw(S.OPERATION_ENABLED), 8, DT)
    assert out.controlword == 0x010F and c.state is S.OPERATION_ENABLED
    c.set_goal(Goal.DISABLED, 2 * DT)
    assert c.step(sw(S.OPERATION_ENABLED), 8, 2 * DT).controlword == 0x0107
    c.set_halt(False)
    assert c.step(sw(S.SWITCHED_ON), 8, 3 * DT).controlword == 0x0006


# --- unknown statuswords, Indy7, bad input ---------------------------------------------------


def test_unknown_statusword_never_enables_and_is_reported():
    c, _ = in_state(S.OPERATION_ENABLED, Goal.ENABLED)
    assert decode_statusword(0x0001) is S.UNKNOWN
    out = c.step(0x0001, 8, DT)
    assert out.controlword == 0x0007
    assert any(e.kind is EventKind.TRANSITION and e.to_state is S.UNKNOWN
               and e.reason == "unknown statusword 0x0001" for e in out.events)
    assert EventKind.GOAL_FAILED in kinds(out)
    assert c.step(0x0001, 8, 2 * DT).controlword == 0x0007
    # back in switched on: the failed goal is not retried upward
    assert c.step(sw(S.SWITCHED_ON), 8, 3 * DT).controlword == CW.SWITCH_ON


def test_unknown_statusword_keeps_the_last_safe_command():
    c, out = in_state(S.READY_TO_SWITCH_ON, Goal.DISABLED)
    assert out.controlword == CW.DISABLE_VOLTAGE
    assert c.step(0x0003, 8, DT).controlword == CW.DISABLE_VOLTAGE
    c2, out = in_state(S.SWITCH_ON_DISABLED, Goal.ENABLED)
    assert out.controlword == CW.SHUTDOWN
    assert c2.step(0x0003, 8, DT).controlword == CW.SHUTDOWN


def test_indy7_0x0220_gets_shutdown_after_grace_and_is_enabled():
    cfg = ControllerConfig(not_ready_grace_s=0.1)
    c = DriveController(cfg)
    c.set_goal(Goal.ENABLED, 0.0)
    assert decode_statusword(0x0220) is S.NOT_READY_TO_SWITCH_ON
    assert c.step(0x0220, 8, 0.0).controlword == CW.DISABLE_VOLTAGE
    assert c.step(0x0220, 8, 0.05).controlword == CW.DISABLE_VOLTAGE
    assert c.step(0x0220, 8, 0.1).controlword == CW.SHUTDOWN
    out = c.step(0x0221, 8, 0.11)
    assert out.controlword == CW.SWITCH_ON and c.state is S.READY_TO_SWITCH_ON
    assert any(e.reason == "not a standard transition" for e in out.events)
    assert c.step(0x0233, 8, 0.12).controlword == CW.ENABLE_OPERATION
    out = c.step(0x0237, 8, 0.13)
    assert out.controlword == CW.ENABLE_OPERATION and EventKind.GOAL_REACHED in kinds(out)


@pytest.mark.parametrize("goal", [Goal.DISABLED, Goal.QUICK_STOP])
def test_indy7_tolerance_not_used_for_disabled_or_quick_stop(goal):
    c = DriveController()
    c.set_goal(goal, 0.0)
    for i in range(20):
        assert c.step(0x0220, 8, i * 0.05).controlword == CW.DISABLE_VOLTAGE


def test_bad_input_raises_and_changes_nothing():
    c, _ = in_state(S.READY_TO_SWITCH_ON, Goal.READY)
    with pytest.raises(ValueError):
        c.set_goal("bogus", 1.0)  # type: ignore[arg-type]
    assert c.goal is Goal.READY
    with pytest.raises(ValueError):
        c.step(0x10000, 8, 1.0)
    with pytest.raises(ValueError):
        c.step(-1, 8, 1.0)
    assert c.state is S.READY_TO_SWITCH_ON
    c.set_goal("switched_on", 1.0)  # type: ignore[arg-type]  # wire value accepted
    assert c.goal is Goal.SWITCHED_ON
    for bad in (dict(fault_reset_retries=0), dict(transition_timeout_s=-1.0),
                dict(quick_stop_option_code=0x10000), dict(fault_reset_low_s=float("nan"))):
        with pytest.raises(ValueError):
            ControllerConfig(**bad)


def test_raising_transitions_are_the_upward_ones():
    assert RAISING_TRANSITIONS == {2, 3, 4, 16}


# --- closed loop against the project's drive model (extra; the core tests do not need it) --


@pytest.mark.parametrize("profile", ["generic", "indy7"])
def test_closed_loop_with_drive_model(profile):
    from bus_agent.bus.pdo import DriveOutputs
    from bus_agent.sim.drive_model import PROFILES, DriveModel

    drive = DriveModel(PROFILES[profile])
    c = DriveController(mode=8)
    c.set_goal(Goal.ENABLED, 0.0)
    t, events = 0.0, []

    def cycle() -> ControllerOutput:
        nonlocal t
        inputs = drive.inputs()
        out = c.step(inputs.statusword, inputs.modes_of_operation_display, t)
        events.extend(out.events)
        # no trajectory here: the target is the actual position whether held or not
        drive.apply_outputs(DriveOutputs(controlword=out.controlword, target_position=inputs.position_actual,
                                         modes_of_operation=out.mode_of_operation))
        drive.step(DT)
        t += DT
        return out

    for _ in range(1000):
        cycle()
        if c.state is S.OPERATION_ENABLED:
            break
    assert c.state is S.OPERATION_ENABLED, [e for e in events if e.kind is EventKind.TRANSITION]
    assert EventKind.GOAL_REACHED in [e.kind for e in events]
    drive.inject_fault(0x2310)
    for _ in range(200):
        out = cycle()
        assert not out.controlword & 0x80
    assert c.state is S.FAULT
    c.request_fault_reset(t)
    for _ in range(500):
        cycle()
        if any(e.kind is EventKind.FAULT_RESET_DONE for e in events):
            break
    assert c.state is S.SWITCH_ON_DISABLED and c.goal is Goal.DISABLED
    c.set_goal(Goal.ENABLED, t)
    for _ in range(1000):
        cycle()
        if c.state is S.OPERATION_ENABLED:
            break
    assert c.state is S.OPERATION_ENABLED
    c.set_goal(Goal.DISABLED, t)
    seen = []
    for _ in range(1000):
        out = cycle()
        if not seen or seen[-1] != out.controlword:
            seen.append(out.controlword)
        if c.state is S.SWITCH_ON_DISABLED:
            break
    assert c.state is S.SWITCH_ON_DISABLED
    assert seen[:3] == [0x0007, 0x0006, 0x0000]
