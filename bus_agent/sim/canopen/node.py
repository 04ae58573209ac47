"""One simulated CANopen CiA 402 node: the device side of NMT, SDO, SYNC, PDOs, heartbeat, EMCY.

Frames in, frames out: :meth:`SimNode.on_frame` and :meth:`SimNode.tick` take a frame or the
time and return the frames the node sends (COB-ID, data); the segment does the CAN I/O. The SDO
server is python-canopen's (``SdoServer``) over this node's object dictionary
(:mod:`bus_agent.sim.canopen.od`): communication objects live here, the drive's objects in the
:class:`~bus_agent.sim.drive_model.DriveModel`.

Behaviour (CiA 301):
- NMT slave per :data:`bus_agent.bus.canopen.nmt.TRANSITIONS`. A reset sends the boot-up
  message and lands in pre-operational; reset node power-cycles the drive, both reset the
  communication objects (PDO mapping, heartbeat time) to their defaults. Leaving operational
  makes a drive in Operation enabled lose communication (fault 0x8130, as the EtherCAT SM
  watchdog does).
- SYNC (0x080): in operational, the RPDOs received since the previous SYNC are applied, the drive
  steps, and every valid synchronous TPDO is sent. With 0x1019 (synchronous counter overflow
  value) 2..240 a SYNC carries a counter 1..value, checked in sequence; a SYNC of the wrong
  length is EMCY 0x8240. In operational without SYNC for
  ``watchdog_s`` (after a first one), the drive loses communication.
- Heartbeat every 0x1017 ms (0 = none) with the NMT state; EMCY on every fault and reset.
- PDO mapping writable only outside operational, with sub 0 = 0 first (abort 0x08000022 /
  0x06010000); entries must be mappable, in the right direction, <= 64 bits (0x06040041/42).
- Unplugged: no frame in or out; plugged back: power-cycled, boot-up, pre-operational.
"""

from __future__ import annotations

import logging
import struct
from typing import Any

from canopen.sdo import SdoAbortedError, SdoServer

from bus_agent.bus.canopen import cob as c, emcy
from bus_agent.bus.canopen.nmt import (HEARTBEAT_COB_BASE, NMT_COB_ID, NmtCommand, NmtState, after_command,
                                       decode_command)
from bus_agent.bus.mapping import RX_FIELDS, split_entry
from bus_agent.bus.pdo import DriveOutputs
from bus_agent.sim.canopen import od
from bus_agent.sim.drive_model import DriveModel, DriveProfile, SdoAbort, _INT_FORMATS

log = logging.getLogger(__name__)

Frame = tuple[int, bytes]
Entry = tuple[int, int, int]  # (index, subindex, bits) of a mapping entry
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_DEVICE_STATE = 0x08000022
DEFAULT_WATCHDOG_S = 0.5  # generous: Python processes on a shared host stall for 100 ms at times


class _Outbox:
    """What python-canopen's SdoServer sees as its network: frames collected for the segment."""

    def __init__(self) -> None:
        self.frames: list[Frame] = []

    def send_message(self, can_id: int, data: Any, remote: bool = False) -> None:
        self.frames.append((can_id, bytes(data)))


