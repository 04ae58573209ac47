"""A chain of simulated ESCs answering EtherCAT datagrams (ETG.1000.4 §5.4).

:meth:`Segment.process` handles one frame in place (data and working counters), so the frame
loop can send the very buffer back. Logical datagrams use plans precomputed from the FMMUs
(memoryview pairs to copy), rebuilt only when FMMUs, SMs, station addresses, AL states or
fault injections change.
"""

from __future__ import annotations

import logging
import struct
import time
from enum import IntEnum
from typing import Sequence

from bus_agent.bus.base import ALState

from bus_agent.sim.drive_model import DriveProfile
from bus_agent.sim.ecat.esc import Esc
from bus_agent.sim.ecat.profiles import EcatProfile, parse_profiles

log = logging.getLogger(__name__)

DATAGRAM = struct.Struct("<BBHHHH")  # cmd, index, ADP, ADO, length/flags, irq
U16 = struct.Struct("<H")
ETH_HEADER = 14
ECAT_HEADER = 2
DG_HEADER = DATAGRAM.size
MORE_FOLLOWS = 0x8000


class Cmd(IntEnum):
    """Datagram commands (ETG.1000.4 Table 12)."""

    NOP = 0
    APRD = 1
    APWR = 2
    APRW = 3
    FPRD = 4
    FPWR = 5
    FPRW = 6
    BRD = 7
    BWR = 8
    BRW = 9
    LRD = 10
    LWR = 11
    LRW = 12
    ARMW = 13
    FRMW = 14


_READS = {Cmd.APRD, Cmd.FPRD, Cmd.BRD}
_WRITES = {Cmd.APWR, Cmd.FPWR, Cmd.BWR}
_RWS = {Cmd.APRW, Cmd.FPRW, Cmd.BRW}
_AUTO_INC = {Cmd.APRD, Cmd.APWR, Cmd.APRW, Cmd.ARMW, Cmd.BRD, Cmd.BWR, Cmd.BRW}


#: After a round started by an SM2 event, the free-run timer's next round comes this many periods
#: later (it runs only when no outputs arrive, or when the master cycles slower than the models).
SM_FALLBACK_PERIODS = 1.5


