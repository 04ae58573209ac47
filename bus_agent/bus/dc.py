"""Distributed clocks: keeping the master's cycle in step with the slaves' SYNC0 (pure).

With DC on, every process-data frame carries an FRMW of the reference clock's system time
(ESC register 0x0910); SOEM hands it back as ``master.dc_time``. SYNC0 fires at
``start + k * cycle`` where ``start`` is a whole multiple of the cycle plus the shift
(``slave.dc_sync``: SOEM's ``ecx_dcsync0``), so the frame's phase in the SYNC0 period is
``(dc_time - shift) % cycle``. :class:`DcSync` is SOEM's sample PI on that phase: it returns a
correction for the master's next wake-up so frames keep arriving ``target_ns`` after SYNC0
(ETG.1020 §3: the outputs must be in the slave well before its next SYNC0).

No clock reads, no I/O: the cycle feeds it ``dc_time`` once per cycle (cycle-safe, a few
integer operations) and adds the correction to its deadline.
"""

from __future__ import annotations

from dataclasses import dataclass

#: DC modes of the agent's ``[dc] mode``.
DC_MODES = ("auto", "off")


@dataclass(frozen=True)
class DcConfig:
    """``[dc]``: ``auto`` = SYNC0 on DC-capable slaves whose mode is cyclic synchronous (8/9/10);
    ``off`` = no DC. ``sync0_cycle_ns`` 0 = the agent's cycle; ``sync0_shift_ns`` = SYNC0 shift;
    ``before_safeop`` = SYNC0 started in PRE-OP (drives that need it before SAFE-OP)."""

    mode: str = "auto"
    sync0_cycle_ns: int = 0
    sync0_shift_ns: int = 0
    before_safeop: bool = False
    #: Where frames should sit in the SYNC0 period (fraction of the cycle after SYNC0).
    target_fraction: float = 0.5


def phase_ns(dc_time_ns: int, cycle_ns: int, shift_ns: int = 0) -> int:
    """Time since the last SYNC0 at ``dc_time_ns``, 0 <= phase < cycle."""
    return (dc_time_ns - shift_ns) % cycle_ns


class DcSync:
    """PI on the frame-to-SYNC0 phase; :meth:`step` returns the wake-up correction (ns).

    The correction moves one wake-up, so it is also period jitter: the gains are small (P 0.01
    as SOEM's sample programs, I 0.00002 of the summed error for a clock that drifts) and each
    correction is clamped to 1 % of the cycle. The phase error then decays by about 1 % per
    cycle (a start-up error of half a cycle is gone in about 0.5 s at 1 kHz), and measurement
    noise of +-300 us moves a period by at most 3 us."""

    def __init__(self, cycle_ns: int, shift_ns: int = 0, target_fraction: float = 0.5,
                 kp: float = 0.01, ki: float = 0.00002, max_step_ns: int | None = None) -> None:
        if cycle_ns <= 0:
            raise ValueError(f"cycle_ns must be > 0, got {cycle_ns}")
        self.cycle_ns = cycle_ns
        self.shift_ns = shift_ns
        self.target_ns = int(cycle_ns * target_fraction)
        self.kp = kp
        self.ki = ki
        self.max_step_ns = max_step_ns if max_step_ns is not None else cycle_ns // 100
        self.integral = 0.0
        self.offset_ns = 0   # last frame-to-SYNC0 phase
        self.error_ns = 0    # last phase error (wrapped to +-cycle/2)
        #: A cycle that starts later than this after its deadline does not move the PI.
        self.hold_late_ns = cycle_ns // 4
        #: The reference clock's time must advance by more than 0 and at most this much from one
        #: frame to the next; otherwise it is not the slaves' time (see :meth:`step`).
        self.max_advance_ns = 100 * cycle_ns
        self.held = 0        # cycles that held the PI
        self._last_time: int | None = None

    def step(self, dc_time_ns: int, late_ns: int = 0, hold: bool = False) -> int:
        """One cycle's correction of the next wake-up (positive: wake later).

        ``late_ns``: how late this cycle started after its deadline. The PI steers the schedule,
        so it sees the phase the frame would have had on time; a cycle more than
        :attr:`hold_late_ns` late (an overrun, a stall) holds the PI (correction 0), so a loaded
        host cannot wind it up. So does a time that did not advance, went back, or jumped more
        than :attr:`max_advance_ns`: the reference clock (the first DC slave) did not answer the
        frame's FRMW (its time stands still in the frame), came back from a power cycle with its
        time restarted at 0, or got its time back. ``hold``: the caller knows the time is not the
        slaves' (the reference clock's slave is lost, or not yet back with its time restored).
        :attr:`offset_ns` is always the frame's actual phase."""
        c = self.cycle_ns
        self.offset_ns = phase_ns(dc_time_ns, c, self.shift_ns)
        last, self._last_time = self._last_time, dc_time_ns
        if hold or (last is not None and not 0 < dc_time_ns - last <= self.max_advance_ns):
            self.held += 1
            return 0
        if late_ns > self.hold_late_ns:
            self.held += 1
            return 0
        ph = phase_ns(dc_time_ns - late_ns, c, self.shift_ns)
        err = (self.target_ns - ph + c // 2) % c - c // 2  # wrapped: early frames have err > 0
        self.error_ns = err
        self.integral += err
        lim = self.max_step_ns / self.ki if self.ki else 0.0
        self.integral = max(-lim, min(lim, self.integral))
        out = self.kp * err + self.ki * self.integral
        return int(max(-self.max_step_ns, min(self.max_step_ns, out)))
