"""Distributed clocks of one simulated ESC: system time, receive-time latches, SYNC0 (ETG.1000.4 §9).

The registers SOEM uses (``ecx_configdc``, ``ecx_dcsync0``, the FRMW of every process-data frame):

| register | what |
|---|---|
| 0x0900..0x090F | receive times of ports 0..3 (u32), latched by a write to 0x0900 |
| 0x0910 | system time (u64) = local time + 0x0920; a write (FRMW of the reference's time) is the time control loop: the difference goes to 0x092C |
| 0x0918 | receive time of the processing unit (u64), latched with 0x0900 |
| 0x0920 / 0x0928 | system time offset (u64) / propagation delay (u32) |
| 0x092C | system time difference (u32: bit 31 = sign, magnitude in ns) |
| 0x0980 / 0x0981 | cyclic unit control / activation (bit 0 cyclic operation, bit 1 SYNC0, bit 2 SYNC1) |
| 0x098E | SYNC0 status |
| 0x0990 | start time of cyclic operation (u64, system time) |
| 0x09A0 / 0x09A4 | SYNC0 / SYNC1 cycle time (u32, ns) |

Local time is the host's monotonic clock since the ESC's power-on. SYNC0 fires at ``start + k *
cycle`` once ``start`` is reached; a start time already past when activated never fires (SOEM#784).
"""

from __future__ import annotations

import struct
import time

U32 = struct.Struct("<I")
U64 = struct.Struct("<Q")
MASK64 = (1 << 64) - 1

REG_RECV_TIME0 = 0x0900
REG_SYS_TIME = 0x0910
REG_RECV_TIME_PU = 0x0918
REG_SYS_OFFSET = 0x0920
REG_SYS_DELAY = 0x0928
REG_SYS_DIFF = 0x092C
REG_ACTIVATION = 0x0981
REG_SYNC0_STATUS = 0x098E
REG_START0 = 0x0990
REG_CYCLE0 = 0x09A0
DC_FIRST, DC_END = 0x0900, 0x09B0

SYNC_MODE_FREE_RUN = 0
SYNC_MODE_SM = 1
SYNC_MODE_SYNC0 = 2


