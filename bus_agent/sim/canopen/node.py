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
from typing import Any, Mapping

from canopen.sdo import SdoAbortedError, SdoServer

from bus_agent.bus.canopen import cob as c, emcy
from bus_agent.bus.canopen.nmt import (HEARTBEAT_COB_BASE, NMT_COB_ID, NmtCommand, NmtState, after_command,
                                       decode_command)
from bus_agent.bus.mapping import RX_FIELDS, split_entry
from bus_agent.bus.pdo import DriveOutputs
from bus_agent.devices.eds import EdsObject
from bus_agent.sim.canopen import dictionary as nd
from bus_agent.sim.canopen.dictionary import NodeDictionary
from bus_agent.sim.drive_model import DriveModel, DriveProfile, ObjectEntry, SdoAbort, _INT_FORMATS

log = logging.getLogger(__name__)

Frame = tuple[int, bytes]
Entry = tuple[int, int, int]  # (index, subindex, bits) of a mapping entry
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
ABORT_LENGTH = 0x06070010
ABORT_RANGE = 0x06090030
#: Transmission types sent at a SYNC only when their data changed (acyclic synchronous; event-driven)
ON_CHANGE = frozenset({0, 0xFE, 0xFF})
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


class _DeviceDriveModel(DriveModel):
    """The drive model powering on with a device file's defaults (its EDS's) over the table's."""

    def __init__(self, profile: DriveProfile, serial: int, defaults: Mapping[tuple[int, int], int | str]) -> None:
        self._device_defaults = defaults
        super().__init__(profile, serial=serial)

    def _reset_power_on(self) -> None:
        super()._reset_power_on()
        self._values.update(self._device_defaults)


