"""The output stage: every cyclic target passes it on its way to the wire, whatever produced it.

Functional core (no clock, no I/O; the cycle thread owns one per axis and calls :meth:`OutputStage.step`
once per cycle with the targets about to be written). It keeps the axis limits on the wire by
construction, not by the care of each producer (planner, jog, stop, homing, a new mode):

- cyclic synchronous position (0x6061 = 8): the step of 0x607A per cycle is at most the velocity
  limit x period, and the change of that step at most the acceleration limit x period^2;
- cyclic synchronous velocity (0x6061 = 9): 0x60FF is within the velocity limit and changes per
  cycle at most by the acceleration limit x period;
- any other mode, or ``mode`` 0 (not in Operation enabled, halted, targets held at the actual
  values): the targets pass unchanged and the stage follows them, so limiting resumes from what
  was written last (enabling never jumps, and never counts).

Targets are whole counts. A path that keeps the limits exactly, rounded to counts, steps up to 1
count more and changes its step up to 2 counts more, and a velocity rounds by half a count, so
the stage accepts a target when some exact path within the limits rounds to it: an interval of
the exact step (velocity) consistent with every target since the last follow. These rounding
allowances are the wire's tolerance (:data:`ROUND_STEP`, :data:`ROUND_CHANGE`), and they cannot
accumulate: a sequence that accelerates faster than the limit empties the interval within a few
cycles.

A target no such path reaches is not written. The stage moves towards it at the limits instead
(the time-optimal braking curve of the discrete double integrator, on top of the target's own
step, so it converges to a constant target, and to a moving one slower than the velocity limit,
without losing position), counts the cycle in :attr:`OutputStage.clamps` (reported in the
drive status as ``target_clamps`` and in the dashboard's metrics) and is not :attr:`settled`
until the written target is the given one again. Cost: a few float operations per axis and cycle
(bench/bench_cycle.py, ``stage``).
"""

from __future__ import annotations

import math

__all__ = ["OutputStage", "ROUND_STEP", "ROUND_CHANGE", "MODE_CSP", "MODE_CSV"]

MODE_CSP = 8
MODE_CSV = 9
#: Counts a rounded path within the limits may exceed the step limit by (0x607A per cycle) ...
ROUND_STEP = 1
#: ... and the limit of the change of its step by.
ROUND_CHANGE = 2


class OutputStage:
    """Per-axis limits on the cyclic targets (see the module docstring). Limits in counts/s and
    counts/s^2, the nominal cycle period in seconds."""

    __slots__ = ("step_max", "change_max", "velocity_max", "velocity_change_max", "position", "velocity",
                 "clamps", "settled", "_pos", "_lo", "_hi", "_last_in", "_vlo", "_vhi")

    def __init__(self, max_velocity: float, max_acceleration: float, period_s: float) -> None:
        if not (max_velocity > 0 and max_acceleration > 0 and period_s > 0):
            raise ValueError(f"output stage limits must be > 0 (velocity {max_velocity!r}, acceleration "
                             f"{max_acceleration!r}, period {period_s!r})")
        #: counts per cycle, counts per cycle^2, counts/s, counts/s per cycle
        self.step_max = float(max_velocity) * period_s
        self.change_max = float(max_acceleration) * period_s * period_s
        self.velocity_max = float(max_velocity)
        self.velocity_change_max = float(max_acceleration) * period_s
        #: The targets written last (0x607A, 0x60FF).
        self.position = 0
        self.velocity = 0
        #: Cycles in which a target was not written as given (limited), since start.
        self.clamps = 0
        #: The last targets were written as given (nothing left to catch up).
        self.settled = True
        self._pos = 0.0         # position of the exact path (float counts)
        self._lo = 0.0          # interval of the exact path's step (counts per cycle)
        self._hi = 0.0
        self._last_in = 0       # position target given last (its own step: the target's velocity)
        self._vlo = 0.0         # interval of the exact velocity (counts/s)
        self._vhi = 0.0

    def step(self, mode: int, position: int, velocity: int) -> None:
        """This cycle's targets in; :attr:`position` and :attr:`velocity` are what to write.
        ``mode``: 8 limits the position, 9 the velocity, anything else follows both."""
        if mode == MODE_CSP:
            self._limit_position(position)
            self._follow_velocity(velocity)
        elif mode == MODE_CSV:
            self._limit_velocity(velocity)
            self._follow_position(position)
        else:
            self._follow_position(position)
            self._follow_velocity(velocity)
            self.settled = True

    # ---- position (CSP) ---------------------------------------------------------------------

    def _follow_position(self, x: int) -> None:
        # Limiting may resume from rest (enable: the targets held at a standing drive's actual
        # position, whose steps are noise) or moving with the followed steps (a halt released
        # while the drive still moves): the exact step may be anything between.
        smax = self.step_max
        u = x - self.position
        if -smax - ROUND_STEP <= u <= smax + ROUND_STEP:
            self._lo, self._hi = max(min(u - ROUND_STEP, 0), -smax), min(max(u + ROUND_STEP, 0), smax)
        else:  # a jump (not limited here): from rest
            self._lo = self._hi = 0.0
        self.position = self._last_in = x
        self._pos = float(x)

    def _limit_position(self, x: int) -> None:
        smax, dmax = self.step_max, self.change_max
        u = x - self.position
        slo = max(self._lo - dmax, -smax)   # the exact steps reachable from the last one
        shi = min(self._hi + dmax, smax)
        lo, hi = max(slo, u - ROUND_STEP), min(shi, u + ROUND_STEP)
        if lo <= hi:  # some exact path within the limits rounds to x: written as given
            self._lo, self._hi = lo, hi
            self.position = self._last_in = x
            self._pos = float(x)
            self.settled = True
            return
        # Limited: towards x at the limits. The target moves by r per cycle: moving with it
        # leaves the gap g = x - pos - r; closing it by w more this cycle leaves g - w, which
        # the braking curve must still cover decelerating by dmax per cycle:
        # w = |g|/m + (m - 1) dmax / 2 over the m cycles that takes.
        r = min(max(x - self._last_in, -smax), smax)
        g = x - self._pos - r
        a = abs(g)
        if a > 0.0:
            m = math.ceil((math.sqrt(1.0 + 8.0 * a / dmax) - 1.0) / 2.0)
            w = math.copysign(a / m + (m - 1) * dmax / 2.0, g)
        else:
            w = 0.0
        s = min(max(r + w, slo), shi)
        self._pos += s
        self._lo = self._hi = s
        self.position = round(self._pos)
        self._last_in = x
        self.clamps += 1
        self.settled = False

    # ---- velocity (CSV) ---------------------------------------------------------------------

    def _follow_velocity(self, v: int) -> None:
        vmax = self.velocity_max
        self._vlo, self._vhi = max(min(v - 0.5, vmax), -vmax), min(max(v + 0.5, -vmax), vmax)
        self.velocity = v

    def _limit_velocity(self, v: int) -> None:
        vmax, amax = self.velocity_max, self.velocity_change_max
        wlo, whi = max(self._vlo - amax, -vmax), min(self._vhi + amax, vmax)
        lo, hi = max(wlo, v - 0.5), min(whi, v + 0.5)
        if lo <= hi:
            self._vlo, self._vhi = lo, hi
            self.velocity = v
            self.settled = True
            return
        w = min(max(float(v), wlo), whi)
        self._vlo = self._vhi = w
        self.velocity = round(w)
        self.clamps += 1
        self.settled = False
