"""The PDO communication objects of a simulated slave: 0x1C00 (SM types), 0x1C12/0x1C13 (PDO
assignment) and the mapping objects (ETG.1000.6 5.6.7.4), checked against the drive's catalogue
(:mod:`bus_agent.sim.ecat.profiles`): fixed PDOs, ``<Exclude>`` clashes, PRE-OP only.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import Mapping

from bus_agent.bus.base import ALState
from bus_agent.sim.drive_model import ObjectEntry, SdoAbort
from bus_agent.sim.ecat.image import BitImage
from bus_agent.sim.ecat.profiles import FLEXIBLE, PdoCatalog
from bus_agent.sim.ecat.sii import SmType


class SdoAbortCode(IntEnum):
    """SDO abort codes (CiA 301 Table 22 / ETG.1000.6 Table 41)."""

    TOGGLE = 0x05030000
    TIMEOUT = 0x05040000
    INVALID_COMMAND = 0x05040001
    UNSUPPORTED_ACCESS = 0x06010000
    WRITE_ONLY = 0x06010001
    READ_ONLY = 0x06010002
    NO_OBJECT = 0x06020000
    NOT_MAPPABLE = 0x06040041
    INCOMPATIBLE = 0x06040043
    PDO_TOO_LONG = 0x06040042
    LENGTH_MISMATCH = 0x06070010
    LENGTH_TOO_HIGH = 0x06070012
    NO_SUBINDEX = 0x06090011
    VALUE_RANGE = 0x06090030
    GENERAL = 0x08000000
    WRONG_STATE = 0x08000022


SM_COMM_TYPES = (SmType.MBX_OUT, SmType.MBX_IN, SmType.OUTPUTS, SmType.INPUTS)  # 0x1C00:1..4
MAX_PDO_BYTES = 256

_STRUCT_CODE = {"u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i"}


class PdoConfig:
    """0x1C00, 0x1C12/0x1C13 (PDO assignment) and 0x16xx/0x1Axx/0x1Bxx (PDO mapping) of one drive.

    ``objects`` is the drive's object dictionary, used to validate mapped entries; ``catalog``
    says which PDOs exist, their power-on content and what the master may change
    (:mod:`bus_agent.sim.ecat.profiles`).
    """

    def __init__(self, objects: Mapping[tuple[int, int], ObjectEntry], catalog: PdoCatalog = FLEXIBLE):
        self._objects = objects
        self.catalog = catalog
        self.reset()

    def reset(self) -> None:
        """Power-on content of the catalogue (a power cycle forgets every change)."""
        c = self.catalog
        self.assign: dict[int, list[int]] = {k: list(v) + [0] * (c.max_pdos - len(v)) for k, v in c.assign.items()}
        self.assign_count = {k: len(v) for k, v in c.assign.items()}
        self.maps: dict[int, list[int]] = {p: list(v) + [0] * (c.max_entries - len(v)) for p, v in c.maps.items()}
        self.map_count: dict[int, int] = {p: len(v) for p, v in c.maps.items()}

    def handles(self, index: int) -> bool:
        return index in (0x1C00, 0x1C12, 0x1C13) or index in self.maps

    # -- layout ---------------------------------------------------------------------------
    def layout(self, sm_assign: int) -> list[tuple[int, int, int]]:
        """(index, subindex, bits) of every entry assigned to SM2 (0x1C12) or SM3 (0x1C13)."""
        out = []
        for pdo in self.assign[sm_assign][: self.assign_count[sm_assign]]:
            for entry in self.maps[pdo][: self.map_count[pdo]]:
                out.append((entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF))
        return out

    def size_bytes(self, sm_assign: int) -> int:
        return (sum(bits for _i, _s, bits in self.layout(sm_assign)) + 7) // 8

    # -- SDO access -----------------------------------------------------------------------
    def read(self, index: int, sub: int) -> bytes:
        if index == 0x1C00:
            if sub == 0:
                return bytes([len(SM_COMM_TYPES)])
            if 1 <= sub <= len(SM_COMM_TYPES):
                return bytes([SM_COMM_TYPES[sub - 1]])
            raise SdoAbort(SdoAbortCode.NO_SUBINDEX)
        if index in self.assign:
            if sub == 0:
                return bytes([self.assign_count[index]])
            if 1 <= sub <= self.catalog.max_pdos:
                return struct.pack("<H", self.assign[index][sub - 1])
            raise SdoAbort(SdoAbortCode.NO_SUBINDEX)
        if index in self.maps:
            if sub == 0:
                return bytes([self.map_count[index]])
            if 1 <= sub <= self.catalog.max_entries:
                return struct.pack("<I", self.maps[index][sub - 1])
            raise SdoAbort(SdoAbortCode.NO_SUBINDEX)
        raise SdoAbort(SdoAbortCode.NO_OBJECT)

    def write(self, index: int, sub: int, data: bytes, al_state: ALState) -> None:
        """Download to a communication object; only in PRE-OP (ETG.1000.6 §5.6.7.4)."""
        if index == 0x1C00:
            self.read(index, sub)  # abort for a missing subindex first
            raise SdoAbort(SdoAbortCode.READ_ONLY)
        if index not in self.assign and index not in self.maps:
            raise SdoAbort(SdoAbortCode.NO_OBJECT)
        c = self.catalog
        limit = c.max_pdos if index in self.assign else c.max_entries
        if sub > limit:
            raise SdoAbort(SdoAbortCode.NO_SUBINDEX)
        if index not in c.writable_assign and index not in c.writable_maps:
            raise SdoAbort(SdoAbortCode.READ_ONLY, f"0x{index:04X} is fixed in this drive")
        size = 1 if sub == 0 else (2 if index in self.assign else 4)
        if len(data) != size:
            raise SdoAbort(SdoAbortCode.LENGTH_MISMATCH)
        if al_state != ALState.PREOP:
            raise SdoAbort(SdoAbortCode.WRONG_STATE, "PDO configuration only in PRE-OP")
        value = int.from_bytes(data, "little")
        if index in self.assign:
            self._write_assign(index, sub, value)
        else:
            self._write_map(index, sub, value)

    @staticmethod
    def _same_side(assign: int, pdo: int) -> bool:
        return 0x1600 <= pdo <= 0x17FF if assign == 0x1C12 else 0x1A00 <= pdo <= 0x1BFF

    def _excluded(self, pdos: list[int]) -> tuple[int, int] | None:
        """Two PDOs of ``pdos`` that exclude each other (ESI <Exclude>), or None."""
        ex = self.catalog.excludes
        for k, a in enumerate(pdos):
            for b in pdos[k + 1:]:
                if b in ex.get(a, ()) or a in ex.get(b, ()):
                    return a, b
        return None

    def _write_assign(self, index: int, sub: int, value: int) -> None:
        table = self.assign[index]
        if sub == 0:
            if value > self.catalog.max_pdos:
                raise SdoAbort(SdoAbortCode.VALUE_RANGE)
            if any(table[k] not in self.maps for k in range(value)):
                raise SdoAbort(SdoAbortCode.VALUE_RANGE, "assignment references no PDO")
            clash = self._excluded(table[:value])
            if clash:
                raise SdoAbort(SdoAbortCode.INCOMPATIBLE, f"PDOs 0x{clash[0]:04X} and 0x{clash[1]:04X} exclude each other")
            if sum(self._pdo_bits(table[k]) for k in range(value)) > MAX_PDO_BYTES * 8:
                raise SdoAbort(SdoAbortCode.PDO_TOO_LONG)
            self.assign_count[index] = value
            return
        if self.assign_count[index] != 0:
            raise SdoAbort(self.catalog.sub0_first_abort, "set subindex 0 to 0 before changing entries")
        if value != 0 and not (value in self.maps and self._same_side(index, value)):
            raise SdoAbort(SdoAbortCode.VALUE_RANGE, f"PDO 0x{value:04X} is not offered by this drive")
        clash = self._excluded([p for p in table[:sub - 1] if p] + [value]) if value else None
        if clash:
            raise SdoAbort(SdoAbortCode.INCOMPATIBLE, f"PDOs 0x{clash[0]:04X} and 0x{clash[1]:04X} exclude each other")
        table[sub - 1] = value

    def _pdo_bits(self, pdo: int) -> int:
        return sum(e & 0xFF for e in self.maps[pdo][: self.map_count[pdo]])

    def _write_map(self, index: int, sub: int, value: int) -> None:
        entries = self.maps[index]
        if sub == 0:
            if value > self.catalog.max_entries:
                raise SdoAbort(SdoAbortCode.VALUE_RANGE)
            if any(entries[k] == 0 for k in range(value)):
                raise SdoAbort(SdoAbortCode.NOT_MAPPABLE, "empty mapping entry")
            if sum(e & 0xFF for e in entries[:value]) > MAX_PDO_BYTES * 8:
                raise SdoAbort(SdoAbortCode.PDO_TOO_LONG)
            self.map_count[index] = value
            return
        if self.map_count[index] != 0:
            raise SdoAbort(self.catalog.sub0_first_abort, "set subindex 0 to 0 before changing entries")
        if value != 0:
            self.check_mappable(value, rx=index < 0x1A00)
        entries[sub - 1] = value

    def check_mappable(self, entry: int, rx: bool) -> None:
        """Abort unless ``entry`` names a mappable object of the right direction and size."""
        obj_index, obj_sub, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        obj = self._objects.get((obj_index, obj_sub))
        if obj is None:
            raise SdoAbort(SdoAbortCode.NO_OBJECT, f"0x{obj_index:04X}:{obj_sub} does not exist")
        if not obj.pdo_mappable or obj.datatype not in _STRUCT_CODE or bits != obj.bits:
            raise SdoAbort(SdoAbortCode.NOT_MAPPABLE)
        if rx and obj.access == "ro":
            raise SdoAbort(SdoAbortCode.NOT_MAPPABLE, "read-only object in an RxPDO")
        if not rx and obj.access == "wo":
            raise SdoAbort(SdoAbortCode.NOT_MAPPABLE, "write-only object in a TxPDO")

    def struct_for(self, sm_assign: int) -> tuple["struct.Struct | BitImage", list[tuple[int, int]]]:
        """Struct packing the assigned entries, and their (index, subindex) in order. A layout
        with padding, bit-sized entries or objects the dictionary lacks (an ESI's) gets a
        :class:`BitImage` with the same ``pack_into``/``unpack_from``."""
        layout = self.layout(sm_assign)
        objs = [self._objects.get((i, s)) for i, s, _b in layout]
        if all(o is not None and o.datatype in _STRUCT_CODE and o.bits == b == o.size * 8
               for o, (_i, _s, b) in zip(objs, layout)):
            codes = "".join(_STRUCT_CODE[o.datatype] for o in objs if o is not None)
            return struct.Struct("<" + codes), [(i, s) for i, s, _b in layout]
        signed = [o is not None and o.datatype.startswith("i") for o in objs]
        image = BitImage([(i, s, b, sg) for (i, s, b), sg in zip(layout, signed)])
        return image, image.keys