class Segment:
    """``n`` ESCs with drive models, position 0 nearest to the master."""

    def __init__(self, n: int, profile: DriveProfile | EcatProfile | str | Sequence[DriveProfile | EcatProfile | str] = "generic"):
        if not 1 <= n <= 1000:
            raise ValueError(f"drives must be 1..1000, got {n}")
        profiles = parse_profiles(profile, n)
        self._plans: dict[tuple[int, int, int, int], tuple] = {}
        self._by_addr: dict[int, list[Esc]] | None = None
        self._active: bool | None = None
        self.escs: list[Esc] = []
        self.escs = [Esc(k, profiles[k], last=(k == n - 1), on_change=self._changed) for k in range(n)]
        self.frames = 0
        self._cursor = 0
        self._round_due = 0.0
        #: Outputs arrived for a slave in SM-synchronous mode (0x1C32:01 = 1): its application runs
        #: on that SM2 event, so the next round starts as soon as the frame is answered.
        self._sm_event = False
        self._round_sm = False
        start = time.monotonic()
        for esc in self.escs:
            esc.last_step = start

    def _changed(self, kind: str) -> None:
        self._plans.clear()
        self._active = None
        if kind in ("address", "all"):
            self._by_addr = None

    def any_active(self) -> bool:
        """True while some slave is in SAFE-OP or OP (process data flows: step at full rate)."""
        if self._active is None:
            self._active = any(e.al_state >= ALState.SAFEOP for e in self.escs)
        return self._active

    def _addr_map(self) -> dict[int, list[Esc]]:
        if self._by_addr is None:
            table: dict[int, list[Esc]] = {}
            for esc in self.escs:
                table.setdefault(esc.station_address, []).append(esc)
            self._by_addr = table
        return self._by_addr

    # -- fault injection hooks ------------------------------------------------------------
    def unplug(self, position: int) -> None:
        """The slave stops answering: its datagrams pass without WKC or data."""
        esc = self.escs[position]
        if esc.present:
            esc.present = False
            if esc.al_state == ALState.OP:
                esc.model.communication_lost()
            self._changed("all")

    def plug(self, position: int) -> None:
        """Back on the wire after a power cycle: INIT, registers reset, must be reconfigured."""
        esc = self.escs[position]
        if not esc.present:
            esc.model.power_cycle()
            esc.power_on()
            esc.present = True
            self._changed("all")

    def set_wkc_fault(self, position: int, on: bool) -> None:
        """Process data of this slave still flows, but it does not count in the WKC."""
        self.escs[position].wkc_fault = bool(on)
        self._changed("fmmu")

    # -- frame processing -----------------------------------------------------------------
    def process(self, buf: memoryview, n: int, now: float) -> bool:
        """Answer one frame in place. Returns False for a frame that must not be answered."""
        if n < ETH_HEADER + ECAT_HEADER + DG_HEADER + 2:
            return False
        header = U16.unpack_from(buf, ETH_HEADER)[0]
        if header >> 12 != 1:
            return False
        pos = ETH_HEADER + ECAT_HEADER
        present = None
        while True:
            if pos + DG_HEADER + 2 > n:
                return False
            cmd, _idx, adp, ado, dlen, _irq = DATAGRAM.unpack_from(buf, pos)
            length = dlen & 0x07FF
            data_off = pos + DG_HEADER
            wkc_off = data_off + length
            if wkc_off + 2 > n:
                return False
            if 10 <= cmd <= 12:
                key = (cmd, adp | (ado << 16), length, data_off)
                plan = self._plans.get(key)
                if plan is None:
                    plan = self._plan(cmd, adp | (ado << 16), length, buf, data_off)
                    self._plans[key] = plan
                writes, reads, wkc, written, sm_event = plan
                for dst, src in writes:
                    dst[:] = src
                for dst, src in reads:
                    dst[:] = src
                for esc in written:
                    esc.out_time = now
                    esc.out_count += 1
                if sm_event:
                    self._sm_event = True
            else:
                wkc = self._register_datagram(cmd, adp, ado, buf, data_off, length)
                if cmd in _AUTO_INC:
                    if present is None:
                        present = sum(1 for e in self.escs if e.present)
                    U16.pack_into(buf, pos + 2, (adp + present) & 0xFFFF)
            if wkc:
                U16.pack_into(buf, wkc_off, (U16.unpack_from(buf, wkc_off)[0] + wkc) & 0xFFFF)
            if not dlen & MORE_FOLLOWS:
                break
            pos = wkc_off + 2
        buf[6] |= 0x02  # a real ESC marks the source MAC on the way back
        self.frames += 1
        return True

    def _plan(self, cmd: int, laddr: int, length: int, buf: memoryview, data_off: int) -> tuple:
        writes, reads, written = [], [], []
        wkc = 0
        lend = laddr + length
        for esc in self.escs:
            if not esc.present or esc.al_state < ALState.SAFEOP or esc.al_state == ALState.BOOT:
                continue
            did_read = did_write = False
            for log_start, log_len, phys, ftype in esc.fmmus:
                a, b = max(log_start, laddr), min(log_start + log_len, lend)
                if a >= b:
                    continue
                p = phys + (a - log_start)
                if p + (b - a) > esc.mem_size:
                    continue
                frame_part = buf[data_off + a - laddr: data_off + b - laddr]
                mem_part = esc.mv[p: p + (b - a)]
                # Outputs only in OP: in SAFE-OP the output SyncManager takes no data, so a slave
                # that fell out of OP shows in the working counter (+1 instead of +3 for an LRW).
                if ftype == 2 and cmd in (Cmd.LWR, Cmd.LRW) and esc.al_state == ALState.OP:
                    writes.append((mem_part, frame_part))
                    did_write = True
                elif ftype == 1 and cmd in (Cmd.LRD, Cmd.LRW):
                    reads.append((frame_part, mem_part))
                    did_read = True
            if did_write:
                written.append(esc)
            if not esc.wkc_fault:
                wkc += int(did_read) + ((2 if cmd == Cmd.LRW else 1) if did_write else 0)
        # Without SYNC0 a slave is SM-synchronous: an output write is its SM2 event. A slave on
        # SYNC0 takes its outputs on its own clock (the round's grid).
        sm_event = any(esc.dc is None or esc.dc.sync0 is None for esc in written)
        return tuple(writes), tuple(reads), wkc, tuple(written), sm_event

    def _register_datagram(self, cmd: int, adp: int, ado: int, buf: memoryview, off: int, length: int) -> int:
        data = buf[off: off + length]
        if cmd in (Cmd.APRD, Cmd.APWR, Cmd.APRW, Cmd.FPRD, Cmd.FPWR, Cmd.FPRW):
            if cmd <= Cmd.APRW:
                k = (-adp) & 0xFFFF
                targets = [self.escs[k]] if k < len(self.escs) else []
            else:
                targets = self._addr_map().get(adp, [])
            wkc = 0
            for esc in targets:
                if not esc.present:
                    continue
                if cmd in _READS:
                    wkc += esc.read(ado, data)
                elif cmd in _WRITES:
                    wkc += esc.write(ado, data)
                else:
                    new = bytes(data)
                    wkc += esc.read(ado, data) + 2 * esc.write(ado, memoryview(new))
            return wkc
        if cmd in (Cmd.BRD, Cmd.BWR, Cmd.BRW):
            wkc = 0
            acc = int.from_bytes(data, "little")
            tmp = bytearray(length)
            new = bytes(data)
            for esc in self.escs:
                if not esc.present:
                    continue
                if cmd != Cmd.BWR:
                    tmp[:] = bytes(length)
                    if esc.read(ado, memoryview(tmp)):
                        acc |= int.from_bytes(tmp, "little")
                        wkc += 1
                if cmd != Cmd.BRD:
                    wkc += (2 if cmd == Cmd.BRW else 1) * esc.write(ado, memoryview(new))
            if cmd != Cmd.BWR:
                data[:] = acc.to_bytes(length, "little")
            return wkc
        if cmd in (Cmd.ARMW, Cmd.FRMW):
            wkc = 0
            for k, esc in enumerate(self.escs):
                if not esc.present:
                    continue
                reader = ((-adp) & 0xFFFF) == k if cmd == Cmd.ARMW else esc.station_address == adp
                if reader:
                    wkc += esc.read(ado, data)
                else:
                    wkc += esc.write(ado, data)
            return wkc
        return 0

    # -- application side -----------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance every drive by ``dt`` at once (tests and tools; the loop uses step_some)."""
        for esc in self.escs:
            self._step_one(esc, dt)

    @staticmethod
    def _step_one(esc: Esc, dt: float) -> None:
        state = esc.al_state
        if state == ALState.OP and esc.present:
            esc.apply_outputs()
        esc.model.step(dt)
        esc.push_emergencies()
        if state >= ALState.SAFEOP and state != ALState.BOOT:
            esc.update_inputs()

    def step_some(self, now: float, period: float, budget: int) -> bool:
        """Step at most ``budget`` drives of the current round (outputs in OP, model by its
        own elapsed time, EMCY, inputs). Returns True while the round is unfinished, so the
        frame loop polls instead of sleeping: frames never wait behind more than ``budget``
        model steps.

        A round starts on an SM2 event (a frame wrote the outputs of an SM-synchronous slave:
        drives without SYNC0 run their application on it, as real ones in that mode do, so a new
        controlword is obeyed right after the frame that carried it), or else every ``period``
        on a grid (free run: SAFE-OP, no frames, slaves on SYNC0). After an SM2 round the timer
        waits :data:`SM_FALLBACK_PERIODS` periods, so that a master cycling at ``period``
        drives the rounds alone and no round is run twice for one frame."""
        if self._cursor == 0:
            if self._sm_event:
                self._sm_event = False
                self._round_sm = True
            elif now < self._round_due:
                return False
            else:
                self._round_sm = False
        end = min(self._cursor + budget, len(self.escs))
        for esc in self.escs[self._cursor:end]:
            dt = now - esc.last_step
            esc.last_step = now
            self._step_one(esc, dt if dt < 0.1 else 0.1)
        if end >= len(self.escs):
            self._cursor = 0
            if self._round_sm:
                self._round_due = now + SM_FALLBACK_PERIODS * period
                return False
            # On a grid: one period after this round was *due*. Due one period after it started,
            # the next round fell a few us after the next frame, which wakes the loop, and then
            # waited for the frame after: the models stepped after about 60 % of 1 ms frames
            # only, so a drive answered a new controlword up to 2 ms late.
            due = self._round_due + period
            self._round_due = due if due > now - period else now + period  # far behind (idle, stalled): restart
            return False
        self._cursor = end
        return True

    def check_watchdogs(self, now: float) -> None:
        for esc in self.escs:
            if esc.al_state == ALState.OP and esc.wd_timeout_s and now - esc.out_time > esc.wd_timeout_s:
                log.warning("slave %d: SM watchdog expired (%.0f ms without outputs)",
                            esc.position, (now - esc.out_time) * 1e3)
                esc.watchdog_expired()
            esc.check_sync(now)

    def status(self) -> list[dict]:
        """Per-slave snapshot for the control interface."""
        return [{"slave": e.position, "profile": e.ecat_profile.name, "present": e.present, "al_state": e.al_state.wire_name,
                 "al_error": e.al_error, "al_status_code": e.al_code, "station_address": e.station_address,
                 "drive_state": e.model.state.value, "statusword": e.model.statusword,
                 "controlword": e.model.value(0x6040, 0), "mode_display": e.model.value(0x6061, 0),
                 "error_code": e.model.error_code, "wkc_fault": e.wkc_fault,
                 "dc": None if e.dc is None else {**e.dc.status(), "sync_error_counter": e.sync_error_counter}} for e in self.escs]
