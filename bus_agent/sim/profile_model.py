"""Profile Position (mode 1) on the device side of the simulated drive, and the velocity ramp
every profile mode shares: pure, stepped by :class:`bus_agent.sim.drive_model.DriveModel`.

CiA 402 Profile Position: a rising edge of controlword bit 4 (new set-point) takes 0x607A as the
target (bit 6: relative to the running target, else to the position) and sets the set-point
acknowledge (statusword bit 12), which falls with bit 4. The drive then ramps with 0x6083/0x6084
at up to 0x6081 (and 0x607F) so that it can still stop at the target with 0x6084.
"""

from __future__ import annotations

import math
from typing import Callable

__all__ = ["ramp", "SimProfilePosition"]

CONTROLWORD_NEW_SETPOINT = 0x10
CONTROLWORD_RELATIVE = 0x40


def ramp(v: float, target_v: float, accel: float, decel: float, dt: float) -> float:
    """The velocity after ``dt`` on the way from ``v`` to ``target_v``: ``decel`` when slowing
    down or reversing, else ``accel``; never past the target."""
    rate = decel if abs(target_v) < abs(v) or target_v * v < 0 else accel
    dv = rate * dt
    if abs(target_v - v) <= dv:
        return target_v
    return v + math.copysign(dv, target_v - v)


class SimProfilePosition:
    """The PP set-point handshake and the motion to the taken target (see the module docstring).

    ``target`` is None without a set-point (the drive ramps to rest); ``ack`` is the set-point
    acknowledge (statusword bit 12)."""

    __slots__ = ("target", "ack", "_wait", "_prev_new_setpoint")

    def __init__(self) -> None:
        self.target: float | None = None
        self.ack = False
        self._wait: int | None = None
        self._prev_new_setpoint = False

    def step(self, cw: int, demand: int, position: float, velocity: float, *, profile_velocity: float,
             vmax: float, accel: float, decel: float, dt: float, within_limits: Callable[[float], float],
             ack_delay_steps: int, ack_stuck: bool) -> tuple[float, bool]:
        """One step in Operation enabled with ``cw`` and 0x607A = ``demand``: the new velocity and
        whether the target is reached (statusword bit 10). ``ack_delay_steps``: steps before a
        set-point is taken; ``ack_stuck``: an acknowledge that never falls (a drive bug)."""
        new_setpoint = bool(cw & CONTROLWORD_NEW_SETPOINT)
        if new_setpoint and not self._prev_new_setpoint:
            self._wait = ack_delay_steps
        self._prev_new_setpoint = new_setpoint
        if new_setpoint and self._wait is not None:
            if self._wait <= 0:
                target = float(demand)
                if cw & CONTROLWORD_RELATIVE:
                    target += self.target if self.target is not None else position
                self.target = within_limits(target)
                self.ack = True
                self._wait = None
            else:
                self._wait -= 1
        elif not new_setpoint and not ack_stuck:
            self._wait = None
            self.ack = False
        if self.target is None:
            return ramp(velocity, 0.0, accel, decel, dt), False
        dist = self.target - position
        # the fastest speed that can still stop at the target with 0x6084
        want = math.copysign(min(profile_velocity, vmax, math.sqrt(2.0 * decel * abs(dist))), dist)
        v = ramp(velocity, want, accel, decel, dt)
        if dt > 0 and abs(dist) <= abs(v) * dt:
            v = dist / dt  # land on the target this step
        return v, abs(dist - v * dt) < 0.5
