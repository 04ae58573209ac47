"""The cycle's timing: the schedule of deadlines, the wait before each, DC steering, process settings.

:class:`Timing` (cycle thread only) keeps the drift-free deadlines ``t0 + k * period`` (shifted by
the DC steering), sleeps until the spin before each deadline (a ``select`` on the wake eventfd and
the trigger socket of the :class:`~bus_agent.cycle.triggers.TriggerInbox`, so a remote group
trigger ends it at once), then spins to the deadline; the adaptive spin follows the sleep's
overshoot. :class:`DcSteering` keeps the cycle in step with SYNC0. It also sets the process-wide
settings while the loop runs (GC, switch interval). See docs/agent-cycle.md, "Timing".
"""

from __future__ import annotations

import gc
import sys
import time
from array import array
from typing import AbstractSet, Callable

from bus_agent import hops
from bus_agent.bus.dc import DcSync
from bus_agent.cycle.drive import Drive
from bus_agent.cycle.stats import STATS_WINDOW, Statistics
from bus_agent.cycle.triggers import TriggerInbox

#: Spin (busy-wait) at most this long before a deadline; sleep before that. time.sleep overshoots
#: by ~50-100 us on Linux with the default 50 us timer slack, so the spin absorbs it.
SPIN_NS = 150_000
#: The adaptive spin (``Cycle.spin_ns = None``): the SPIN_QUANTILE of the sleep's overshoot over
#: the last STATS_WINDOW sleeps plus SPIN_MARGIN_NS, at least SPIN_MIN_NS and at most SPIN_NS,
#: recomputed every STATS_EVERY cycles, and raised at once past a sleep that overshot it. The
#: quantile is that of the jitter figure kept (p99.9): about one cycle in a thousand may start
#: late, as with a fixed spin that the overshoot's tail exceeds. A quiet host wakes the thread
#: (1 ns timer slack) within tens of us, so part of the 150 us of spinning (15 % of a core at
#: 1 kHz) is saved; a loaded one keeps it at SPIN_NS. docs/agent-cycle.md, Timing.
SPIN_MIN_NS = 10_000
SPIN_MARGIN_NS = 10_000
SPIN_QUANTILE = 0.999


