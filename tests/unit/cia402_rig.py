"""A CiA 402 device side and helpers for the DriveController tests (test_cia402_controller*.py):
statuswords by state, a controller set in a state with a goal, a tiny drive for closed loops."""

from __future__ import annotations

from bus_agent.cia402.controller import (
    ControllerConfig,
    ControllerOutput,
    DriveController,
    EventKind,
    Goal,
)
from bus_agent.cia402.states import (
    STATUSWORD_OF_STATE,
    TRANSITIONS,
    Controlword,
    State,
)

S = State
CW = Controlword
DT = 0.001  # a 1 ms cycle


def sw(state: State) -> int:
    """A statusword a drive reports in ``state`` (voltage enabled and remote bits set)."""
    return STATUSWORD_OF_STATE[state] | 0x0210


def kinds(out: ControllerOutput) -> list[EventKind]:
    return [e.kind for e in out.events]


def in_state(state: State, goal: Goal, config: ControllerConfig = ControllerConfig(),
             mode_display: int = 8) -> tuple[DriveController, ControllerOutput]:
    c = DriveController(config)
    c.set_goal(goal, 0.0)
    return c, c.step(sw(state), mode_display, 0.0)


class TinyDrive:
    """A minimal device side for closed-loop sequences: applies TRANSITIONS by controlword,
    fault reset on the rising edge of bit 7, transition 1 after ``boot_steps``; the drive
    can be told to ignore fault resets (``fault_sticks``)."""

    def __init__(self, state: State = S.NOT_READY_TO_SWITCH_ON, boot_steps: int = 2,
                 fault_sticks: bool = False) -> None:
        self.state = state
        self.boot_steps = boot_steps
        self.fault_sticks = fault_sticks
        self.prev_bit7 = False
        self.edges = 0
        self.mode = 0

    def apply(self, controlword: int, mode: int) -> None:
        self.mode = mode
        bit7 = bool(controlword & 0x80)
        edge = bit7 and not self.prev_bit7
        self.prev_bit7 = bit7
        if self.state is S.FAULT:
            if edge:
                self.edges += 1
                if not self.fault_sticks:
                    self.state = S.SWITCH_ON_DISABLED
            return
        if self.state is S.NOT_READY_TO_SWITCH_ON:
            self.boot_steps -= 1
            if self.boot_steps <= 0:
                self.state = S.SWITCH_ON_DISABLED
            return
        command = controlword & 0x8F
        for t in TRANSITIONS:
            if t.from_state is self.state and t.command is not None and t.number != 15 and (
                    command == t.command or command in t.alternatives):
                self.state = t.to_state
                return

    @property
    def statusword(self) -> int:
        return sw(self.state)


def run(c: DriveController, drive: TinyDrive, t0: float, steps: int) -> tuple[list[int], list, float]:
    """Closed loop for ``steps`` cycles; returns controlwords, events and the next time."""
    cws: list[int] = []
    events: list = []
    t = t0
    for _ in range(steps):
        out = c.step(drive.statusword, drive.mode, t)
        cws.append(out.controlword)
        events.extend(out.events)
        drive.apply(out.controlword, out.mode_of_operation)
        t += DT
    return cws, events, t
