"""DriveController: the per-transition commands, goals, deadlines, fault reset edge, modes,
hold target, halt, unknown statuswords and the Indy7 tolerance. Pure: times are passed in."""

from __future__ import annotations

import pytest

from bus_agent.cia402.controller import (
    GOAL_TARGETS,
    NEXT_STEP,
    NEXT_STEP_QUICK_STOP_STAYS,
    ControllerConfig,
    DriveController,
    EventKind,
    Goal,
    next_step,
)
from bus_agent.cia402.states import TRANSITIONS, State
from tests.unit.cia402_rig import CW, DT, S, TinyDrive, in_state, kinds, run, sw


# --- the next-step table ---------------------------------------------------------------------


def test_next_step_table_is_complete_and_uses_the_transition_table():
    for table in (NEXT_STEP, NEXT_STEP_QUICK_STOP_STAYS):
        for (state, goal), step in table.items():
            if step.transition is not None:
                t = TRANSITIONS[step.transition]
                assert t.from_state is state, (state, goal, step)
                assert step.command == t.command or step.command in t.alternatives
    for state in State:
        if state is not S.UNKNOWN:
            for goal in Goal:
                assert (state, goal) in NEXT_STEP


@pytest.mark.parametrize("stays", [False, True])
@pytest.mark.parametrize("goal", list(Goal))
@pytest.mark.parametrize("start", [S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON,
                                   S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE])
def test_following_the_table_reaches_every_goal(start, goal, stays):
    state, path = start, []
    for _ in range(6):
        if state in GOAL_TARGETS[goal]:
            break
        step = next_step(state, goal, stays_in_quick_stop=stays)
        if step.transition is None:  # waiting for the automatic transition 12 (0x605A 0..4)
            assert state is S.QUICK_STOP_ACTIVE and not stays
            step_to = TRANSITIONS[12]
        else:
            step_to = TRANSITIONS[step.transition]
        path.append(step_to.number)
        state = step_to.to_state
    assert state in GOAL_TARGETS[goal], (start, goal, path)
    assert 9 not in path  # never disable voltage from operation enabled (the motor would coast)


# --- one test per transition 0..16 ---------------------------------------------------------


def test_transition_0_observed_on_the_first_statusword():
    c = DriveController()
    out = c.step(0x0000, 0, 0.0)
    ev = [e for e in out.events if e.kind is EventKind.TRANSITION]
    assert ev and ev[0].to_state is S.NOT_READY_TO_SWITCH_ON and ev[0].reason == "transition 0"
    assert out.controlword == CW.DISABLE_VOLTAGE


def test_transition_1_observed_automatic():
    c = DriveController()
    c.step(0x0000, 8, 0.0)
    out = c.step(0x0250, 8, DT)
    assert [(e.from_state, e.to_state, e.reason) for e in out.events if e.kind is EventKind.TRANSITION] == [
        (S.NOT_READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED, "transition 1")]
    assert EventKind.GOAL_REACHED in kinds(out)  # the initial goal is DISABLED
    assert out.controlword == CW.DISABLE_VOLTAGE