class DcClock:
    """DC unit of one ESC over its register memory ``mem`` (a bytearray shared with the ESC)."""

    def __init__(self, mem: bytearray, clock_ns=time.monotonic_ns) -> None:
        self.mem = mem
        self.clock_ns = clock_ns
        self.power_on()

    def power_on(self) -> None:
        self.boot_ns = self.clock_ns()
        self.sync0: tuple[int, int] | None = None  # (start system time, cycle ns)
        self.sync0_late = False

    def local_ns(self) -> int:
        return self.clock_ns() - self.boot_ns

    def system_ns(self) -> int:
        return (self.local_ns() + U64.unpack_from(self.mem, REG_SYS_OFFSET)[0]) & MASK64

    def render(self) -> None:
        """Before a read of 0x0910: the current system time."""
        U64.pack_into(self.mem, REG_SYS_TIME, self.system_ns())

    def written(self, ado: int, end: int, before: bytes) -> None:
        """After a write to [ado, end) of the DC registers; ``before`` = 0x0900..0x09B0 as it was."""
        mem = self.mem
        if ado <= REG_RECV_TIME0 < end:
            local = self.local_ns()
            for port in range(4):  # port k's return time: a little later downstream
                U32.pack_into(mem, REG_RECV_TIME0 + 4 * port, (local + 40 * port) & 0xFFFFFFFF)
            U64.pack_into(mem, REG_RECV_TIME_PU, local)
        elif ado < REG_RECV_TIME0 + 16 and end > REG_RECV_TIME0:
            mem[REG_RECV_TIME0:REG_RECV_TIME0 + 16] = before[0:16]  # read-only latches
        if ado < REG_SYS_TIME + 8 and end > REG_SYS_TIME:
            # FRMW of the reference clock: the time control loop sees the difference (same host
            # clock here, so nothing drifts; the difference is reported, the clock not steered)
            received = U64.unpack_from(mem, REG_SYS_TIME)[0]
            diff = received - self.system_ns()
            U32.pack_into(mem, REG_SYS_DIFF, min(abs(diff), 0x7FFFFFFF) | (0x80000000 if diff < 0 else 0))
            self.render()
        if ado <= REG_ACTIVATION < end:
            act = mem[REG_ACTIVATION]
            start = U64.unpack_from(mem, REG_START0)[0]
            cycle = U32.unpack_from(mem, REG_CYCLE0)[0]
            if act & 0x03 == 0x03 and cycle > 0:
                self.sync0 = (start, cycle)
                self.sync0_late = start < self.system_ns()
            else:
                self.sync0 = None
                self.sync0_late = False

    def time_control(self, src: memoryview) -> None:
        """The write of the reference's time to 0x0910 (8 bytes) that every process-data frame
        carries (FRMW): what :meth:`written` does for it, without the general register path."""
        now = self.system_ns()
        diff = U64.unpack_from(src)[0] - now
        U32.pack_into(self.mem, REG_SYS_DIFF, min(abs(diff), 0x7FFFFFFF) | (0x80000000 if diff < 0 else 0))
        U64.pack_into(self.mem, REG_SYS_TIME, now)

    def sync0_running(self) -> bool:
        """SYNC0 pulses are being generated (activated, start time reached, not activated late)."""
        return self.sync0 is not None and not self.sync0_late and self.system_ns() >= self.sync0[0]

    def sync0_events(self) -> int:
        """SYNC0 pulses since the start time (0 while not running)."""
        s = self.sync0
        if s is None or self.sync0_late:
            return 0
        now = self.system_ns()  # once: this runs for every slave in every round
        return (now - s[0]) // s[1] + 1 if now >= s[0] else 0

    def sync_mode(self) -> int:
        """0x1C32:01 / 0x1C33:01: 0 free run, 1 SM event, 2 DC SYNC0. Without SYNC0 the
        simulated drives run on the SM2 event (the segment starts their round on it)."""
        return SYNC_MODE_SYNC0 if self.sync0 is not None else SYNC_MODE_SM

    def status(self) -> dict:
        return {"sync0": self.sync0_running(), "sync0_cycle_ns": self.sync0[1] if self.sync0 else 0,
                "sync0_start_ns": self.sync0[0] if self.sync0 else 0,
                "sync0_late": self.sync0_late, "system_time_ns": self.system_ns()}


#: dc-required sync error (0x001A), counted as drives count missed SM events against SYNC0
#: (ETG.6010 0x10F1:02, sync error counter limit): +3 for a SYNC0 period without new outputs,
#: -1 for a period with, a sync error above the limit. So 51 periods in a row without outputs
#: (51 ms at 1 kHz: before the 100 ms SM watchdog), or a master at half the SYNC0 rate for about
#: 150 periods; a late frame now and then is not one. Counted in OP only (from entering it).
SYNC_ERROR_MISSED = 3
SYNC_ERROR_LIMIT = 150


class SyncErrorCounter:
    """The sync error counter of a dc-required drive in OP (:data:`SYNC_ERROR_LIMIT`)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Entering OP: counting starts again at the next SYNC0 event."""
        self.counter = 0
        self._seen: tuple[int, int] | None = None  # (SYNC0 events, outputs) at the start of counting
        self._events = 0  # SYNC0 events at the last count
        self._lag_ref = 0

    def count(self, events: int, outputs: int) -> bool:
        """``events`` SYNC0 events and ``outputs`` process-data writes so far; True when the
        counter is above the limit."""
        # lag = SYNC0 periods - outputs since OP: in step it stays within one of its lowest
        # (an output is due in every period); each rise beyond that is a period missed
        if self._seen is None:
            if events:
                self._seen = (events, outputs)
                self._events, self._lag_ref = events, 0
            return False
        events0, outs0 = self._seen
        lag = (events - events0) - (outputs - outs0)
        periods, self._events = events - self._events, events
        if periods <= 0:
            self._lag_ref = min(self._lag_ref, lag)
            return False
        if lag > self._lag_ref + 1:
            missed = lag - self._lag_ref - 1
            self._lag_ref = lag - 1
            self.counter += SYNC_ERROR_MISSED * missed
        else:
            self.counter = max(0, self.counter - periods)
            self._lag_ref = min(self._lag_ref, lag)
        return self.counter > SYNC_ERROR_LIMIT
