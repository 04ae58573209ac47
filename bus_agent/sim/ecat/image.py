"""A process image of arbitrary bit layout (ESI PDOs: padding, BOOL and BITn entries, odd sizes).

Same ``pack_into``/``unpack_from`` interface as :class:`struct.Struct`, so the ESC uses either.
Used only for layouts that a struct cannot describe (bit-sized or unaligned entries); the
built-in profiles keep their structs.
"""

from __future__ import annotations

from typing import Sequence


class BitImage:
    """Entries (index, subindex, bits, signed) packed LSB-first in order; index 0 is padding."""

    def __init__(self, entries: Sequence[tuple[int, int, int, bool]]):
        self.size = (sum(b for _i, _s, b, _sg in entries) + 7) // 8
        fields = []
        offset = 0
        for index, sub, bits, signed in entries:
            if index:
                fields.append((offset, bits, signed))
            offset += bits
        self._fields = tuple(fields)
        #: (index, subindex) of the values, in order (padding left out)
        self.keys = [(i, s) for i, s, _b, _sg in entries if i]

    def unpack_from(self, buf, offset: int = 0) -> tuple[int, ...]:
        raw = int.from_bytes(bytes(buf[offset: offset + self.size]), "little")
        out = []
        for off, bits, signed in self._fields:
            v = (raw >> off) & ((1 << bits) - 1)
            if signed and v >> (bits - 1):
                v -= 1 << bits
            out.append(v)
        return tuple(out)

    def pack_into(self, buf, offset: int, *values: "int | bytes") -> None:
        raw = 0
        for (off, bits, _signed), v in zip(self._fields, values):
            n = int.from_bytes(v, "little") if isinstance(v, (bytes, bytearray)) else int(v)  # REAL etc.: raw
            raw |= (n & ((1 << bits) - 1)) << off
        buf[offset: offset + self.size] = raw.to_bytes(self.size, "little")