@pytest.mark.parametrize("number, from_state, goal, qs_code, command", [
    (2, S.SWITCH_ON_DISABLED, Goal.READY, 2, CW.SHUTDOWN),
    (2, S.SWITCH_ON_DISABLED, Goal.ENABLED, 2, CW.SHUTDOWN),
    (3, S.READY_TO_SWITCH_ON, Goal.SWITCHED_ON, 2, CW.SWITCH_ON),
    (3, S.READY_TO_SWITCH_ON, Goal.ENABLED, 2, CW.SWITCH_ON),
    (4, S.SWITCHED_ON, Goal.ENABLED, 2, CW.ENABLE_OPERATION),
    (5, S.OPERATION_ENABLED, Goal.DISABLED, 2, CW.SWITCH_ON),  # disable operation 0x0007
    (5, S.OPERATION_ENABLED, Goal.SWITCHED_ON, 2, CW.SWITCH_ON),
    (6, S.SWITCHED_ON, Goal.READY, 2, CW.SHUTDOWN),
    (6, S.SWITCHED_ON, Goal.DISABLED, 2, CW.SHUTDOWN),
    (7, S.READY_TO_SWITCH_ON, Goal.DISABLED, 2, CW.DISABLE_VOLTAGE),
    (7, S.READY_TO_SWITCH_ON, Goal.QUICK_STOP, 2, CW.QUICK_STOP),
    (8, S.OPERATION_ENABLED, Goal.READY, 2, CW.SHUTDOWN),
    (10, S.SWITCHED_ON, Goal.QUICK_STOP, 2, CW.QUICK_STOP),
    (11, S.OPERATION_ENABLED, Goal.QUICK_STOP, 2, CW.QUICK_STOP),
    (12, S.QUICK_STOP_ACTIVE, Goal.DISABLED, 6, CW.DISABLE_VOLTAGE),
    (12, S.QUICK_STOP_ACTIVE, Goal.READY, 6, CW.DISABLE_VOLTAGE),
    (16, S.QUICK_STOP_ACTIVE, Goal.ENABLED, 6, CW.ENABLE_OPERATION),
])
def test_commanded_transition(number, from_state, goal, qs_code, command):
    t = TRANSITIONS[number]
    assert t.from_state is from_state
    assert command == t.command or command in t.alternatives
    c, out = in_state(from_state, goal, ControllerConfig(quick_stop_option_code=qs_code))
    assert out.controlword == command
    assert EventKind.GOAL_REACHED not in kinds(out)
    # the drive makes the transition; the controller reports it with its number
    out = c.step(sw(t.to_state), 8, DT)
    assert any(e.kind is EventKind.TRANSITION and e.reason == f"transition {number}" for e in out.events)


def test_transition_9_is_never_chosen():
    """Disable voltage from operation enabled lets the motor coast: no goal uses it."""
    for goal in Goal:
        _, out = in_state(S.OPERATION_ENABLED, goal)
        assert out.controlword & 0x8F != CW.DISABLE_VOLTAGE, goal
    # the controller still names it when a drive does it by itself
    c, _ = in_state(S.OPERATION_ENABLED, Goal.ENABLED)
    out = c.step(sw(S.SWITCH_ON_DISABLED), 8, DT)
    assert any(e.reason == "transition 9" for e in out.events)
    assert EventKind.GOAL_FAILED in kinds(out)


@pytest.mark.parametrize("goal", [Goal.DISABLED, Goal.READY, Goal.ENABLED])
def test_transition_12_automatic_with_option_code_0_to_4(goal):
    c, out = in_state(S.QUICK_STOP_ACTIVE, goal, ControllerConfig(quick_stop_option_code=2))
    assert out.controlword == CW.QUICK_STOP  # wait: the drive leaves by itself
    out = c.step(sw(S.SWITCH_ON_DISABLED), 8, DT)
    assert any(e.reason == "transition 12" for e in out.events)


def test_transition_16_waits_when_the_drive_does_not_stay_in_quick_stop():
    c, out = in_state(S.QUICK_STOP_ACTIVE, Goal.ENABLED, ControllerConfig(quick_stop_option_code=1))
    assert out.controlword == CW.QUICK_STOP


def test_transitions_13_and_14_observed():
    c, out = in_state(S.OPERATION_ENABLED, Goal.ENABLED)
    assert EventKind.GOAL_REACHED in kinds(out)
    out = c.step(sw(S.FAULT_REACTION_ACTIVE), 8, DT)
    assert [e.reason for e in out.events if e.kind is EventKind.TRANSITION] == ["transition 13"]
    assert EventKind.FAULT in kinds(out) and EventKind.GOAL_FAILED in kinds(out)
    assert out.controlword == CW.DISABLE_VOLTAGE
    out = c.step(sw(S.FAULT), 8, 2 * DT)
    assert [e.reason for e in out.events if e.kind is EventKind.TRANSITION] == ["transition 14"]
    assert EventKind.FAULT not in kinds(out)  # one fault, one FAULT event
    assert out.controlword == CW.DISABLE_VOLTAGE


