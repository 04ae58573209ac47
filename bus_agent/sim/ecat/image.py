"""A process image of arbitrary bit layout (ESI PDOs: padding, BOOL and BITn entries, odd sizes).

Same ``pack_into``/``unpack_from`` interface as :class:`struct.Struct`, so the ESC uses either.
Used only for layouts that a struct cannot describe (bit-sized or unaligned entries); the
built-in profiles keep their structs. Both functions are generated once per layout as
straight-line code over one integer (no per-field loop per step).
"""

from __future__ import annotations

from typing import Any, Callable, Sequence


def _raw(v: Any) -> int:
    """A value as an integer (REAL and other raw entries come as bytes)."""
    return int.from_bytes(v, "little") if isinstance(v, (bytes, bytearray)) else int(v)


class BitImage:
    """Entries (index, subindex, bits, signed) packed LSB-first in order; index 0 is padding."""

    unpack_from: Callable[..., tuple[int, ...]]
    pack_into: Callable[..., None]

    def __init__(self, entries: Sequence[tuple[int, int, int, bool]]):
        self.size = (sum(b for _i, _s, b, _sg in entries) + 7) // 8
        #: (index, subindex) of the values, in order (padding left out)
        self.keys = [(i, s) for i, s, _b, _sg in entries if i]
        fields = []
        offset = 0
        for index, _sub, bits, signed in entries:
            if index:
                fields.append((offset, bits, signed))
            offset += bits
        n = self.size
        gets, puts = [], []
        for k, (off, bits, signed) in enumerate(fields):
            mask = (1 << bits) - 1
            get = f"(r >> {off}) & {mask}"
            if signed:
                get = f"((({get}) ^ {1 << (bits - 1)}) - {1 << (bits - 1)})"
            gets.append(get)
            puts.append(f"((raw(v[{k}]) & {mask}) << {off})")
        src = (f"def unpack_from(buf, offset=0):\n"
               f"    r = from_bytes(bytes(buf[offset:offset + {n}]), 'little')\n"
               f"    return ({''.join(g + ', ' for g in gets)})\n"
               f"def pack_into(buf, offset, *v):\n"
               f"    buf[offset:offset + {n}] = ({' | '.join(puts) or '0'}).to_bytes({n}, 'little')\n")
        ns: dict[str, Any] = {"from_bytes": int.from_bytes, "raw": _raw}
        exec(compile(src, "<BitImage>", "exec"), ns)
        self.unpack_from = ns["unpack_from"]
        self.pack_into = ns["pack_into"]
