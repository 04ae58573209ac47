"""Homing in mode 6, master side: the standard's status table and the per-axis homing stepper.

Functional core (no clock, no I/O). CiA 402 homing: the parameters 0x6098 method, 0x6099:1/2
speeds, 0x609A acceleration and 0x607C home offset are written by SDO first (the cycle hands
:attr:`Homing.sdo_writes` to its management thread and reports back with :meth:`Homing.sdo_done`),
then modes of operation 6 is requested and confirmed by 0x6061, then controlword bit 4 rises
(start) and the procedure is followed on statusword bits 13/12/10 (:data:`HOMING_STATUS`, the
standard's table as data). Whatever the outcome, bit 4 falls and the previous mode is restored
before the command's reply; the homing deadline (``timeout_s`` of the axis's homing config, or
the command's timeout if shorter) bounds the whole run.

A homing status seen right after the start edge may be stale (a drive keeps "completed" or an
error from a previous run until it has seen the edge; "not started" until it starts): a status
counts once the run was seen under way (in progress, attained), or when it differs from the
status before the edge, or after :data:`STALE_CYCLES` cycles (methods 35 and 37 complete within
one drive cycle and may show "completed" throughout).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import Enum

from bus_agent.motion.config import HomingConfig

__all__ = ["HomingStatus", "HOMING_STATUS", "HOMING_STATUS_MASK", "decode_homing_status", "Homing",
           "HomingStep", "MODE_HOMING", "CONTROLWORD_HOMING_START", "STALE_CYCLES"]

MODE_HOMING = 6
#: Controlword bit 4 in mode 6: homing operation start (rising edge; falling edge interrupts).
CONTROLWORD_HOMING_START = 0x0010
#: Statusword bits 13 (homing error), 12 (homing attained), 10 (target reached).
HOMING_STATUS_MASK = 0x3400
#: Cycles after the start edge after which an unchanged status counts as this run's.
STALE_CYCLES = 20


class HomingStatus(str, Enum):
    """The homing procedure's state as statusword bits 13/12/10 report it."""

    IN_PROGRESS = "in progress"
    INTERRUPTED = "interrupted or not started"
    ATTAINED = "attained, target not reached"
    COMPLETED = "completed"
    ERROR_MOVING = "error, velocity not 0"
    ERROR_AT_REST = "error, velocity 0"
    RESERVED = "reserved"


#: CiA 402 (IEC 61800-7-201) homing status table: statusword & 0x3400 -> status.
HOMING_STATUS: dict[int, HomingStatus] = {
    0x0000: HomingStatus.IN_PROGRESS,
    0x0400: HomingStatus.INTERRUPTED,
    0x1000: HomingStatus.ATTAINED,
    0x1400: HomingStatus.COMPLETED,
    0x2000: HomingStatus.ERROR_MOVING,
    0x2400: HomingStatus.ERROR_AT_REST,
    0x3000: HomingStatus.RESERVED,
    0x3400: HomingStatus.RESERVED,
}
_ERRORS = (HomingStatus.ERROR_MOVING, HomingStatus.ERROR_AT_REST, HomingStatus.RESERVED)


def decode_homing_status(statusword: int) -> HomingStatus:
    """Bits 13/12/10 of ``statusword`` (0x6041) by :data:`HOMING_STATUS`."""
    return HOMING_STATUS[statusword & HOMING_STATUS_MASK]


def homing_sdo_writes(cfg: HomingConfig, method: int) -> tuple[tuple[int, int, bytes], ...]:
    """(index, subindex, data) of the homing parameters, ``cfg`` in counts (0x6099/0x609A u32,
    0x6098 i8, 0x607C i32)."""
    return (
        (0x6098, 0, struct.pack("<b", method)),
        (0x6099, 1, struct.pack("<I", min(int(round(cfg.switch_speed)), 0xFFFFFFFF))),
        (0x6099, 2, struct.pack("<I", min(int(round(cfg.zero_speed)), 0xFFFFFFFF))),
        (0x609A, 0, struct.pack("<I", min(int(round(cfg.acceleration)), 0xFFFFFFFF))),
        (0x607C, 0, struct.pack("<i", max(-2**31, min(2**31 - 1, int(round(cfg.offset)))))),
    )


@dataclass(frozen=True)
class HomingStep:
    """What the cycle does this cycle for a homing axis."""

    start_bit: bool                 # controlword bit 4
    request_mode: int | None = None  # request this modes of operation (0x6060) now
    outcome: str = ""               # done | failed | timeout | aborted: the command's reply, once
    reason: str = ""


