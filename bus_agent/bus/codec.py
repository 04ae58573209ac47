"""One precompiled process-data codec per drive, built once at start-up from its mapping.

The cycle's cost stays flat: decoding a drive's inputs is one ``struct.unpack_from`` over its
whole TxPDO image plus one ``itemgetter`` that picks the cycle's fields (and one more for the
other mapped objects); encoding its outputs is one ``itemgetter`` and one ``struct.pack``.
No per-object Python loop runs per cycle. Cycle-safe (no allocation beyond the tuples).

Objects at byte offsets with a size of 8/16/32/64 bits are decoded; their type comes from the
CiA 402 table (:data:`bus_agent.bus.mapping.OBJECTS`), else unsigned. Padding (index 0) and
bit-sized entries become pad bytes (``x``); a required object that is not byte-aligned is a
:class:`~bus_agent.bus.mapping.MappingError`. Objects of the cycle's records that are not
mapped decode as 0 and are listed in :attr:`DriveCodec.absent_inputs`.
"""

from __future__ import annotations

import logging
import struct
from operator import itemgetter
from typing import Any, Callable, Sequence

from bus_agent.bus.mapping import (OBJECTS, RX_FIELDS, STATUS_FIELD_OF, TX_FIELDS, MappedEntry, MappingError,
                                   SlaveMapping)
from bus_agent.bus.pdo import DriveInputs, DriveOutputs

log = logging.getLogger(__name__)

_CODE = {"u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i", "u64": "Q", "i64": "q"}
_UNSIGNED = {8: "B", 16: "H", 32: "I", 64: "Q"}
IN_FIELDS = ("statusword", "position_actual", "velocity_actual", "torque_actual", "modes_of_operation_display",
             "error_code")
OUT_FIELDS = ("controlword", "target_position", "target_velocity", "target_torque", "modes_of_operation")


def _getter(idx: Sequence[int]) -> Callable[[tuple], tuple]:
    """itemgetter that always returns a tuple (also for 0 or 1 index)."""
    if not idx:
        return lambda t: ()
    if len(idx) == 1:
        i = idx[0]
        return lambda t: (t[i],)
    return itemgetter(*idx)


def _format(entries: Sequence[MappedEntry], total_bytes: int, side: str) -> tuple[str, list[MappedEntry]]:
    """Struct format over the whole image and the decoded entries in struct order."""
    fmt = ["<"]
    decoded: list[MappedEntry] = []
    pos = 0  # bytes covered so far
    for e in entries:
        if e.padding:
            continue
        code = None
        if e.bit_offset % 8 == 0 and e.bits in _UNSIGNED:
            info = OBJECTS.get(e.key)
            code = _CODE[info.datatype] if info and int(info.datatype[1:]) == e.bits else _UNSIGNED[e.bits]
        if code is None:
            if e.key in RX_FIELDS or e.key in TX_FIELDS:
                raise MappingError(f"{side} 0x{e.index:04X}:{e.subindex:02X} is {e.bits} bits at bit offset "
                                   f"{e.bit_offset}: the agent needs it byte-aligned with its natural size")
            log.info("%s 0x%04X:%02X (%d bits at bit %d) is not byte-aligned: not decoded", side, e.index,
                     e.subindex, e.bits, e.bit_offset)
            continue
        start = e.bit_offset // 8
        if start > pos:
            fmt.append(f"{start - pos}x")
        fmt.append(code)
        pos = start + e.bits // 8
        decoded.append(e)
    if total_bytes > pos:
        fmt.append(f"{total_bytes - pos}x")
    return "".join(fmt), decoded


class DriveCodec:
    """Encoder of a drive's outputs and decoder of its inputs, for one :class:`SlaveMapping`."""

    def __init__(self, mapping: SlaveMapping) -> None:
        self.mapping = mapping
        in_fmt, tx = _format(mapping.tx, mapping.in_bytes, "TxPDO")
        out_fmt, rx = _format(mapping.rx, mapping.out_bytes, "RxPDO")
        self.in_struct = struct.Struct(in_fmt)
        self.out_struct = struct.Struct(out_fmt)
        tx_keys = [e.key for e in tx]
        rx_keys = [e.key for e in rx]
        # inputs: the unpacked tuple plus a trailing 0 for the fields that are not mapped
        zero = len(tx_keys)
        field_pos = {TX_FIELDS[k]: i for i, k in enumerate(tx_keys) if k in TX_FIELDS}
        self._in_fields = _getter([field_pos.get(f, zero) for f in IN_FIELDS])
        extra = [i for i, k in enumerate(tx_keys) if k not in TX_FIELDS]
        self._in_extra = _getter(extra)
        self.extra_names: tuple[str, ...] = tuple(tx[i].name for i in extra)
        #: DriveStatus fields whose objects the drive does not map (reported absent, not 0).
        self.absent_inputs: tuple[str, ...] = tuple(
            name for key, name in STATUS_FIELD_OF.items() if key not in tx_keys)
        self.mapped_inputs = frozenset(tx_keys)
        self.mapped_outputs = frozenset(rx_keys)
        # outputs: (5 record fields..., 0) picked into the RxPDO's order; unknown objects get 0
        out_index = {f: i for i, f in enumerate(OUT_FIELDS)}
        self._out_pick = _getter([out_index.get(RX_FIELDS.get(k, ""), len(OUT_FIELDS)) for k in rx_keys])
        self._zero_tail = (0,)

    @property
    def in_size(self) -> int:
        return self.in_struct.size

    @property
    def out_size(self) -> int:
        return self.out_struct.size

    def decode_into(self, rec: DriveInputs, buf: Any) -> None:
        """Unpack ``buf`` (the slave's inputs) into ``rec``. Cycle-safe."""
        vals = self.in_struct.unpack_from(buf) + self._zero_tail
        (rec.statusword, rec.position_actual, rec.velocity_actual, rec.torque_actual,
         rec.modes_of_operation_display, rec.error_code) = self._in_fields(vals)
        rec.extra = self._in_extra(vals)

    def encode(self, o: DriveOutputs) -> bytes:
        """The slave's outputs for ``o``. Cycle-safe."""
        return self.out_struct.pack(*self._out_pick((o.controlword, o.target_position, o.target_velocity,
                                                     o.target_torque, o.modes_of_operation, 0)))
