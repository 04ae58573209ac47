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
                 "clamps", "settled", "_mode", "_pos", "_lo", "_hi", "_last_in", "_pprev", "_vlo", "_vhi")

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
        self._mode = 0          # the mode of the last step: what was followed
        self._pos = 0.0         # while not settled: position of the exact path (float counts) ...
        self._last_in = 0       # ... and the position target given last (its step: the target's velocity)
        self._lo = 0.0          # interval of the exact path's step (counts per cycle)
        self._hi = 0.0
        self._pprev = 0         # while following: the position target before the last one
        self._vlo = 0.0         # interval of the exact velocity (counts/s)
        self._vhi = 0.0

    def step(self, mode: int, position: int, velocity: int) -> None:
        """This cycle's targets in; :attr:`position` and :attr:`velocity` are what to write.
        ``mode``: 8 limits the position, 9 the velocity, anything else follows both. Cycle-safe;
        the common case (a target within the limits) is a few comparisons."""
        last_mode = self._mode
        if mode == MODE_CSP:
            if last_mode != MODE_CSP:
                self._resume_position()
                self._mode = MODE_CSP
            # inline: the exact steps reachable from the last one, and those that round to u
            u = position - self.position
            smax = self.step_max
            lo = self._lo - self.change_max
            hi = self._hi + self.change_max
            if lo < -smax:
                lo = -smax
            if hi > smax:
                hi = smax
            if u - ROUND_STEP > lo:
                lo = u - ROUND_STEP
            if u + ROUND_STEP < hi:
                hi = u + ROUND_STEP
            if lo <= hi:  # some exact path within the limits rounds to it: written as given
                self._lo = lo
                self._hi = hi
                self.position = position
                self.settled = True
            else:
                self._limit_position(position)
            self.velocity = velocity
        elif mode == MODE_CSV:
            if last_mode != MODE_CSV:
                self._resume_velocity()
                self._mode = MODE_CSV
            vmax = self.velocity_max
            lo = self._vlo - self.velocity_change_max
            hi = self._vhi + self.velocity_change_max
            if lo < -vmax:
                lo = -vmax
            if hi > vmax:
                hi = vmax
            if velocity - 0.5 > lo:
                lo = velocity - 0.5
            if velocity + 0.5 < hi:
                hi = velocity + 0.5
            if lo <= hi:
                self._vlo = lo
                self._vhi = hi
                self.velocity = velocity
                self.settled = True
            else:
                self._limit_velocity(velocity)
            self._pprev = self.position
            self.position = position
        else:
            self._mode = 0
            self._pprev = self.position
            self.position = position
            self.velocity = velocity
            self.settled = True

    # ---- position (CSP) ---------------------------------------------------------------------

    def _resume_position(self) -> None:
        """Limiting 0x607A after following it. It may resume from rest (enable: the targets held
        at a standing drive's actual position, whose steps are noise) or moving with the followed
        steps (a halt released while the drive still moves): the exact step may be anything
        between. A jump (beyond the limits) was not limited: from rest."""
        smax = self.step_max
        u = self.position - self._pprev
        self._pos = float(self.position)
        self._last_in = self.position
        if -smax - ROUND_STEP <= u <= smax + ROUND_STEP:
            self._lo, self._hi = max(min(u - ROUND_STEP, 0), -smax), min(max(u + ROUND_STEP, 0), smax)
        else:
            self._lo = self._hi = 0.0

    def _limit_position(self, x: int) -> None:
        smax, dmax = self.step_max, self.change_max
        slo = max(self._lo - dmax, -smax)   # the exact steps reachable from the last one
        shi = min(self._hi + dmax, smax)
        if self.settled:  # written as given until now: the exact path is there
            self._pos = float(self.position)
            self._last_in = self.position
        # Towards x at the limits. The target moves by r per cycle: moving with it leaves the gap
        # g = x - pos - r; closing it by w more this cycle leaves g - w, which the braking curve
        # must still cover decelerating by dmax per cycle: w = |g|/m + (m - 1) dmax / 2 over the
        # m cycles that takes.
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

    def _resume_velocity(self) -> None:
        """Limiting 0x60FF after following it: from the velocity written last."""
        vmax, v = self.velocity_max, self.velocity
        self._vlo, self._vhi = max(min(v - 0.5, vmax), -vmax), min(max(v + 0.5, -vmax), vmax)

    def _limit_velocity(self, v: int) -> None:
        vmax, amax = self.velocity_max, self.velocity_change_max
        w = min(max(float(v), self._vlo - amax, -vmax), self._vhi + amax, vmax)
        self._vlo = self._vhi = w
        self.velocity = round(w)
        self.clamps += 1
        self.settled = False
