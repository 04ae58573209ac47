"""Trajectory planning: jerk-limited profiles from ruckig, computed once per move, sampled per cycle.

Pure: no clock, no I/O. A :class:`Plan` is computed when a command starts (``plan_*``, tens of
microseconds at most) and sampled every cycle with :meth:`Plan.sample` (well under 1 us per axis,
see docs/motion.md). Positions are increments (counts) of the drive's 0x607A/0x6064, velocities
counts/s, accelerations counts/s^2, jerk counts/s^3.

ruckig is badly conditioned with raw counts (a profile from 5e4 counts/s down to rest at 1e7
counts/s^3 fails in its step 1), so every plan is computed in normalised units: positions
relative to the start, divided by the velocity limit, so the limit is 1 and durations are
unchanged. :class:`Plan` converts back when sampled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from ruckig import ControlInterface, InputParameter, Result, Ruckig, RuckigError, Trajectory

__all__ = ["Limits", "Plan", "PlanError", "hold", "plan_position", "plan_velocity", "plan_stop", "plan_group"]


class PlanError(ValueError):
    """No trajectory for these inputs (the message says why); nothing was started."""


@dataclass(frozen=True)
class Limits:
    """Velocity, acceleration and jerk limits of one move, all > 0 (counts/s, /s^2, /s^3)."""

    velocity: float
    acceleration: float
    jerk: float


@dataclass(frozen=True)
class Kinematic:
    """Position, velocity and acceleration at one instant (counts, counts/s, counts/s^2)."""

    position: float
    velocity: float = 0.0
    acceleration: float = 0.0


class Plan:
    """A computed trajectory of one axis: ``sample(t)`` for t in seconds from its start.

    Before 0 it returns the start, after :attr:`duration` the end (position and velocity of the
    final state; a velocity plan keeps moving at its target velocity)."""

    __slots__ = ("_traj", "_origin", "_scale", "duration", "start", "final_velocity", "target")

    def __init__(self, traj: Trajectory | None, origin: float, scale: float, start: Kinematic,
                 target: float, final_velocity: float = 0.0) -> None:
        self._traj = traj
        self._origin = origin
        self._scale = scale
        self.start = start
        self.target = target
        self.final_velocity = final_velocity
        self.duration = float(traj.duration) if traj is not None else 0.0

    def sample(self, t: float) -> tuple[float, float, float]:
        """(position, velocity, acceleration) at ``t`` seconds after the start. Cycle-safe."""
        traj = self._traj
        if traj is None or t <= 0.0:
            if traj is None and t > 0.0:
                return self.start.position + self.final_velocity * t, self.final_velocity, 0.0
            return self.start.position, self.start.velocity, self.start.acceleration
        if t >= self.duration:
            # Exactly the final state: a position plan ends at rest on its target, a velocity
            # plan at its velocity (ruckig's own end state differs by rounding).
            end = self.duration
            if math.isnan(self.target) or self.final_velocity:
                p, _, _ = traj.at_time(end)
                pos = self._origin + p[0] * self._scale
            else:
                pos = self.target
            return pos + self.final_velocity * (t - end), self.final_velocity, 0.0
        p, v, a = traj.at_time(t)
        s = self._scale
        return self._origin + p[0] * s, v[0] * s, a[0] * s


def hold(position: float) -> Plan:
    """A plan that stays at ``position`` (no motion)."""
    return Plan(None, position, 1.0, Kinematic(position), position)


def _input(start: Kinematic, limits: Limits, scale: float) -> InputParameter:
    for name in ("velocity", "acceleration", "jerk"):
        value = getattr(limits, name)
        if not (value > 0.0 and math.isfinite(value)):
            raise PlanError(f"{name} limit {value!r} must be a finite number > 0")
    inp = InputParameter(1)
    inp.current_position = [0.0]
    inp.current_velocity = [start.velocity / scale]
    inp.current_acceleration = [start.acceleration / scale]
    inp.max_velocity = [limits.velocity / scale]
    inp.max_acceleration = [limits.acceleration / scale]
    inp.max_jerk = [limits.jerk / scale]
    return inp


def _calculate(inp: InputParameter, what: str) -> Trajectory:
    traj = Trajectory(1)
    try:
        result = Ruckig(1).calculate(inp, traj)
    except RuckigError as e:
        raise PlanError(f"{what}: no trajectory ({str(e).strip().splitlines()[0]})") from None
    if result not in (Result.Working, Result.Finished):
        raise PlanError(f"{what}: no trajectory (ruckig {result.name})")
    return traj


def plan_position(start: Kinematic, target: float, limits: Limits, min_duration_s: float = 0.0) -> Plan:
    """A jerk-limited move from ``start`` to rest at ``target`` within ``limits``, lasting at
    least ``min_duration_s`` (a synchronised group's common duration). Raises PlanError."""
    if not math.isfinite(target):
        raise PlanError(f"target {target!r} is not a finite number")
    scale = limits.velocity
    inp = _input(start, limits, scale)
    inp.target_position = [(target - start.position) / scale]
    if min_duration_s > 0.0:
        inp.minimum_duration = min_duration_s
    return Plan(_calculate(inp, f"move to {target:.6g}"), start.position, scale, start, target)


def plan_velocity(start: Kinematic, velocity: float, limits: Limits) -> Plan:
    """Reach ``velocity`` (counts/s) from ``start`` within ``limits``, then keep it (jog)."""
    if not math.isfinite(velocity):
        raise PlanError(f"velocity {velocity!r} is not a finite number")
    scale = limits.velocity
    inp = _input(start, limits, scale)
    inp.control_interface = ControlInterface.Velocity
    inp.target_velocity = [velocity / scale]
    return Plan(_calculate(inp, f"velocity {velocity:.6g}"), start.position, scale, start, math.nan,
                final_velocity=velocity)


def plan_stop(start: Kinematic, limits: Limits) -> Plan:
    """Decelerate from ``start`` to rest within ``limits`` (halt, stop, timeout). Never raises:
    if ruckig finds nothing, the plan holds the start position (the drive's own limits apply)."""
    if abs(start.velocity) < 1e-9 and abs(start.acceleration) < 1e-9:
        return hold(start.position)
    try:
        p = plan_velocity(start, 0.0, limits)
    except PlanError:
        return hold(start.position)
    end, _, _ = p.sample(p.duration)
    p.target = end
    p.final_velocity = 0.0
    return p


def plan_group(starts: Sequence[Kinematic], targets: Sequence[float], limits: Sequence[Limits],
               min_duration_s: float = 0.0) -> list[Plan]:
    """Moves that start together and arrive together: each axis's own fastest duration first,
    then every axis planned again to the longest of them (ruckig's time synchronisation of
    independent axes, one degree of freedom each, so each keeps its own limits)."""
    fastest = [plan_position(s, t, lim) for s, t, lim in zip(starts, targets, limits)]
    common = max([min_duration_s] + [p.duration for p in fastest])
    return [p if p.duration >= common else plan_position(s, t, lim, common)
            for p, s, t, lim in zip(fastest, starts, targets, limits)]
