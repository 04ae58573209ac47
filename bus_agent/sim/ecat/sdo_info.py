"""CoE SDO information service (ETG.1000.6 5.6.3), device side, pure: the object dictionary's list,
object and entry descriptions, cut into fragments that fit the mailbox.

Served only for devices whose ESI says ``SdoInfo="true"``; the others answer a mailbox error
(service not supported), as such drives do.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import Mapping

from bus_agent.sim.ecat.sii import type_code as _type_code
from bus_agent.sim.objects import ObjectEntry

SDO_INFO_SERVICE = 8
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
ABORT_INVALID_COMMAND = 0x05040001


class InfoOpcode(IntEnum):
    OD_LIST_REQ = 1
    OD_LIST_RES = 2
    OBJECT_DESC_REQ = 3
    OBJECT_DESC_RES = 4
    ENTRY_DESC_REQ = 5
    ENTRY_DESC_RES = 6
    ERROR_REQ = 7


#: object access bits: read in PRE-OP/SAFE-OP/OP (0..2), write in PRE-OP/SAFE-OP/OP (3..5),
#: RxPDO mappable (6), TxPDO mappable (7)
_ACCESS = {"ro": 0x07, "rw": 0x3F, "wo": 0x38}
OBJECT_CODE_VAR, OBJECT_CODE_ARRAY, OBJECT_CODE_RECORD = 7, 8, 9


def _bits(e: ObjectEntry, value) -> int:
    if e.datatype == "str":
        return 8 * len(str(value).encode())
    return e.bits


def _fragments(opcode: int, payload: bytes, room: int) -> list[bytes]:
    """SDO info replies (after the CoE header) carrying ``payload`` in pieces of at most ``room``
    bytes (even, so list entries never split); bit 7 of the opcode marks more to follow."""
    room -= room % 2
    pieces = [payload[k:k + room] for k in range(0, len(payload), room)] or [b""]
    out = []
    for n, piece in enumerate(pieces):
        left = len(pieces) - 1 - n
        out.append(struct.pack("<BBH", opcode | (0x80 if left else 0), 0, left) + piece)
    return out


def _error(code: int) -> list[bytes]:
    return [struct.pack("<BBHI", InfoOpcode.ERROR_REQ, 0, 0, code)]


def handle(req: bytes, objects: Mapping[tuple[int, int], ObjectEntry], values, room: int) -> list[bytes]:
    """One SDO information request (the bytes after the CoE header) -> the replies (after the CoE
    header), each at most ``room`` bytes of data behind the 4-byte info header.

    ``values(index, subindex)`` gives the current value (the length of strings)."""
    if len(req) < 4:
        return _error(ABORT_INVALID_COMMAND)
    opcode = req[0] & 0x7F
    data = req[4:]
    if opcode == InfoOpcode.OD_LIST_REQ and len(data) >= 2:
        list_type = struct.unpack_from("<H", data)[0]
        indexes = sorted({i for i, _s in objects})
        if list_type == 0:  # the number of objects in each list: all, RxPDO, TxPDO, backup, settings
            rx = {i for (i, _s), e in objects.items() if e.pdo_mappable and e.access != "ro"}
            tx = {i for (i, _s), e in objects.items() if e.pdo_mappable and e.access != "wo"}
            body = struct.pack("<6H", 0, len(indexes), len(rx), len(tx), 0, 0)
        elif list_type == 1:
            body = struct.pack(f"<H{len(indexes)}H", 1, *indexes)
        else:  # mappable-only lists and the rest: not kept apart here
            body = struct.pack("<H", list_type)
        return _fragments(InfoOpcode.OD_LIST_RES, body, room)
    if opcode == InfoOpcode.OBJECT_DESC_REQ and len(data) >= 2:
        index = struct.unpack_from("<H", data)[0]
        subs = sorted((s, e) for (i, s), e in objects.items() if i == index)
        if not subs:
            return _error(ABORT_NO_OBJECT)
        max_sub = subs[-1][0]
        head = subs[0][1]
        if max_sub == 0:
            code, dtype, name = OBJECT_CODE_VAR, _type_code(head), head.name
        else:
            same = len({_type_code(e) for s, e in subs if s > 0}) == 1
            code = OBJECT_CODE_ARRAY if same else OBJECT_CODE_RECORD
            dtype = _type_code(subs[-1][1]) if same else 0
            name = head.name.split(":")[0]
        body = struct.pack("<HHBB", index, dtype, max_sub, code) + name.encode("latin-1", "replace")
        return _fragments(InfoOpcode.OBJECT_DESC_RES, body, room)
    if opcode == InfoOpcode.ENTRY_DESC_REQ and len(data) >= 4:
        index, sub, _value_info = struct.unpack_from("<HBB", data)
        entry = objects.get((index, sub))
        if entry is None:
            return _error(ABORT_NO_SUBINDEX if any(i == index for i, _s in objects) else ABORT_NO_OBJECT)
        access = _ACCESS.get(entry.access, 0x07)
        if entry.pdo_mappable:
            access |= 0x40 if entry.access != "ro" else 0x80
        body = struct.pack("<HBBHHH", index, sub, 0, _type_code(entry), _bits(entry, values(index, sub)), access)
        name = entry.name.split(": ", 1)[-1] if (index, 1) in objects else entry.name  # a record's: the entry's
        return _fragments(InfoOpcode.ENTRY_DESC_RES, body + name.encode("latin-1", "replace"), room)
    return _error(ABORT_INVALID_COMMAND)
