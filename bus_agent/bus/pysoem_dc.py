"""Distributed clocks of the pysoem backend: DC capability, SYNC0, the reference clock's time,
and a recovered slave's DC time (:class:`PysoemDc`, a part
:class:`bus_agent.bus.pysoem_bus.PysoemBus` owns).

SOEM's DC (``config_dc`` in PRE-OP: offsets 0x0920 and delays 0x0928 from latched receive
times; ``dc_sync``: 0x0981, start time 0x0990, cycle 0x09A0) is set up once at start-up; a
power-cycled slave forgets all of it, so recovery sets its offset, delay and SYNC0 again
before it returns to OP (ETG.1000.4 §9, ETG.1020 §3).
"""

from __future__ import annotations

import logging
import struct
import time
from typing import Any, Callable, Sequence

from bus_agent.bus.base import BusError

log = logging.getLogger("bus_agent.bus.pysoem_bus")

#: Single-datagram timeout (us) of management reads/writes; each holds the GIL at most this long.
MGMT_TIMEOUT_US = 1000
#: SOEM's dc_sync starts SYNC0 100 ms (SyncDelay) after now: wait this long before the next AL state.
SYNC0_START_S = 0.12
_REG_FEATURES = 0x0008        # ESC features: bit 2 = distributed clocks
_REG_DC_SYSTEM_TIME = 0x0910  # u64 system time = local time + 0x0920
_REG_DC_OFFSET = 0x0920       # u64 system time offset
_REG_DC_DELAY = 0x0928        # u32 propagation delay


class PysoemDc:
    """The DC state of a segment (which slaves have DC, SYNC0 per slave, their delays) and its
    operations; the bus passes the slaves (they change when start-up opens the segment again)."""

    def __init__(self, ifname: str) -> None:
        self.ifname = ifname
        #: Per slave: DC available (0x0008 bit 2), read at open().
        self.capable: list[bool] = []
        #: Per SYNC0 slave: (cycle ns, shift ns).
        self.sync0: dict[int, tuple[int, int]] = {}
        self._armed_at: dict[int, float] = {}
        #: Per SYNC0 slave: its propagation delay (0x0928) as config_dc set it, for recovery.
        self._delay: dict[int, int] = {}

    def use(self, sync0: dict[int, tuple[int, int]]) -> None:
        """At start(): the slaves whose SYNC0 start-up starts, with (cycle ns, shift ns) each."""
        self.sync0 = sync0

    def read_capable(self, slaves: Sequence[Any]) -> None:
        """At open(): each slave's ESC feature register 0x0008 bit 2 (distributed clocks)."""
        self.capable = [self._read_capable(s) for s in slaves]

    def read_delays(self, slaves: Sequence[Any]) -> None:
        """After start(): each SYNC0 slave's propagation delay (0x0928) as config_dc set it."""
        for pos in self.sync0:
            s = slaves[pos]
            try:
                self._delay[pos] = struct.unpack("<I", bytes(s._fprd(_REG_DC_DELAY, 4, 2000))[:4])[0]
            except Exception as e:
                raise BusError(f"slave {pos} ({s.name!r}): reading back its DC delay (0x0928) failed: {e}") from None

    @staticmethod
    def _read_capable(s: Any) -> bool:
        """ESC feature register 0x0008 bit 2: distributed clocks available."""
        try:
            return bool(struct.unpack("<H", bytes(s._fprd(_REG_FEATURES, 2, 2000))[:2])[0] & 0x0004)
        except Exception:
            return False

    def states(self) -> list[str]:
        """Per slave: "sync0" (SYNC0 started), "off" (DC capable, unused) or "none"."""
        return ["sync0" if p in self.sync0 else "off" if cap else "none" for p, cap in enumerate(self.capable)]

    def sync0_pending(self, position: int) -> bool:
        """True while the slave's SYNC0, started last, has not given its first pulse (armed + 100 ms)."""
        return time.monotonic() - self._armed_at.get(position, 0.0) < SYNC0_START_S

    def start_sync0(self, slaves: Sequence[Any], positions: Sequence[int]) -> None:
        """``dc_sync`` (SOEM ecx_dcsync0: 0x0981 = 0, 0x0990 start = whole cycles after now + 100 ms
        + shift, 0x09A0 cycle, 0x0981 = 3) for each slave; SYNC0 runs from the start time on."""
        for pos in positions:
            cycle_ns, shift_ns = self.sync0[pos]
            try:
                slaves[pos].dc_sync(True, cycle_ns, shift_ns)
            except Exception as e:
                raise BusError(f"slave {pos} ({slaves[pos].name!r}): SYNC0 not started: {e}") from None
            self._armed_at[pos] = time.monotonic()
            log.info("%s: slave %d: SYNC0 %d ns, shift %d ns", self.ifname, pos, cycle_ns, shift_ns)

    def restore_time(self, slaves: Sequence[Any], position: int,
                     fprd: Callable[[int, int, int], tuple[bytes | None, bool]]) -> None:
        """A recovered slave's DC time (before its SYNC0 is started again): a power cycle reset its
        system time offset (0x0920) and delay (0x0928), so its SYNC0 would run at another phase
        than the others'. The delay is written as config_dc set it at start-up (the topology is
        the same); the offset so that its system time (0x0910) reads that of another DC slave in
        step: slave, other, slave read one after the other, the other's time taken at the middle
        of the slave's two (error: about one datagram round trip; the FRMW of every frame then
        keeps it in step). ``fprd`` is one bounded FPRD (the bus's). Raises BusError when no
        other DC slave answers."""
        s = slaves[position]

        def read_u64(pos: int, reg: int) -> int:
            raw, _ = fprd(pos, reg, 8)
            if raw is None:
                raise BusError(f"slave {pos}: no answer reading DC register 0x{reg:04X}")
            return struct.unpack("<Q", raw[:8])[0]

        for other in (p for p in self.sync0 if p != position):
            try:
                own1 = read_u64(position, _REG_DC_SYSTEM_TIME)
                ref = read_u64(other, _REG_DC_SYSTEM_TIME)
                own2 = read_u64(position, _REG_DC_SYSTEM_TIME)
                offset = read_u64(position, _REG_DC_OFFSET)
            except BusError as e:
                log.debug("%s: DC time of slave %d from slave %d: %s", self.ifname, position, other, e)
                continue
            new = (offset + ref - (own1 + own2) // 2) & 0xFFFFFFFFFFFFFFFF
            try:
                s._fpwr(_REG_DC_OFFSET, struct.pack("<Q", new), MGMT_TIMEOUT_US)
                s._fpwr(_REG_DC_DELAY, struct.pack("<I", self._delay.get(position, 0)), MGMT_TIMEOUT_US)
            except Exception as e:
                raise BusError(f"slave {position} ({s.name!r}): DC offset/delay not written: {e}") from None
            log.info("%s: slave %d: DC system time set from slave %d (offset 0x%016X, delay %d ns, read "
                     "within %d ns)", self.ifname, position, other, new, self._delay.get(position, 0), own2 - own1)
            return
        raise BusError(f"slave {position} ({s.name!r}): no other DC slave answers to set its DC time from")

    def wait_sync0_start(self, exchange: Callable[[], int] | None = None) -> None:
        """Until every started SYNC0's start time (armed + 100 ms) has passed: a drive that
        needs SYNC0 refuses the next state before its first pulse. ``exchange``: process data
        kept flowing meanwhile."""
        if not self._armed_at:
            return
        until = max(self._armed_at.values()) + SYNC0_START_S
        while time.monotonic() < until:
            if exchange is not None:
                exchange()
            time.sleep(0.001)