class SimNode:
    """A CANopen drive node. Not thread-safe: the segment serialises calls."""

    def __init__(self, node_id: int, profile: DriveProfile, serial: int = 0,
                 watchdog_s: float | None = DEFAULT_WATCHDOG_S) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id} outside 1..127")
        self.node_id = node_id
        self.model = DriveModel(profile, serial=serial)
        self.watchdog_s = watchdog_s
        self.object_dictionary = od.build(node_id, profile.device_name)  # python-canopen SdoServer reads it
        self._outbox = _Outbox()
        self.sdo = SdoServer(c.SDO_RX_BASE + node_id, c.SDO_TX_BASE + node_id, self)
        self.sdo.network = self._outbox  # type: ignore[assignment]
        self.state = NmtState.INITIALISING
        self.plugged = True
        self.comm: dict[tuple[int, int], int] = {}
        self._pending: dict[tuple[int, int], int] = {}
        self._last_step_s: float | None = None
        self._last_sync_s: float | None = None
        self._next_heartbeat_s = 0.0
        self.counters = {"sync": 0, "tpdo": 0, "rpdo": 0, "emcy": 0, "heartbeat": 0, "nmt": 0,
                         "sync_length_errors": 0, "sync_counter_errors": 0}
        self.last_sync_counter: int | None = None
        self._sync_length_bad = False
        self._rx: dict[int, tuple[tuple[Entry, ...], int]] = {}
        self._boot(0.0, power=False)

    # ---------------------------------------------------------------- lifecycle

    def _boot(self, now_s: float, power: bool) -> list[Frame]:
        """Initialisation: communication objects to defaults (and the drive when powered up),
        boot-up message, pre-operational (CiA 301 Figure 48)."""
        if power:
            self.model.power_cycle()
        self.comm = od.comm_defaults(self.node_id)
        self._pending.clear()
        self._last_sync_s = None
        self.last_sync_counter = None
        self._sync_length_bad = False
        self._rebuild_rx()
        self.state = NmtState.PRE_OPERATIONAL
        self._next_heartbeat_s = now_s + self.heartbeat_s
        self.counters["heartbeat"] += 1
        return [(HEARTBEAT_COB_BASE + self.node_id, b"\x00")]

    @property
    def heartbeat_s(self) -> float:
        return self.comm[(0x1017, 0)] / 1000.0

    def _rebuild_rx(self) -> None:
        """COB-ID -> (entries, comm index) of every valid RPDO."""
        self._rx = {}
        for n in range(c.MAX_PDOS):
            cob = self.comm[(c.RPDO_COMM + n, 1)]
            if not cob & c.COB_ID_INVALID:
                self._rx[cob & c.COB_ID_MASK] = (self._entries(c.RPDO_MAP + n), n)

    def _entries(self, map_index: int) -> tuple[Entry, ...]:
        return tuple(split_entry(self.comm[(map_index, i)]) for i in range(1, self.comm[(map_index, 0)] + 1))

    def _set_state(self, state: NmtState) -> None:
        if self.state is NmtState.OPERATIONAL and state is not NmtState.OPERATIONAL:
            self.model.communication_lost()
            self._last_sync_s = None
        self.state = state

    def unplug(self) -> None:
        self.plugged = False

    def plug(self, now_s: float) -> list[Frame]:
        if self.plugged:
            return []
        self.plugged = True
        self._last_step_s = now_s
        return self._boot(now_s, power=True)

    # ---------------------------------------------------------------- frames in

    def on_frame(self, cob_id: int, data: bytes, now_s: float) -> list[Frame]:
        """Handle one received frame; returns the frames this node sends in response."""
        if not self.plugged:
            return []
        out: list[Frame] = []
        if cob_id == NMT_COB_ID:
            out += self._on_nmt(data, now_s)
        elif cob_id == self.comm[(0x1005, 0)] & c.COB_ID_MASK:
            out += self._on_sync(data, now_s)
        elif cob_id == c.SDO_RX_BASE + self.node_id and self.state is not NmtState.STOPPED:
            self.sdo.on_request(cob_id, bytearray(data), now_s)
            out += self._outbox.frames
            self._outbox.frames = []
        elif cob_id in self._rx and self.state is NmtState.OPERATIONAL:
            entries, _n = self._rx[cob_id]
            try:
                self._pending.update(_unpack(entries, data))
                self.counters["rpdo"] += 1
            except struct.error:
                out += self._emcy(0x8210)  # PDO not processed due to length error
        return out

    def _on_nmt(self, data: bytes, now_s: float) -> list[Frame]:
        try:
            command, target = decode_command(data)
        except ValueError:
            return []
        if command is None or target not in (0, self.node_id):
            return []
        self.counters["nmt"] += 1
        new = after_command(self.state, command)
        log.info("node %d: NMT 0x%02X: %s -> %s", self.node_id, command, self.state.wire_name, new.wire_name)
        self._set_state(new)
        if new is NmtState.INITIALISING:
            return self._boot(now_s, power=command is NmtCommand.RESET_NODE)
        return self._heartbeat(now_s)

    def _on_sync(self, data: bytes, now_s: float) -> list[Frame]:
        self.counters["sync"] += 1
        self._step(now_s)
        out = self._check_sync_counter(data)
        if self.state is not NmtState.OPERATIONAL:
            return out + self._take_emcy()
        self._last_sync_s = now_s
        if self._pending:
            self._apply_pending()
        out += self._take_emcy()
        for n in range(c.MAX_PDOS):
            cob = self.comm[(c.TPDO_COMM + n, 1)]
            if cob & c.COB_ID_INVALID or self.comm[(c.TPDO_COMM + n, 2)] != c.TRANSMISSION_SYNC:
                continue
            entries = self._entries(c.TPDO_MAP + n)
            data = b"".join(struct.pack(_INT_FORMATS[od.DRIVE_OBJECTS[e[:2]].datatype],
                                        int(self.model.read(e[0], e[1]))) for e in entries)
            out.append((cob & c.COB_ID_MASK, data))
            self.counters["tpdo"] += 1
        return out

    def _check_sync_counter(self, data: bytes) -> list[Frame]:
        """0x1019 (CiA 301 §7.5.2.22): 0 = SYNC without data; 2..240 = one byte counting 1..value
        and back to 1. Another length is counted, with EMCY 0x8240 (unexpected SYNC data length)
        on the first of a run; a counter out of sequence or range is counted and logged."""
        overflow = self.comm[(0x1019, 0)]
        if len(data) != (1 if overflow in c.SYNC_COUNTER_RANGE else 0):
            self.counters["sync_length_errors"] += 1
            first, self._sync_length_bad = not self._sync_length_bad, True
            return self._emcy(0x8240) if first else []
        self._sync_length_bad = False
        if not data:
            return []
        counter, last = data[0], self.last_sync_counter
        expected = 1 if last is None or last >= overflow else last + 1
        if not 1 <= counter <= overflow or (last is not None and counter != expected):
            self.counters["sync_counter_errors"] += 1
            log.warning("node %d: SYNC counter %d, expected %s (0x1019 = %d)", self.node_id, counter,
                        expected if last is not None else f"1..{overflow}", overflow)
        self.last_sync_counter = counter
        return []

    def _apply_pending(self) -> None:
        """The RPDO objects received since the last SYNC: the cycle's through the drive's
        outputs (as the EtherCAT simulator applies them), any other mapped object written."""
        values = {k: int(self.model.read(*k)) for k in RX_FIELDS}
        for key, value in self._pending.items():
            if key in RX_FIELDS:
                values[key] = value
            else:
                try:
                    self.model.write(key[0], key[1], value)
                except SdoAbort as e:
                    log.info("node %d: RPDO object 0x%04X:%02X = %d refused: %s", self.node_id, *key, value, e)
        self._pending.clear()
        self.model.apply_outputs(DriveOutputs(**{RX_FIELDS[k]: v for k, v in values.items()}))

    # ---------------------------------------------------------------- time

    def _step(self, now_s: float) -> None:
        dt = 0.0 if self._last_step_s is None else max(0.0, now_s - self._last_step_s)
        self._last_step_s = now_s
        self.model.step(dt)

    def tick(self, now_s: float) -> list[Frame]:
        """Time passes without SYNC: the drive steps, the watchdog and heartbeat run."""
        if not self.plugged:
            self._last_step_s = now_s
            return []
        if self._last_step_s is None or now_s - self._last_step_s >= 0.005:
            self._step(now_s)
        if (self.state is NmtState.OPERATIONAL and self.watchdog_s is not None and self._last_sync_s is not None
                and now_s - self._last_sync_s > self.watchdog_s):
            log.warning("node %d: no SYNC for %.0f ms in operational: communication lost", self.node_id,
                        (now_s - self._last_sync_s) * 1000)
            self._last_sync_s = None
            self.model.communication_lost()
        out = self._take_emcy()
        if self.heartbeat_s > 0 and now_s >= self._next_heartbeat_s:
            out += self._heartbeat(now_s)
        return out

    def _heartbeat(self, now_s: float) -> list[Frame]:
        if self.heartbeat_s <= 0:
            return []
        self._next_heartbeat_s = now_s + self.heartbeat_s
        self.counters["heartbeat"] += 1
        return [(HEARTBEAT_COB_BASE + self.node_id, bytes((int(self.state),)))]

    def _take_emcy(self) -> list[Frame]:
        out: list[Frame] = []
        for e in self.model.take_emcy():
            out += self._emcy(e.error_code, e.error_register)
        return out

    def _emcy(self, code: int, register: int = 0) -> list[Frame]:
        if self.state is NmtState.STOPPED:
            return []
        self.counters["emcy"] += 1
        return [(self.comm[(0x1014, 0)] & c.COB_ID_MASK, emcy.encode(code, register))]

    def inject_fault(self, error_code: int, now_s: float) -> list[Frame]:
        self.model.inject_fault(error_code)
        return self._take_emcy()

    # ---------------------------------------------------------------- SDO server callbacks

    def get_data(self, index: int, subindex: int, check_readable: bool = False) -> bytes:
        """python-canopen SdoServer hook: the value of an object as bytes, or SdoAbortedError."""
        key = (index, subindex)
        if key in od.COMM_OBJECTS:
            return struct.pack(_INT_FORMATS[od.COMM_OBJECTS[key].datatype], self.comm[key])
        if key not in od.DRIVE_OBJECTS:
            raise SdoAbortedError(0x06090011 if (index, 0) in od.DRIVE_OBJECTS else 0x06020000)
        try:
            return self.model.read_bytes(index, subindex)
        except SdoAbort as e:
            raise SdoAbortedError(e.code) from None

    def set_data(self, index: int, subindex: int, data: bytes, check_writable: bool = False) -> None:
        """python-canopen SdoServer hook: write an object, or SdoAbortedError (nothing changes)."""
        key = (index, subindex)
        if key in od.COMM_OBJECTS:
            self._write_comm(od.COMM_OBJECTS[key], bytes(data))
            return
        if key not in od.DRIVE_OBJECTS:
            raise SdoAbortedError(0x06090011 if (index, 0) in od.DRIVE_OBJECTS else 0x06020000)
        try:
            self.model.write_bytes(index, subindex, bytes(data))
        except SdoAbort as e:
            raise SdoAbortedError(e.code) from None

    def _write_comm(self, entry: od.ObjectEntry, data: bytes) -> None:
        if entry.access == "ro":
            raise SdoAbortedError(0x06010002)
        if len(data) != entry.size:
            raise SdoAbortedError(0x06070010)
        (value,) = struct.unpack(_INT_FORMATS[entry.datatype], data)
        lo, hi = entry.value_range()
        if not lo <= value <= hi:
            raise SdoAbortedError(0x06090030)
        index, sub = entry.index, entry.subindex
        is_map = c.RPDO_MAP <= index < c.RPDO_MAP + c.MAX_PDOS or c.TPDO_MAP <= index < c.TPDO_MAP + c.MAX_PDOS
        if (is_map or c.RPDO_COMM <= index < c.RPDO_COMM + c.MAX_PDOS
                or c.TPDO_COMM <= index < c.TPDO_COMM + c.MAX_PDOS) and self.state is NmtState.OPERATIONAL:
            raise SdoAbortedError(ABORT_DEVICE_STATE)
        if index == 0x1019 and value != 0 and value not in c.SYNC_COUNTER_RANGE:
            raise SdoAbortedError(0x06090030)  # 1 and 241..255 are reserved
        if is_map:
            tx = index >= c.TPDO_MAP
            if sub > 0:
                if self.comm[(index, 0)] != 0:
                    raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)  # disable the mapping (sub 0 = 0) first
                if value != 0:
                    obj = od.DRIVE_OBJECTS.get(split_entry(value)[:2])
                    wrong_way = obj is not None and (obj.access == "ro" if not tx else obj.access == "wo")
                    if obj is None or not obj.pdo_mappable or obj.bits != value & 0xFF or wrong_way:
                        raise SdoAbortedError(ABORT_NOT_MAPPABLE)
            elif value > 0:
                bits = sum(self.comm[(index, i)] & 0xFF for i in range(1, value + 1))
                if bits > c.MAX_PDO_BITS or any(self.comm[(index, i)] == 0 for i in range(1, value + 1)):
                    raise SdoAbortedError(ABORT_PDO_LENGTH)
        self.comm[(index, sub)] = value
        self._rebuild_rx()
        if index == 0x1017:
            self._next_heartbeat_s = 0.0


def _unpack(entries: tuple[Entry, ...], data: bytes) -> dict[tuple[int, int], int]:
    """Object values of one RPDO frame, by the drive's own object types (device side; the
    entries were checked mappable with their size when written). Raises struct.error when
    the frame is shorter than its mapping."""
    values = {}
    offset = 0
    for index, sub, bits in entries:
        fmt = _INT_FORMATS[od.DRIVE_OBJECTS[(index, sub)].datatype]
        values[(index, sub)] = struct.unpack_from(fmt, data, offset)[0]
        offset += bits // 8
    return values
