"""The cycle's counters and period statistics (``CycleStats``).

:class:`Statistics` counts cycles, overruns and working counter errors, keeps the last
:data:`STATS_WINDOW` periods in a ring (p50/p99/max, recomputed every :data:`STATS_EVERY` cycles)
and, for benchmarks, an optional full record of periods. Cycle thread only; the counters are
read from other threads as plain ints.
"""

from __future__ import annotations

from array import array

from bus_agent.runtime import CycleStats

#: Periods kept for p50/p99/max (one statistics window), and how often they are recomputed.
STATS_WINDOW = 1000
STATS_EVERY = 250


class Statistics:
    """Counters and the period ring of one cycle."""

    def __init__(self, cycle_us: int, record_periods: int = 0) -> None:
        self.cycle_us = cycle_us
        self.cycles = 0
        #: Drive steps made in full so far (at most cycles x drives; the fast path skips the rest).
        self.drives_stepped = 0
        self.overruns = 0
        self.wkc_errors = 0
        #: The last STATS_WINDOW periods (ns), by cycle number.
        self.periods = array("q", bytes(8 * STATS_WINDOW))
        self.period_max_ns = 0
        self.last_start_ns = 0
        #: The statistics published with each snapshot (recomputed every STATS_EVERY cycles).
        self.current = CycleStats(cycle_us=cycle_us)
        #: Optional full record of periods (ns) for benchmarks: ``record_periods`` slots.
        self.period_log: array | None = array("q", bytes(8 * record_periods)) if record_periods else None
        self.period_log_len = 0

    def begin_cycle(self, now_ns: int) -> int:
        """Count a cycle starting at ``now_ns`` and record its period (since the last start);
        returns the period (0 for the first cycle)."""
        self.cycles = cycle = self.cycles + 1
        last = self.last_start_ns
        self.last_start_ns = now_ns
        if not last:
            return 0
        p = now_ns - last
        self.periods[cycle % STATS_WINDOW] = p
        if p > self.period_max_ns:
            self.period_max_ns = p
        log = self.period_log
        if log is not None and self.period_log_len < len(log):
            log[self.period_log_len] = p
            self.period_log_len += 1
        return p

    def update(self, expected_wkc: int, dc: dict[str, float]) -> None:
        """Recompute :attr:`current` from the period ring (``dc``: the DC offset figures)."""
        ps = sorted(self.periods)
        n = len(ps)
        self.current = CycleStats(
            cycles=self.cycles, cycle_us=self.cycle_us,
            period_p50_us=ps[n // 2] / 1000, period_p99_us=ps[min(n - 1, (n * 99) // 100)] / 1000,
            period_max_us=self.period_max_ns / 1000, overruns=self.overruns, wkc_errors=self.wkc_errors,
            expected_wkc=expected_wkc, **dc)
