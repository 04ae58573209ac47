"""Distributed clocks of the pysoem backend: DC capability, SYNC0, the reference clock's time,
and a recovered slave's DC time (the :class:`PysoemDc` part of
:class:`bus_agent.bus.pysoem_bus.PysoemBus`).

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
    """DC state and operations over the master's slaves (set up by PysoemBus)."""

    ifname: str
    _master: Any
    _slaves: list[Any]
    _dc_capable: list[bool]
    #: Per SYNC0 slave: (cycle ns, shift ns).
    _sync0: dict[int, tuple[int, int]]
    _sync0_armed_at: dict[int, float]
    #: Per SYNC0 slave: its propagation delay (0x0928) as config_dc set it, for recovery.
    _dc_delay: dict[int, int]

    _fprd: Callable[[int, int, int], tuple[bytes | None, bool]]  # one bounded FPRD (PysoemBus)
    exchange: Callable[[], int]                                   # one LRW (PysoemBus)

    def _read_dc_delays(self) -> None:
        """After start(): each SYNC0 slave's propagation delay (0x0928) as config_dc set it."""
        for pos in self._sync0:
            s = self._slaves[pos]
            try:
                self._dc_delay[pos] = struct.unpack("<I", bytes(s._fprd(_REG_DC_DELAY, 4, 2000))[:4])[0]
            except Exception as e:
                raise BusError(f"slave {pos} ({s.name!r}): reading back its DC delay (0x0928) failed: {e}") from None

    @staticmethod
    def _read_dc_capable(s: Any) -> bool:
        """ESC feature register 0x0008 bit 2: distributed clocks available."""
        try:
            return bool(struct.unpack("<H", bytes(s._fprd(_REG_FEATURES, 2, 2000))[:2])[0] & 0x0004)
        except Exception:
            return False

    def dc_capable(self, position: int) -> bool:
        """True when the slave's ESC has distributed clocks (0x0008 bit 2), read at open()."""
        return self._dc_capable[position]

    def dc_states(self) -> list[str]:
        """Per slave: "sync0" (SYNC0 started), "off" (DC capable, unused) or "none"."""
        return ["sync0" if p in self._sync0 else "off" if cap else "none" for p, cap in enumerate(self._dc_capable)]

    @property
    def dc_active(self) -> bool:
        return bool(self._sync0)

    def dc_time_ns(self) -> int:
        """System time of the reference clock from the last frame's FRMW (0x0910). Cycle-safe."""
        return self._master.dc_time

    def _start_sync0(self, positions: Sequence[int]) -> None:
        """``dc_sync`` (SOEM ecx_dcsync0: 0x0981 = 0, 0x0990 start = whole cycles after now + 100 ms
        + shift, 0x09A0 cycle, 0x0981 = 3) for each slave; SYNC0 runs from the start time on."""
        for pos in positions:
            cycle_ns, shift_ns = self._sync0[pos]
            try:
                self._slaves[pos].dc_sync(True, cycle_ns, shift_ns)
            except Exception as e:
                raise BusError(f"slave {pos} ({self._slaves[pos].name!r}): SYNC0 not started: {e}") from None
            self._sync0_armed_at[pos] = time.monotonic()
            log.info("%s: slave %d: SYNC0 %d ns, shift %d ns", self.ifname, pos, cycle_ns, shift_ns)

    def _restore_dc_time(self, position: int) -> None:
        """A recovered slave's DC time (before its SYNC0 is started again): a power cycle reset its
        system time offset (0x0920) and delay (0x0928), so its SYNC0 would run at another phase
        than the others'. The delay is written as config_dc set it at start-up (the topology is
        the same); the offset so that its system time (0x0910) reads that of another DC slave in
        step: slave, other, slave read one after the other, the other's time taken at the middle
        of the slave's two (error: about one datagram round trip; the FRMW of every frame then
        keeps it in step). Raises BusError when no other DC slave answers."""
        s = self._slaves[position]

        def read_u64(pos: int, reg: int) -> int:
            raw, _ = self._fprd(pos, reg, 8)
            if raw is None:
                raise BusError(f"slave {pos}: no answer reading DC register 0x{reg:04X}")
            return struct.unpack("<Q", raw[:8])[0]

        for other in (p for p in self._sync0 if p != position):
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
                s._fpwr(_REG_DC_DELAY, struct.pack("<I", self._dc_delay.get(position, 0)), MGMT_TIMEOUT_US)
            except Exception as e:
                raise BusError(f"slave {position} ({s.name!r}): DC offset/delay not written: {e}") from None
            log.info("%s: slave %d: DC system time set from slave %d (offset 0x%016X, delay %d ns, read "
                     "within %d ns)", self.ifname, position, other, new, self._dc_delay.get(position, 0), own2 - own1)
            return
        raise BusError(f"slave {position} ({s.name!r}): no other DC slave answers to set its DC time from")

    def _wait_sync0_start(self, exchange: bool = False) -> None:
        """Until every started SYNC0's start time (armed + 100 ms) has passed: a drive that
        needs SYNC0 refuses the next state before its first pulse."""
        if not self._sync0_armed_at:
            return
        until = max(self._sync0_armed_at.values()) + SYNC0_START_S
        while time.monotonic() < until:
            if exchange:
                self.exchange()
            time.sleep(0.001)