def test_transition_15_fault_reset_edge():
    cfg = ControllerConfig(fault_reset_low_s=0.01, fault_reset_high_s=0.05)
    c = DriveController(cfg)
    drive = TinyDrive(S.FAULT)
    run(c, drive, 0.0, 50)
    assert drive.state is S.FAULT and drive.edges == 0  # nobody asked: no reset
    c.request_fault_reset(0.05)
    cws, events, _ = run(c, drive, 0.05, 30)
    first_high = next(i for i, cw in enumerate(cws) if cw & 0x80)
    assert first_high >= 10  # low for fault_reset_low_s first
    assert all(cw == 0x0000 for cw in cws[:first_high])
    assert cws[first_high] == CW.FAULT_RESET
    assert drive.edges == 1 and drive.state is S.SWITCH_ON_DISABLED
    done = [e for e in events if e.kind is EventKind.FAULT_RESET_DONE]
    assert len(done) == 1 and done[0].reason == "transition 15 to switch_on_disabled"
    assert any(e.kind is EventKind.TRANSITION and e.reason == "transition 15" for e in events)
    assert cws[-1] == CW.DISABLE_VOLTAGE
    assert c.goal is Goal.DISABLED and c.goal_phase == "reached"


# --- seed 000: enable, and the disable order -----------------------------------------------


def test_enable_sequence_then_seed_000_disable_order():
    c = DriveController()
    drive = TinyDrive()
    c.set_goal(Goal.ENABLED, 0.0)
    cws, events, t = run(c, drive, 0.0, 10)
    assert drive.state is S.OPERATION_ENABLED
    distinct = [cw for i, cw in enumerate(cws) if i == 0 or cw != cws[i - 1]]
    assert distinct == [0x0000, CW.SHUTDOWN, CW.SWITCH_ON, CW.ENABLE_OPERATION]
    assert [e.kind for e in events].count(EventKind.GOAL_REACHED) == 1
    c.set_goal(Goal.DISABLED, t)
    cws, events, t = run(c, drive, t, 6)
    distinct = [cw for i, cw in enumerate(cws) if i == 0 or cw != cws[i - 1]]
    assert distinct == [0x0007, 0x0006, 0x0000]  # disable operation, shutdown, disable voltage
    assert [e.reason for e in events if e.kind is EventKind.TRANSITION] == [
        "transition 5", "transition 6", "transition 7"]
    assert drive.state is S.SWITCH_ON_DISABLED
    assert [e.kind for e in events].count(EventKind.GOAL_REACHED) == 1


# --- fault reset: bounded retries, no blind reset -------------------------------------------


def test_fault_reset_bounded_retries_then_failed_once():
    cfg = ControllerConfig(fault_reset_retries=3, fault_reset_low_s=0.002, fault_reset_high_s=0.003)
    c = DriveController(cfg)
    drive = TinyDrive(S.FAULT, fault_sticks=True)
    run(c, drive, 0.0, 3)
    c.request_fault_reset(0.003)
    cws, events, _ = run(c, drive, 0.003, 200)
    assert drive.edges == 3
    rising = sum(1 for a, b in zip([0] + cws, cws) if b & 0x80 and not a & 0x80)
    assert rising == 3
    failed = [e for e in events if e.kind is EventKind.FAULT_RESET_FAILED]
    assert len(failed) == 1 and "3 reset edges" in failed[0].reason
    assert not any(e.kind is EventKind.FAULT_RESET_DONE for e in events)
    assert all(cw == 0 for cw in cws[-150:])  # not retried forever
    assert not c.fault_reset_active