class DcSteering:
    """The PI that keeps the cycle in step with SYNC0 (:class:`~bus_agent.bus.dc.DcSync`) and
    its figures. Inactive (``sync`` None) without distributed clocks."""

    def __init__(self) -> None:
        self.sync: DcSync | None = None
        #: The system time in the last frame (the bus's ``dc_time_ns``).
        self.time_ns: Callable[[], int] = lambda: 0
        #: The drive whose slave is the reference clock, if any.
        self.ref: Drive | None = None
        #: The shift of the schedule (ns), the PI's output so far.
        self.adjust_ns = 0
        #: How late the running cycle started after its deadline (ns; 0 for tick()).
        self.late_ns = 0
        self.offsets = array("q", bytes(8 * STATS_WINDOW))
        #: Optional record of frame-to-SYNC0 offsets (ns), beside ``Statistics.period_log``.
        self.log: array | None = None
        #: The DC state of each slave (the bus's ``dc_states``).
        self.states: tuple[str, ...] = ()

    def step(self, cycle: int, period_log_len: int) -> None:
        """After an exchange that came back: one PI step on the frame's phase (bus_agent.bus.dc);
        while the reference clock's drive is lost the time in the frames is not the slaves'."""
        dcs = self.sync
        assert dcs is not None
        ref = self.ref
        self.adjust_ns += dcs.step(self.time_ns(), self.late_ns, ref is not None and ref.lost)
        self.offsets[cycle % STATS_WINDOW] = dcs.offset_ns
        log = self.log
        if log is not None and 0 < period_log_len <= len(log):
            log[period_log_len - 1] = dcs.offset_ns

    def figures(self, cycles: int) -> dict[str, float]:
        """The offset figures of CycleStats (none without SYNC0)."""
        if self.sync is None:
            return {}
        offs = sorted(self.offsets[:min(cycles, STATS_WINDOW)] or [0])
        n = len(offs)
        return {"dc_offset_p50_us": offs[n // 2] / 1000, "dc_offset_p99_us": offs[min(n - 1, (n * 99) // 100)] / 1000}


class Timing:
    """The schedule, the wait before each deadline and the adaptive spin; the process settings."""

    def __init__(self, period_ns: int, clock_ns: Callable[[], int], sleep: Callable[[float], None],
                 triggers: TriggerInbox, dc: DcSteering, stats: Statistics, armed: AbstractSet[int], *,
                 spin_ns: int | None, manage_gc: bool, switch_interval_s: float | None) -> None:
        self.period_ns = period_ns
        self.clock_ns = clock_ns
        self.sleep = sleep
        self.manage_gc = manage_gc
        self.switch_interval_s = switch_interval_s
        #: Spin before each deadline (ns): None adapts it to the sleep's overshoot (SPIN_MIN_NS ..
        #: SPIN_NS), a number fixes it (0: none). See ``Cycle.spin_ns``.
        self.spin_ns = spin_ns
        #: False: the spin is made only while a period's jitter can matter (``armed`` not empty,
        #: SYNC0 running); with every drive off the loop only sleeps (``[cycle] spin_at_rest``).
        self.spin_at_rest = False
        #: The adaptive spin now (SPIN_NS until the first sleeps are measured).
        self.spin_auto_ns = SPIN_NS
        self._triggers = triggers
        self._dc = dc
        self._stats = stats
        self._armed = armed  # the controllers' armed drives (a set they keep)
        self._oversleep = array("q", bytes(8 * STATS_WINDOW))
        self._sleeps = 0
        self._t0 = 0
        self._k = 0
        self._process_saved: tuple[float, bool] | None = None

    # ---- process settings ------------------------------------------------------------------------

    def prepare_process(self) -> None:
        """Process-wide settings while the loop runs (restored by :meth:`restore_process`); once."""
        if self._process_saved is not None:
            return
        self._process_saved = (sys.getswitchinterval(), gc.isenabled())
        if self.switch_interval_s:
            # A thread waiting for the GIL asks for it after this long (default 5 ms): the cycle
            # thread waits at most about this long when another thread holds the GIL.
            sys.setswitchinterval(self.switch_interval_s)
        if self.manage_gc:
            # No cyclic-GC pauses in the loop: move what exists to the permanent generation and
            # disable collection while running (reference counting still frees everything acyclic).
            gc.collect()
            gc.freeze()
            gc.disable()

    def restore_process(self) -> None:
        saved = self._process_saved
        if saved is None:
            return
        if self.manage_gc:
            gc.unfreeze()
            if saved[1]:
                gc.enable()
        if self.switch_interval_s:
            sys.setswitchinterval(saved[0])
        self._process_saved = None

    @property
    def real_sleep(self) -> bool:
        """The sleep is ``time.sleep`` (not injected): it may wait on the wake eventfd instead."""
        return self.sleep is time.sleep

    # ---- the schedule ------------------------------------------------------------------------------

    def begin(self) -> None:
        """The schedule starts now (``t0``)."""
        self._t0 = self.clock_ns()
        self._k = 0

    def next_start(self, on_wake: Callable[[], None]) -> int:
        """Wait for the next deadline ``t0 + k * period`` (shifted by the DC steering); returns
        when the cycle starts. ``on_wake`` is called when a remote trigger ends the sleep early.
        A start more than one period late is an overrun: the schedule skips the missed slots (no
        catch-up burst), on the grid shifted by DC."""
        period = self.period_ns
        dc = self._dc
        deadline = self._t0 + self._k * period + dc.adjust_ns
        now = self.clock_ns()
        while now < deadline:
            if not self.wait_until(deadline):
                now = self.clock_ns()
                break
            # woken before the deadline by a remote group trigger: apply it now
            hops.stamp("cy.wake")
            on_wake()
            now = self.clock_ns()
        dc.late_ns = now - deadline
        if now - deadline > period:
            self._stats.overruns += 1
            self._k = (now - self._t0 - dc.adjust_ns) // period
        self._k += 1
        return now

    def wait_until(self, deadline_ns: int) -> bool:
        """Sleep until the spin before ``deadline_ns``, then spin to it. True (at once, without
        spinning) when a remote trigger woke the sleep; a trigger during the spin waits for the
        cycle (at most the spin away)."""
        if self._armed or self.spin_at_rest or self._dc.sync is not None:
            spin = self.spin_ns if self.spin_ns is not None else self.spin_auto_ns
        else:
            spin = 0  # every drive off and no SYNC0: nothing the period's jitter could move
        clock = self.clock_ns
        wake = deadline_ns - spin
        remaining = wake - clock()
        if remaining > 0:
            if self._doze(remaining / 1e9):
                return True
            self._sleeps += 1
            over = self._oversleep[self._sleeps % STATS_WINDOW] = clock() - wake
            if over > self.spin_auto_ns:  # late past the spin: more spin from the next cycle on
                self.spin_auto_ns = min(SPIN_NS, over + SPIN_MARGIN_NS)
        while clock() < deadline_ns:
            pass
        return False

    def _doze(self, seconds: float) -> bool:
        """Sleep ``seconds``, or until a remote trigger wakes the cycle (True)."""
        triggers = self._triggers
        if not triggers.waits:
            self.sleep(seconds)
            # an injected sleep (tests, tools): a trigger queued meanwhile counts as a wake
            return triggers.express and bool(triggers.queue)
        return triggers.wait(seconds)

    def adapt_spin(self) -> None:
        """The adaptive spin (see SPIN_MIN_NS) from the overshoots of the last sleeps."""
        over = sorted(self._oversleep)
        q = over[min(len(over) - 1, int(len(over) * SPIN_QUANTILE))]
        self.spin_auto_ns = min(SPIN_NS, max(SPIN_MIN_NS, q + SPIN_MARGIN_NS))