class SimNode:
    """A CANopen drive node. Not thread-safe: the segment serialises calls.

    Its objects are ``dictionary``'s (:mod:`bus_agent.sim.canopen.dictionary`: an EDS's), else the
    built-in drive's of ``profile``."""

    def __init__(self, node_id: int, profile: DriveProfile | None = None, serial: int = 0,
                 watchdog_s: float | None = DEFAULT_WATCHDOG_S, dictionary: NodeDictionary | None = None) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id} outside 1..127")
        if dictionary is None:
            if profile is None:
                raise ValueError("a node needs a drive profile or a dictionary")
            dictionary = nd.builtin(node_id, profile)
        self.node_id = node_id
        self.dictionary = dictionary
        self.model = (_DeviceDriveModel(dictionary.profile, serial, dictionary.model_defaults)
                      if dictionary.model_defaults else DriveModel(dictionary.profile, serial=serial))
        self.watchdog_s = watchdog_s
        self.object_dictionary = dictionary.od  # python-canopen's SdoServer holds one
        self.plain: dict[tuple[int, int], bytes] = {}
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
        self._tx: list[tuple[int, int, tuple[Entry, ...], int]] = []  # (COB-ID, type, entries, n)
        self._tx_sent: dict[int, bytes] = {}
        self._power_on_plain()
        self._boot(0.0, power=False)

    def _power_on_plain(self) -> None:
        self.plain = {k: o.default_bytes() for k, o in self.dictionary.plain.items()}

    # ---------------------------------------------------------------- lifecycle

    def _boot(self, now_s: float, power: bool) -> list[Frame]:
        """Initialisation: communication objects to defaults (and the drive when powered up),
        boot-up message, pre-operational (CiA 301 Figure 48)."""
        if power:
            self.model.power_cycle()
            self._power_on_plain()
        self.comm = dict(self.dictionary.comm_defaults)
        self._pending.clear()
        self._last_sync_s = None
        self.last_sync_counter = None
        self._sync_length_bad = False
        self._rebuild_pdos()
        self.state = NmtState.PRE_OPERATIONAL
        self._next_heartbeat_s = now_s + self.heartbeat_s
        self.counters["heartbeat"] += 1
        return [(HEARTBEAT_COB_BASE + self.node_id, b"\x00")]

    @property
    def heartbeat_s(self) -> float:
        return self.comm[(0x1017, 0)] / 1000.0

    def _rebuild_pdos(self) -> None:
        """COB-ID -> (entries, n) of every valid RPDO; (COB-ID, type, entries, n) of every valid TPDO."""
        self._rx = {}
        self._tx = []
        self._tx_sent = {}
        for n in range(c.MAX_PDOS):
            cob = self.comm[(c.RPDO_COMM + n, 1)]
            if not cob & c.COB_ID_INVALID:
                self._rx[cob & c.COB_ID_MASK] = (self._entries(c.RPDO_MAP + n), n)
            cob = self.comm[(c.TPDO_COMM + n, 1)]
            if not cob & c.COB_ID_INVALID:
                self._tx.append((cob & c.COB_ID_MASK, self.comm[(c.TPDO_COMM + n, 2)], self._entries(c.TPDO_MAP + n), n))

    def _entries(self, map_index: int) -> tuple[Entry, ...]:
        values = (self.comm.get((map_index, i), 0) for i in range(1, self.comm[(map_index, 0)] + 1))
        return tuple(split_entry(v) for v in values if v)

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
            entries, n = self._rx[cob_id]
            try:
                self._pending.update(self._typed(_unpack(entries, data)))
                self.counters["rpdo"] += 1
            except ValueError:
                out += self._emcy(0x8210)  # PDO not processed due to length error
            else:
                if self.comm[(c.RPDO_COMM + n, 2)] in ON_CHANGE - {0}:
                    self._apply_pending()  # event-driven: applied now, not at the next SYNC
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
        count = self.counters["sync"]
        for cob, kind, entries, _n in self._tx:
            if kind in ON_CHANGE:
                data = self._tpdo_data(entries)
                if self._tx_sent.get(cob) == data:
                    continue
                self._tx_sent[cob] = data
            elif kind <= 240 and count % kind == 0:  # synchronous, every kind-th SYNC
                data = self._tpdo_data(entries)
            else:
                continue  # RTR-only types (0xFC, 0xFD) and reserved ones: not sent on SYNC
            out.append((cob, data))
            self.counters["tpdo"] += 1
        return out

    def _tpdo_data(self, entries: tuple[Entry, ...]) -> bytes:
        """The frame of one TPDO: its entries' values packed LSB first, each to its bit length."""
        acc = offset = 0
        plain, drive = self.plain, self.dictionary.drive
        for index, sub, bits in entries:
            key = (index, sub)
            if key in plain:
                value = int.from_bytes(plain[key], "little")
            elif key in drive:
                try:
                    value = int(self.model.read(index, sub))
                except (SdoAbort, ValueError):  # an EDS default mapping may name a write-only or string object
                    value = 0
            else:
                value = 0  # a default mapping naming an object the dictionary lacks
            acc |= (value & ((1 << bits) - 1)) << offset
            offset += bits
        return acc.to_bytes((offset + 7) // 8, "little")

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

    def _typed(self, raw: dict[tuple[int, int], tuple[int, int]]) -> dict[tuple[int, int], int]:
        """RPDO values as the objects hold them: the drive model's signed where their type is; a
        stored object's as unsigned; an object the dictionary lacks dropped."""
        out = {}
        for key, (value, bits) in raw.items():
            entry = self.dictionary.drive.get(key)
            if entry is not None:
                out[key] = value - (1 << bits) if nd.signed(entry) and value >> (bits - 1) else value
            elif key in self.dictionary.plain:
                out[key] = value
        return out

    def _apply_pending(self) -> None:
        """The RPDO objects received since the last SYNC: the cycle's through the drive's
        outputs (as the EtherCAT simulator applies them), any other mapped object written."""
        values = {k: int(self.model.read(*k)) for k in RX_FIELDS}
        for key, value in self._pending.items():
            plain = self.dictionary.plain.get(key)
            if plain is not None:
                size = max(1, (plain.bits + 7) // 8)
                self.plain[key] = (value & ((1 << 8 * size) - 1)).to_bytes(size, "little")
                continue
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

    def _absent(self, index: int) -> SdoAbortedError:
        return SdoAbortedError(ABORT_NO_SUBINDEX if self.dictionary.has_index(index) else ABORT_NO_OBJECT)

    def get_data(self, index: int, subindex: int, check_readable: bool = False) -> bytes:
        """python-canopen SdoServer hook: the value of an object as bytes, or SdoAbortedError."""
        key = (index, subindex)
        d = self.dictionary
        if key in d.comm:
            return struct.pack(_INT_FORMATS[d.comm[key].datatype], self.comm[key])
        entry = d.plain.get(key) or d.drive.get(key)
        if entry is None:
            raise self._absent(index)
        if entry.access == "wo":
            raise SdoAbortedError(ABORT_WRITE_ONLY)
        if key in d.plain:
            return self.plain[key]
        try:
            return self.model.read_bytes(index, subindex)
        except SdoAbort as e:
            raise SdoAbortedError(e.code) from None

    def set_data(self, index: int, subindex: int, data: bytes, check_writable: bool = False) -> None:
        """python-canopen SdoServer hook: write an object, or SdoAbortedError (nothing changes)."""
        key = (index, subindex)
        d = self.dictionary
        if key in d.comm:
            self._write_comm(d.comm[key], bytes(data))
            return
        entry = d.plain.get(key) or d.drive.get(key)
        if entry is None:
            raise self._absent(index)
        if entry.access == "ro":
            raise SdoAbortedError(ABORT_READ_ONLY)
        plain = d.plain.get(key)
        if plain is not None:
            self.plain[key] = _checked(plain, bytes(data))
            return
        try:
            self.model.write_bytes(index, subindex, bytes(data))
        except SdoAbort as e:
            raise SdoAbortedError(e.code) from None

    def _write_comm(self, entry: ObjectEntry, data: bytes) -> None:
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
                    mapped = split_entry(value)[:2]
                    obj = self.dictionary.drive.get(mapped) or self.dictionary.plain.get(mapped)
                    wrong_way = obj is not None and (obj.access == "ro" if not tx else obj.access == "wo")
                    if obj is None or not obj.pdo_mappable or obj.bits != value & 0xFF or wrong_way:
                        raise SdoAbortedError(ABORT_NOT_MAPPABLE)
            elif value > 0:
                bits = sum(self.comm.get((index, i), 0) & 0xFF for i in range(1, value + 1))
                if bits > c.MAX_PDO_BITS or any(self.comm.get((index, i), 0) == 0 for i in range(1, value + 1)):
                    raise SdoAbortedError(ABORT_PDO_LENGTH)
        self.comm[(index, sub)] = value
        self._rebuild_pdos()
        if index == 0x1017:
            self._next_heartbeat_s = 0.0


def _unpack(entries: tuple[Entry, ...], data: bytes) -> dict[tuple[int, int], tuple[int, int]]:
    """(raw unsigned value, bits) of every object of one RPDO frame, LSB first. Raises
    ValueError when the frame is shorter than its mapping."""
    total = sum(bits for _i, _s, bits in entries)
    if len(data) * 8 < total:
        raise ValueError(f"RPDO of {len(data)} bytes, its mapping has {total} bits")
    acc = int.from_bytes(data, "little")
    values = {}
    offset = 0
    for index, sub, bits in entries:
        values[(index, sub)] = ((acc >> offset) & ((1 << bits) - 1), bits)
        offset += bits
    return values


def _checked(entry: EdsObject, data: bytes) -> bytes:
    """An SDO download to a stored object: its size (numbers) and LowLimit/HighLimit, else an abort."""
    size = (entry.bits + 7) // 8
    if size and len(data) != size:
        raise SdoAbortedError(ABORT_LENGTH)
    if entry.integer is not None and (entry.low is not None or entry.high is not None):
        value = int.from_bytes(data, "little", signed=entry.integer[2])
        if (entry.low is not None and value < entry.low) or (entry.high is not None and value > entry.high):
            raise SdoAbortedError(ABORT_RANGE)
    return data