def test_fault_with_goal_enabled_fails_the_goal_and_is_not_reset():
    c = DriveController()
    drive = TinyDrive(S.SWITCH_ON_DISABLED)
    c.set_goal(Goal.ENABLED, 0.0)
    _, _, t = run(c, drive, 0.0, 5)
    assert drive.state is S.OPERATION_ENABLED
    drive.state = S.FAULT_REACTION_ACTIVE
    cws, events, t = run(c, drive, t, 2)
    drive.state = S.FAULT
    more, events2, _ = run(c, drive, t, 500)
    events += events2
    assert [e.kind for e in events].count(EventKind.GOAL_FAILED) == 1
    assert [e.kind for e in events].count(EventKind.FAULT) == 1
    assert not any(cw & 0x80 for cw in cws + more)
    assert drive.edges == 0 and drive.state is S.FAULT
    assert EventKind.GOAL_TIMEOUT not in [e.kind for e in events]


def test_fault_reset_without_fault_is_done_and_changes_nothing():
    c, _ = in_state(S.OPERATION_ENABLED, Goal.ENABLED)
    c.request_fault_reset(DT)
    out = c.step(sw(S.OPERATION_ENABLED), 8, DT)
    done = [e for e in out.events if e.kind is EventKind.FAULT_RESET_DONE]
    assert len(done) == 1 and done[0].reason == "no fault to reset"
    assert out.controlword == CW.ENABLE_OPERATION and c.goal is Goal.ENABLED


def test_fault_reset_waits_through_fault_reaction_active():
    c = DriveController(ControllerConfig(fault_reset_low_s=0.0, fault_reset_high_s=0.0))
    c.step(sw(S.FAULT_REACTION_ACTIVE), 8, 0.0)
    c.request_fault_reset(0.0)
    for i in range(1, 5):
        out = c.step(sw(S.FAULT_REACTION_ACTIVE), 8, i * DT)
        assert out.controlword == 0 and not out.events
    out = c.step(sw(S.FAULT), 8, 5 * DT)
    assert out.controlword == CW.FAULT_RESET  # previous cycle had bit 7 low: a real edge
    out = c.step(sw(S.SWITCH_ON_DISABLED), 8, 6 * DT)
    assert EventKind.FAULT_RESET_DONE in kinds(out)


def test_fault_reset_gives_up_when_fault_reaction_never_ends():
    cfg = ControllerConfig(transition_timeout_s=0.5)
    c = DriveController(cfg)
    c.step(sw(S.FAULT_REACTION_ACTIVE), 8, 0.0)
    c.request_fault_reset(0.0)
    assert not kinds(c.step(sw(S.FAULT_REACTION_ACTIVE), 8, 0.4))
    out = c.step(sw(S.FAULT_REACTION_ACTIVE), 8, 0.5)
    assert EventKind.FAULT_RESET_FAILED in kinds(out)


def test_goal_set_during_fault_reset_is_kept():
    cfg = ControllerConfig(fault_reset_low_s=0.0, fault_reset_high_s=0.0)
    c = DriveController(cfg)
    drive = TinyDrive(S.FAULT)
    run(c, drive, 0.0, 2)
    c.request_fault_reset(0.002)
    c.set_goal(Goal.ENABLED, 0.002)  # explicitly asked after the reset request
    cws, events, _ = run(c, drive, 0.002, 10)
    assert EventKind.FAULT_RESET_DONE in [e.kind for e in events]
    assert EventKind.GOAL_FAILED not in [e.kind for e in events]
    assert drive.state is S.OPERATION_ENABLED


def test_goal_set_before_fault_reset_is_replaced_by_disabled():
    c = DriveController(ControllerConfig(fault_reset_low_s=0.0, fault_reset_high_s=0.0))
    drive = TinyDrive(S.FAULT)
    c.set_goal(Goal.ENABLED, 0.0)
    run(c, drive, 0.0, 2)
    c.request_fault_reset(0.002)
    _, events, _ = run(c, drive, 0.002, 20)
    assert drive.state is S.SWITCH_ON_DISABLED and c.goal is Goal.DISABLED


