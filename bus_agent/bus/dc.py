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

    Gains as SOEM's samples (P 0.1, I 0.0005 of the error per cycle, clamped), so the master
    follows the DC reference without jumps."""

    def __init__(self, cycle_ns: int, shift_ns: int = 0, target_fraction: float = 0.5,
                 kp: float = 0.1, ki: float = 0.0005, max_step_ns: int | None = None) -> None:
        if cycle_ns <= 0:
            raise ValueError(f"cycle_ns must be > 0, got {cycle_ns}")
        self.cycle_ns = cycle_ns
        self.shift_ns = shift_ns
        self.target_ns = int(cycle_ns * target_fraction)
        self.kp = kp
        self.ki = ki
        self.max_step_ns = max_step_ns if max_step_ns is not None else cycle_ns // 10
        self.integral = 0.0
        self.offset_ns = 0   # last frame-to-SYNC0 phase
        self.error_ns = 0    # last phase error (wrapped to +-cycle/2)

    def step(self, dc_time_ns: int) -> int:
        """One cycle's correction of the next wake-up (positive: wake later)."""
        c = self.cycle_ns
        ph = phase_ns(dc_time_ns, c, self.shift_ns)
        self.offset_ns = ph
        err = (self.target_ns - ph + c // 2) % c - c // 2  # wrapped: early frames have err > 0
        self.error_ns = err
        self.integral += err
        lim = self.max_step_ns / self.ki if self.ki else 0.0
        self.integral = max(-lim, min(lim, self.integral))
        out = self.kp * err + self.ki * self.integral
        return int(max(-self.max_step_ns, min(self.max_step_ns, out)))
