"""One precompiled process-data codec per drive, built once at start-up from its mapping.

The cycle's cost stays flat: decoding a drive's inputs is one ``struct.unpack_from`` over its
whole TxPDO image whose values land straight in the record's fields (one unpacking assignment);
encoding its outputs is one ``struct.pack`` of the record's fields in RxPDO order. Both are
functions generated once per layout at start-up (as ``dataclasses`` and ``namedtuple`` do), so
no per-object Python loop, no intermediate tuple and no index lookup runs per cycle: for the
default layout they are the very statements the fixed 13/15-byte structs needed. Cycle-safe.

Objects at byte offsets with a size of 8/16/32/64 bits are decoded; their type comes from the
CiA 402 table (:data:`bus_agent.bus.mapping.OBJECTS`), else from the slave's ESI (vendor objects,
named by the ESI too), else unsigned. Padding (index 0) and
bit-sized entries become pad bytes (``x``); a required object that is not byte-aligned is a
:class:`~bus_agent.bus.mapping.MappingError`. Objects of the cycle's records that are not
mapped decode as 0 and are listed in :attr:`DriveCodec.absent_inputs`.
"""

from __future__ import annotations

import logging
import struct
from typing import Any, Callable, Mapping, Sequence

from bus_agent.bus.mapping import (OBJECTS, RX_FIELDS, STATUS_FIELD_OF, TX_FIELDS, MappedEntry, MappingError,
                                   ObjectInfo, SlaveMapping)
from bus_agent.bus.pdo import DriveInputs, DriveOutputs

log = logging.getLogger(__name__)

_CODE = {"u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i", "u64": "Q", "i64": "q"}
_UNSIGNED = {8: "B", 16: "H", 32: "I", 64: "Q"}
IN_FIELDS = ("statusword", "position_actual", "velocity_actual", "torque_actual", "modes_of_operation_display",
             "error_code")
OUT_FIELDS = ("controlword", "target_position", "target_velocity", "target_torque", "modes_of_operation")
_TX_KEY_OF = {name: key for key, name in TX_FIELDS.items()}


def _format(entries: Sequence[MappedEntry], total_bytes: int, side: str,
            objects: Mapping[tuple[int, int], ObjectInfo] = {}) -> tuple[str, list[MappedEntry]]:
    """Struct format over the whole image and the decoded entries in struct order."""
    fmt = ["<"]
    decoded: list[MappedEntry] = []
    pos = 0  # bytes covered so far
    for e in entries:
        if e.padding:
            continue
        code = None
        if e.bit_offset % 8 == 0 and e.bits in _UNSIGNED:
            info = OBJECTS.get(e.key) or objects.get(e.key)
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


def _compile(name: str, source: str, namespace: dict[str, Any]) -> Callable[..., Any]:
    """The function ``name`` defined by ``source`` (built from field names and positions only)."""
    exec(compile(source, f"<DriveCodec {name}>", "exec"), namespace)
    return namespace[name]


def _decode_lines(rec: str, buf: str, unpack: str, tx_keys: Sequence[tuple[int, int]], tag: str = "") -> list[str]:
    """Statements that decode ``buf`` with ``unpack`` into record ``rec``: one unpack whose
    targets are the record's fields (mapped objects) and locals (other objects, gathered into
    ``rec.extra``), then 0 for the fields not mapped."""
    targets, extra = [], []
    for n, key in enumerate(tx_keys):
        field_name = TX_FIELDS.get(key)
        if field_name is not None:
            targets.append(f"{rec}.{field_name}")
        else:
            targets.append(f"x{tag}_{n}")
            extra.append(f"x{tag}_{n}")
    lines = [f"({', '.join(targets)},) = {unpack}({buf})"] if targets else []
    lines += [f"{rec}.{f} = 0" for f in IN_FIELDS if _TX_KEY_OF[f] not in tx_keys]
    lines.append(f"{rec}.extra = ({''.join(x + ', ' for x in extra)})")
    return lines


def _decoder(struct_: struct.Struct, tx_keys: Sequence[tuple[int, int]]) -> Callable[[DriveInputs, Any], None]:
    """``decode_into(rec, buf)`` for one layout."""
    body = _decode_lines("rec", "buf", "unpack_from", tx_keys)
    return _compile("decode_into", "def decode_into(rec, buf):\n    " + "\n    ".join(body),
                    {"unpack_from": struct_.unpack_from})