# --- deadlines ---------------------------------------------------------------------------------


def test_goal_timeout_reported_once_then_safe_hold_and_restart():
    cfg = ControllerConfig(transition_timeout_s=1.0)
    c = DriveController(cfg)
    c.set_goal(Goal.ENABLED, 0.0)
    out = c.step(sw(S.SWITCH_ON_DISABLED), 8, 0.5)
    assert out.controlword == CW.SHUTDOWN and EventKind.GOAL_TIMEOUT not in kinds(out)
    out = c.step(sw(S.SWITCH_ON_DISABLED), 8, 1.0)
    assert kinds(out) == [EventKind.GOAL_TIMEOUT]
    for t in (1.1, 2.0, 50.0):
        out = c.step(sw(S.SWITCH_ON_DISABLED), 8, t)
        assert out.controlword == CW.DISABLE_VOLTAGE and not kinds(out)  # no retry upward
    # a late transition after the timeout is not followed upward
    out = c.step(sw(S.READY_TO_SWITCH_ON), 8, 51.0)
    assert out.controlword == CW.SHUTDOWN
    c.set_goal(Goal.ENABLED, 52.0)  # a new set_goal restarts the deadline
    out = c.step(sw(S.READY_TO_SWITCH_ON), 8, 52.0)
    assert out.controlword == CW.SWITCH_ON


def test_initial_goal_deadline_starts_at_first_step():
    c = DriveController(ControllerConfig(transition_timeout_s=1.0))
    assert EventKind.GOAL_TIMEOUT not in kinds(c.step(sw(S.READY_TO_SWITCH_ON), 8, 100.0))
    out = c.step(sw(S.READY_TO_SWITCH_ON), 8, 101.0)
    assert EventKind.GOAL_TIMEOUT in kinds(out)
    assert out.controlword == CW.DISABLE_VOLTAGE  # going down stays allowed after a timeout


def test_reached_goal_lost_is_reported_and_not_reenabled():
    c, _ = in_state(S.OPERATION_ENABLED, Goal.ENABLED)
    out = c.step(sw(S.SWITCHED_ON), 8, DT)
    assert EventKind.GOAL_FAILED in kinds(out)
    for i in range(2, 10):
        assert c.step(sw(S.SWITCHED_ON), 8, i * DT).controlword == CW.SWITCH_ON


def test_reached_goal_is_reported_again_after_set_goal():
    c, out = in_state(S.READY_TO_SWITCH_ON, Goal.READY)
    assert kinds(out).count(EventKind.GOAL_REACHED) == 1
    assert EventKind.GOAL_REACHED not in kinds(c.step(sw(S.READY_TO_SWITCH_ON), 8, DT))
    c.set_goal(Goal.READY, 2 * DT)
    assert EventKind.GOAL_REACHED in kinds(c.step(sw(S.READY_TO_SWITCH_ON), 8, 2 * DT))


@pytest.mark.parametrize("qs_code, final", [(2, S.SWITCH_ON_DISABLED), (6, S.QUICK_STOP_ACTIVE)])
def test_quick_stop_goal(qs_code, final):
    c, out = in_state(S.OPERATION_ENABLED, Goal.QUICK_STOP, ControllerConfig(quick_stop_option_code=qs_code))
    assert out.controlword == CW.QUICK_STOP
    out = c.step(sw(S.QUICK_STOP_ACTIVE), 8, DT)
    assert EventKind.GOAL_REACHED in kinds(out) and out.controlword == CW.QUICK_STOP
    out = c.step(sw(final), 8, 2 * DT)
    assert EventKind.GOAL_FAILED not in kinds(out) and out.controlword == CW.QUICK_STOP
