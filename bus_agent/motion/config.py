"""Per-axis motion configuration: limits, software position limits, windows, homing, scaling.

Values are in the axis's user unit (``unit``, ``counts_per_unit`` increments of 0x6064 per
unit; the default unit is the drive's increment, "counts"). The agent converts to counts once,
at start-up (:meth:`MotionConfig.in_counts`). Parsed from TOML by ``bus_agent.config``
(``[defaults.motion]``, ``[drives.motion]``, ``[drives.motion.homing]``); validated here. Pure.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

#: What a move does with a velocity, acceleration or jerk above the axis limit.
LIMIT_POLICIES = ("reject", "clamp")
#: Homing methods (0x6098) the agent accepts: current position (37, 35), a home switch (19..22,
#: the simulators' 0x60FD bit 2), index pulses and switches with index (1..14, 33, 34).
HOMING_METHODS = frozenset(range(1, 15)) | frozenset(range(17, 31)) | {33, 34, 35, 37}


class MotionConfigError(ValueError):
    """An invalid motion configuration; the message names the key."""


@dataclass(frozen=True)
class HomingConfig:
    """Homing in mode 6: 0x6098 method, 0x6099:1/2 speeds, 0x609A acceleration, 0x607C offset."""

    method: int = 37                  # 37: the current position is home (no motion)
    switch_speed: float = 10_000.0    # 0x6099:1, unit/s
    zero_speed: float = 1_000.0       # 0x6099:2, unit/s
    acceleration: float = 100_000.0   # 0x609A, unit/s^2
    offset: float = 0.0               # 0x607C, unit
    timeout_s: float = 30.0           # homing not finished by then: failed (timeout)


@dataclass(frozen=True)
class MotionConfig:
    """The motion limits and rules of one axis (user units; see the module docstring)."""

    max_velocity: float = 100_000.0          # unit/s
    max_acceleration: float = 1_000_000.0    # unit/s^2
    max_jerk: float = 20_000_000.0           # unit/s^3
    min_position: float | None = None        # software limits, also written to 0x607D:1/2
    max_position: float | None = None
    position_window: float = 10.0            # done: |actual - target| within this ...
    velocity_window: float = 1_000.0         # ... and |velocity| within this (unit/s)
    settle_s: float = 1.0                    # after the profile ends, time to get into the windows
    limit_policy: str = "reject"             # LIMIT_POLICIES
    require_homing: bool = False             # absolute moves only after a successful home
    counts_per_unit: float = 1.0
    unit: str = "counts"
    homing: HomingConfig = HomingConfig()
    write_limits: bool = True                # write min/max_position to 0x607D:1/2 at start-up

    def __post_init__(self) -> None:
        validate(self)

    def limit_sdos(self) -> tuple[tuple[int, int, int], ...]:
        """(0x607D, subindex, value in counts) to write at start-up: the software position limits
        (CiA 402: 1 min, 2 max, i32) when any is configured and ``write_limits``; an end without
        a limit gets the i32 extreme (no limit), values beyond the i32 range are clamped to it."""
        c = self.in_counts()
        if not self.write_limits or (c.min_position is None and c.max_position is None):
            return ()

        def i32(v: float | None, default: int) -> int:
            return default if v is None else max(-2**31, min(2**31 - 1, int(round(v))))

        return ((0x607D, 1, i32(c.min_position, -2**31)), (0x607D, 2, i32(c.max_position, 2**31 - 1)))

    def to_counts(self, value: float) -> float:
        return value * self.counts_per_unit

    def to_units(self, counts: float) -> float:
        return counts / self.counts_per_unit

    def in_counts(self) -> "MotionConfig":
        """The same configuration with every length in counts (``counts_per_unit`` 1)."""
        k = self.counts_per_unit
        if k == 1.0:
            return self

        def c(v: float | None) -> float | None:
            return None if v is None else v * abs(k)

        lo, hi = (self.min_position, self.max_position)
        if k < 0:  # a negative scale swaps the ends
            lo, hi = hi, lo
        h = self.homing
        return dataclasses.replace(
            self, max_velocity=self.max_velocity * abs(k), max_acceleration=self.max_acceleration * abs(k),
            max_jerk=self.max_jerk * abs(k), min_position=None if lo is None else lo * k,
            max_position=None if hi is None else hi * k, position_window=self.position_window * abs(k),
            velocity_window=self.velocity_window * abs(k), counts_per_unit=1.0, unit="counts",
            homing=dataclasses.replace(h, switch_speed=c(h.switch_speed) or 0.0, zero_speed=c(h.zero_speed) or 0.0,
                                       acceleration=c(h.acceleration) or 0.0, offset=h.offset * k))


def _positive(value: float, key: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (value > 0 and math.isfinite(value)):
        raise MotionConfigError(f"{key}: {value!r} must be a finite number > 0")


def validate(c: MotionConfig, key: str = "motion") -> None:
    """Raise MotionConfigError naming the first bad key."""
    for name in ("max_velocity", "max_acceleration", "max_jerk", "position_window", "velocity_window",
                 "settle_s", "counts_per_unit"):
        v = getattr(c, name)
        if name == "counts_per_unit" and isinstance(v, (int, float)) and v < 0 and math.isfinite(v):
            continue  # a negative scale flips the direction
        _positive(v, f"{key}.{name}")
    for name in ("min_position", "max_position"):
        v = getattr(c, name)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)):
            raise MotionConfigError(f"{key}.{name}: {v!r} must be a finite number")
    if c.min_position is not None and c.max_position is not None and not c.min_position < c.max_position:
        raise MotionConfigError(f"{key}.min_position: {c.min_position} must be below max_position {c.max_position}")
    if not isinstance(c.write_limits, bool):
        raise MotionConfigError(f"{key}.write_limits: {c.write_limits!r} must be true or false")
    if c.limit_policy not in LIMIT_POLICIES:
        raise MotionConfigError(f"{key}.limit_policy: {c.limit_policy!r} is not one of {', '.join(LIMIT_POLICIES)}")
    if not isinstance(c.unit, str) or not 1 <= len(c.unit) <= 16:
        raise MotionConfigError(f"{key}.unit: {c.unit!r} must be a name of 1..16 characters")
    h = c.homing
    if h.method not in HOMING_METHODS:
        raise MotionConfigError(f"{key}.homing.method: {h.method!r} is not a supported 0x6098 method "
                                f"(1..14, 17..30, 33, 34, 35, 37)")
    for name in ("switch_speed", "zero_speed", "acceleration", "timeout_s"):
        _positive(getattr(h, name), f"{key}.homing.{name}")
    if isinstance(h.offset, bool) or not isinstance(h.offset, (int, float)) or not math.isfinite(h.offset):
        raise MotionConfigError(f"{key}.homing.offset: {h.offset!r} must be a finite number")
