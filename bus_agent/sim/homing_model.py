"""Homing (mode 6) on the device side of the simulated drive: pure, stepped by the drive model.

CiA 402 homing: the method in 0x6098, speeds in 0x6099:1 (switch search) and 0x6099:2 (zero
search), acceleration 0x609A, home offset 0x607C; started by a rising edge of controlword bit 4
in Operation enabled, interrupted by bit 4 falling, by halt (bit 8) or by leaving Operation
enabled; the procedure's state is in statusword bits 13/12/10 (:data:`BITS_IN_PROGRESS` ...).

The simulated home switch is digital input 2 (0x60FD bit 2), active at and above the drive's
``home_switch_position`` (None: no switch). Methods as data (:data:`SIM_HOMING_METHODS`): 35
and 37 take the current position as home; 19 and 20 search the switch's edge at 0x6099:1
moving against the final direction, then creep onto it at 0x6099:2 in the final direction. The
drive latches the edge: the position actual value is 0x607C at the edge, and the axis
decelerates past it with 0x609A (attained, then completed at rest). Without a switch the search
gives up after :data:`SEARCH_LIMIT` increments: homing error (0x2000 moving, 0x2400 at rest).
A method the drive does not perform is a homing error at once.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Statusword bits 13/12/10 of the procedure (mask 0x3400; decoded by bus_agent.motion.homing).
BITS_IN_PROGRESS = 0x0000
BITS_INTERRUPTED = 0x0400      # interrupted or not started
BITS_ATTAINED = 0x1000         # home found, target not reached (still moving)
BITS_COMPLETED = 0x1400
BITS_ERROR_MOVING = 0x2000
BITS_ERROR_AT_REST = 0x2400
HOMING_BITS_MASK = 0x3400

#: Digital input (0x60FD) of the home switch (CiA 402: bit 2).
HOME_SWITCH_BIT = 1 << 2
#: Travel (increments) after which a switch search gives up: the simulated axis's length.
SEARCH_LIMIT = 200_000


@dataclass(frozen=True)
class SimHomingMethod:
    """How the simulated drive performs one 0x6098 method."""

    uses_switch: bool
    final_dir: int = 0  # direction of the creep onto the switch edge at 0x6099:2 (+1 / -1)

    @property
    def start_active(self) -> bool:
        """The switch state on the side the creep starts from (the switch is above its edge)."""
        return self.final_dir < 0


#: The 0x6098 methods the simulated drive performs.
SIM_HOMING_METHODS: dict[int, SimHomingMethod] = {
    19: SimHomingMethod(True, -1),   # home switch: edge found leaving the switch, moving negative
    20: SimHomingMethod(True, +1),   # home switch: edge found entering the switch, moving positive
    35: SimHomingMethod(False),      # current position (the old number of 37)
    37: SimHomingMethod(False),      # current position, no motion
}


class SimHoming:
    """One homing procedure (device side). ``phase``: idle | search | creep | stopping
    (attained, decelerating) | done | interrupted | error."""

    def __init__(self) -> None:
        self.phase = "idle"
        self.method: SimHomingMethod | None = None
        self.started_at = 0.0
        self.steps = 0

    def bits(self, velocity: float) -> int:
        """Statusword bits 13/12/10 now."""
        p = self.phase
        if p in ("idle", "interrupted"):
            return BITS_INTERRUPTED
        if p in ("search", "creep"):
            return BITS_IN_PROGRESS
        if p == "stopping":
            return BITS_ATTAINED
        if p == "done":
            return BITS_COMPLETED
        return BITS_ERROR_MOVING if velocity != 0.0 else BITS_ERROR_AT_REST

    def start(self, method: int, position: float, switch_active: bool) -> None:
        """Rising edge of bit 4 in mode 6 (a running procedure restarts)."""
        self.method = m = SIM_HOMING_METHODS.get(method)
        self.started_at = position
        self.steps = 0
        if m is None:
            self.phase = "error"
        elif not m.uses_switch:
            self.phase = "creep"  # found at the next step, where it stands
        else:
            self.phase = "creep" if switch_active == m.start_active else "search"

    def interrupt(self) -> None:
        """Bit 4 fell, halt, or the drive left Operation enabled."""
        if self.phase in ("search", "creep", "stopping"):
            self.phase = "interrupted"

    def step(self, position: float, switch_active: bool, switch_speed: float, zero_speed: float) -> tuple[float | None, bool]:
        """(the velocity the procedure wants this step or None: decelerate to rest, True when the
        home edge is at ``position`` now)."""
        m = self.method
        self.steps += 1
        if m is None or self.phase not in ("search", "creep"):
            return None, False
        if not m.uses_switch:
            self.phase = "stopping"
            return None, True
        if self.phase == "search":
            if switch_active == m.start_active:
                self.phase = "creep"
            elif abs(position - self.started_at) > SEARCH_LIMIT:
                self.phase = "error"
                return None, False
            else:
                return -m.final_dir * switch_speed, False
        if switch_active != m.start_active:
            self.phase = "stopping"
            return None, True
        if abs(position - self.started_at) > SEARCH_LIMIT:
            self.phase = "error"
            return None, False
        return m.final_dir * zero_speed, False

    def at_rest(self) -> None:
        if self.phase == "stopping":
            self.phase = "done"