def segment_decoder(codecs: Sequence["DriveCodec"], records: Sequence[DriveInputs], sources: Sequence[Any],
                    attr: str = "input", changes: bool = False) -> Callable[[], list[int] | None]:
    """One function that decodes every slave's inputs (``sources[k].<attr>``, e.g. a pysoem
    slave's ``input``) into ``records[k]`` with ``codecs[k]``: the whole process image in one
    pass, straight-line code without a loop or a call per slave. Cycle-safe.

    ``changes``: decode only the slaves whose input bytes differ from the last call's (all at
    the first call) and return their positions ``k`` in order (one list, reused: valid until the
    next call); a slave at rest costs one bytes comparison. Else every slave is decoded and
    None returned."""
    if not attr.isidentifier():
        raise ValueError(f"not an attribute name: {attr!r}")
    ns: dict[str, Any] = {"P": [None] * len(codecs), "C": []}
    body: list[str] = ["C.clear()"] if changes else []
    for k, (codec, rec, src) in enumerate(zip(codecs, records, sources, strict=True)):
        ns[f"U{k}"], ns[f"R{k}"], ns[f"S{k}"] = codec.in_struct.unpack_from, rec, src
        if changes:
            body += [f"b = S{k}.{attr}", f"if b != P[{k}]:", f"    P[{k}] = b", f"    C.append({k})"]
            body += ["    " + line for line in _decode_lines(f"R{k}", "b", f"U{k}", codec.tx_keys, str(k))]
        else:
            body += _decode_lines(f"R{k}", f"S{k}.{attr}", f"U{k}", codec.tx_keys, str(k))
    body.append("return C" if changes else "return None")
    return _compile("decode_all", "def decode_all():\n    " + "\n    ".join(body), ns)


def _encoder(struct_: struct.Struct, rx_keys: Sequence[tuple[int, int]]) -> Callable[[DriveOutputs], bytes]:
    """``encode(o)``: one pack of the record's fields in RxPDO order (0 for other objects)."""
    args = [f"o.{RX_FIELDS[k]}" if k in RX_FIELDS else "0" for k in rx_keys]
    return _compile("encode", f"def encode(o):\n    return pack({', '.join(args)})", {"pack": struct_.pack})



class DriveCodec:
    """Encoder of a drive's outputs and decoder of its inputs, for one :class:`SlaveMapping`.

    ``decode_into(rec, buf)`` unpacks ``buf`` (the slave's inputs) into the
    :class:`~bus_agent.bus.pdo.DriveInputs` ``rec``: every field, 0 for objects not mapped, the
    other mapped objects into ``rec.extra`` (in the order of :attr:`extra_names`).
    ``encode(o)`` returns the slave's outputs for the :class:`~bus_agent.bus.pdo.DriveOutputs`
    ``o``. Both cycle-safe.
    """

    decode_into: Callable[[DriveInputs, Any], None]
    encode: Callable[[DriveOutputs], bytes]

    def __init__(self, mapping: SlaveMapping, objects: Mapping[tuple[int, int], ObjectInfo] | None = None) -> None:
        """``objects``: names and types of objects the CiA 402 table lacks (the slave's ESI)."""
        self.mapping = mapping
        objects = objects or {}
        in_fmt, tx = _format(mapping.tx, mapping.in_bytes, "TxPDO", objects)
        out_fmt, rx = _format(mapping.rx, mapping.out_bytes, "RxPDO", objects)
        self.in_struct = struct.Struct(in_fmt)
        self.out_struct = struct.Struct(out_fmt)
        tx_keys = [e.key for e in tx]
        rx_keys = [e.key for e in rx]
        #: The decoded input objects in image order (the struct's fields).
        self.tx_keys: tuple[tuple[int, int], ...] = tuple(tx_keys)
        self.extra_names: tuple[str, ...] = tuple(
            objects[e.key].name if e.key in objects and e.key not in OBJECTS else e.name
            for e in tx if e.key not in TX_FIELDS)
        #: DriveStatus fields whose objects the drive does not map (reported absent, not 0).
        self.absent_inputs: tuple[str, ...] = tuple(
            name for key, name in STATUS_FIELD_OF.items() if key not in tx_keys)
        self.mapped_inputs = frozenset(tx_keys)
        self.mapped_outputs = frozenset(rx_keys)
        # instance attributes, not methods: the cycle's call is a plain function call
        self.decode_into = _decoder(self.in_struct, tx_keys)
        self.encode = _encoder(self.out_struct, rx_keys)

    @property
    def in_size(self) -> int:
        return self.in_struct.size

    @property
    def out_size(self) -> int:
        return self.out_struct.size