class Homing:
    """One homing run of one axis (see the module docstring). Phases: ``params`` (SDO writes
    under way) -> ``mode`` (0x6061 = 6 awaited) -> ``running`` (bit 4 high) -> ``restore``
    (bit 4 low, previous mode awaited) -> ``finished``."""

    def __init__(self, cfg: HomingConfig, method: int, previous_mode: int, now_s: float, deadline_s: float) -> None:
        self.method = method
        self.previous_mode = previous_mode
        self.deadline_s = min(deadline_s, now_s + cfg.timeout_s)
        self.sdo_writes = homing_sdo_writes(cfg, method)
        self.phase = "params"
        self.outcome = ""
        self.reason = ""
        self.replied = False
        self.status = HomingStatus.INTERRUPTED
        self._before = HomingStatus.INTERRUPTED  # the status when bit 4 rose
        self._started = False        # in progress or attained seen since the edge
        self._cycles = 0             # cycles since the edge
        self._mode_asked = False

    @property
    def homed(self) -> bool:
        return self.outcome == "done"

    def sdo_done(self, error: str) -> None:
        """The parameter writes finished (``error``: the SDO abort of the first refused one)."""
        if self.phase != "params":
            return
        if error:
            self._end("failed", f"homing parameters refused: {error}")
        else:
            self.phase = "mode"

    def abort(self, outcome: str, reason: str) -> None:
        """End the run now (stop, quick stop, fault, disable, lost slave): bit 4 falls and the
        previous mode is restored before the reply."""
        if self.phase not in ("restore", "finished"):
            self._end(outcome, reason)

    def _end(self, outcome: str, reason: str) -> None:
        self.outcome, self.reason = outcome, reason
        self.phase = "restore"
        self._mode_asked = False

    def step(self, now_s: float, statusword: int, mode_display: int, enabled: bool) -> HomingStep:
        """One cycle with fresh inputs. Cycle-safe (a few comparisons)."""
        if self.phase == "finished":
            return HomingStep(False)
        if self.phase not in ("restore",) and now_s >= self.deadline_s:
            where = {"params": "writing the homing parameters", "mode": "waiting for 0x6061 = 6"}.get(
                self.phase, f"homing {self.status.value}")
            self._end("timeout", f"homing method {self.method} not finished by its deadline ({where})")
        if self.phase == "params":
            return HomingStep(False)
        if self.phase == "mode":
            if not self._mode_asked:
                self._mode_asked = True
                return HomingStep(False, request_mode=MODE_HOMING)
            if mode_display == MODE_HOMING and enabled:
                self.phase = "running"
                self._before = decode_homing_status(statusword)
                return HomingStep(True)
            return HomingStep(False)
        if self.phase == "running":
            return self._running(statusword)
        # restore: bit 4 low, the previous mode back, then the reply
        if not self._mode_asked:
            self._mode_asked = True
            return HomingStep(False, request_mode=self.previous_mode)
        if mode_display == self.previous_mode or now_s >= self.deadline_s + 1.0:
            self.phase = "finished"
            if mode_display != self.previous_mode:
                self.reason += f"; mode {self.previous_mode} not restored (0x6061 = {mode_display})"
            return HomingStep(False, outcome=self.outcome, reason=self.reason)
        return HomingStep(False)

    def _running(self, statusword: int) -> HomingStep:
        st = self.status = decode_homing_status(statusword)
        self._cycles += 1
        if st in (HomingStatus.IN_PROGRESS, HomingStatus.ATTAINED):
            self._started = True
        # a status is this run's once the run was seen under way, or it differs from the one
        # before the edge, or (methods 35/37, done within a drive cycle) it has stood long enough
        fresh = self._started or st is not self._before or self._cycles >= STALE_CYCLES
        if not fresh:
            return HomingStep(True)
        if st is HomingStatus.COMPLETED:
            self._end("done", f"homed with method {self.method}")
        elif st in _ERRORS:
            self._end("failed", f"homing error (statusword 0x{statusword:04X}: {st.value}), method {self.method}")
        elif st is HomingStatus.INTERRUPTED and (self._started or self._cycles >= STALE_CYCLES):
            self._end("failed", f"homing interrupted by the drive (statusword 0x{statusword:04X}: {st.value}), "
                      f"method {self.method}")
        else:
            return HomingStep(True)
        return HomingStep(False)
