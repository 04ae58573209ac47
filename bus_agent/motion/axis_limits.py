"""One axis's limits as a command meets them: requested velocity/acceleration/jerk within the
axis limits (clamped or rejected, ``limit_policy``), the software position limits, and a jog's
timing. A part of :class:`bus_agent.motion.axis.AxisMotion`; pure (no clock, no I/O), immutable."""

from __future__ import annotations

import math
from typing import Any, Mapping

from bus_agent.motion.config import MotionConfig
from bus_agent.motion.planner import Limits
from bus_agent.motion.records import Rejected
from bus_agent.motion.records import num as _num

__all__ = ["AxisLimits"]


class AxisLimits:
    """The limits of an axis configured by ``cfg`` (user units), in counts; ``lead_s``: the
    period a target takes to act (the inputs' delay in the braking distance)."""

    __slots__ = ("user", "cfg", "scale", "limits", "lead_s")

    def __init__(self, cfg: MotionConfig, lead_s: float) -> None:
        self.user = cfg
        self.cfg = c = cfg.in_counts()
        self.scale = cfg.counts_per_unit
        self.limits = Limits(c.max_velocity, c.max_acceleration, c.max_jerk)
        self.lead_s = lead_s

    def requested(self, args: Mapping[str, Any], notes: list[str]) -> Limits:
        """Requested velocity/accel/jerk (user units) within the axis limits: clamped (a note in
        ``notes``) or rejected."""
        out = []
        for arg, name, limit in (("velocity", "velocity", self.limits.velocity),
                                 ("accel", "acceleration", self.limits.acceleration),
                                 ("jerk", "jerk", self.limits.jerk)):
            v = _num(args, arg)
            if v is None:
                out.append(limit)
                continue
            counts = abs(v * self.scale)
            if not counts > 0:
                raise Rejected(f"{arg} {v:g} must be > 0")
            if counts > limit * (1 + 1e-9):
                max_user = limit / abs(self.scale)
                if self.cfg.limit_policy == "clamp":
                    notes.append(f"{arg} {v:g} clamped to the axis {name} limit {max_user:g} {self.user.unit}")
                    counts = limit
                else:
                    raise Rejected(f"{arg} {v:g} {self.user.unit} exceeds the axis {name} limit {max_user:g}")
            out.append(counts)
        return Limits(*out)

    def jog_velocity(self, args: Mapping[str, Any]) -> tuple[float, Limits, list[str]]:
        """A jog's signed velocity in counts/s (within the axis limit: clamped or rejected), its
        acceleration/jerk limits and the clamp notes. Raises Rejected."""
        v = _num(args, "velocity")
        if v is None:
            raise Rejected("jog needs a velocity")
        notes: list[str] = []
        lim = self.requested({k: args[k] for k in ("accel", "jerk") if k in args}, notes)
        speed = abs(v * self.scale)
        if speed > self.limits.velocity * (1 + 1e-9):
            if self.cfg.limit_policy != "clamp":
                raise Rejected(f"velocity {v:g} {self.user.unit}/s exceeds the axis velocity limit "
                               f"{self.limits.velocity / abs(self.scale):g}")
            notes.append(f"velocity {v:g} clamped to the axis velocity limit {self.limits.velocity / abs(self.scale):g}")
            speed = self.limits.velocity
        return math.copysign(speed, v * self.scale), lim, notes

    @staticmethod
    def jog_end(args: Mapping[str, Any], now_s: float, deadline_s: float, stop_s: float) -> float:
        """When a jog stops accelerating and starts to stop: after ``for_s``, default the
        command's deadline less the time to stop (``stop_s``). Raises Rejected when it could not
        stop within the deadline."""
        for_s = _num(args, "for_s")
        end_s = now_s + for_s if for_s is not None else deadline_s - stop_s - 0.05
        if end_s + stop_s > deadline_s + 1e-9:
            raise Rejected(f"jog for {for_s:g} s cannot stop within the command's timeout "
                           f"({deadline_s - now_s:.3g} s; stopping takes {stop_s:.3g} s)")
        return end_s

    def check_target(self, target: float) -> None:
        """Raise Rejected when a target (counts) is outside the software limits or 0x607A."""
        c = self.cfg
        if c.min_position is not None and target < c.min_position - 1e-9:
            raise Rejected(f"target {target / self.scale:g} {self.user.unit} is below the software limit "
                           f"min_position {c.min_position / self.scale:g}")
        if c.max_position is not None and target > c.max_position + 1e-9:
            raise Rejected(f"target {target / self.scale:g} {self.user.unit} is beyond the software limit "
                           f"max_position {c.max_position / self.scale:g}")
        if not -2**31 <= round(target) < 2**31:
            raise Rejected(f"target {target:.0f} counts is outside the 32-bit range of 0x607A")

    def limit_ahead(self, position: float, velocity: float, lim: Limits | None = None) -> str:
        """A velocity-mode jog at (up to) ``velocity`` from ``position``: the software limit the
        axis would pass if it braked a cycle later, or ''. Conservative braking distance: bringing
        the acceleration to zero (at most |v| a/j), then a jerk-limited stop from |v| at zero
        acceleration (|v| (|v|/a + a/j) / 2), plus three cycles' travel for the inputs' delay."""
        c = self.cfg
        limit = c.max_position if velocity > 0 else c.min_position
        if limit is None or velocity == 0:
            return ""
        lim = lim or self.limits
        speed = abs(velocity)
        brake = (speed * lim.acceleration / lim.jerk + speed * (speed / lim.acceleration + lim.acceleration / lim.jerk) / 2
                 + speed * 3 * self.lead_s)
        if (position + math.copysign(brake, velocity) - limit) * velocity >= 0:
            return f"{'max' if velocity > 0 else 'min'}_position {limit / self.scale:g}"
        return ""
