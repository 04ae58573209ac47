"""Number, boolean and default-value formats of ESI files, as vendors write them (pure).

Numbers as ``#x1A00``, ``#X1a00``, ``0xF3F``, ``#x0x6041`` or decimal; booleans ``1``/``true``;
``DefaultData`` as little-endian hex bytes, or decimal where a vendor writes that, and 0x1C12
defaults byte-swapped by one vendor (docs/device-files.md).
"""

from __future__ import annotations

import re
import struct


class EsiError(ValueError):
    """A file that is no usable ESI, or a device that is not in it."""


_HEX_PREFIX = re.compile(r"^(#x|0x)+", re.IGNORECASE)


def parse_number(text: str | None, what: str = "number") -> int:
    """``#x1A00``, ``#X1a00``, ``0xF3F``, ``#x0x6041``, ``-5`` or ``402`` -> int."""
    if text is None:
        raise EsiError(f"{what}: missing")
    s = text.strip()
    neg = s.startswith("-")
    body = s[1:] if neg else s
    try:
        if _HEX_PREFIX.match(body):
            value = int(_HEX_PREFIX.sub("", body), 16)
        else:
            value = int(body, 10)
    except ValueError:
        raise EsiError(f"{what}: {text!r} is not a number") from None
    return -value if neg else value


def parse_bool(text: str | None, default: bool = False) -> bool:
    if text is None or not text.strip():
        return default
    return text.strip().lower() in ("1", "true")


def decode_value(kind: str, bits: int, data: bytes) -> int | float | str | bytes:
    """Little-endian ``data`` as a value of ``kind`` (see :attr:`EsiObject.kind`)."""
    if kind in ("bool", "uint"):
        return int.from_bytes(data, "little") & ((1 << bits) - 1 if bits else -1)
    if kind == "int":
        return int.from_bytes(data[: max(1, bits // 8)], "little", signed=True)
    if kind == "real":
        return struct.unpack("<f" if bits == 32 else "<d", data[: bits // 8].ljust(bits // 8, b"\0"))[0]
    if kind == "string":
        return data.rstrip(b"\0").decode("latin-1")
    return bytes(data)


def parse_default_data(text: str, nbytes: int) -> bytes:
    """``DefaultData``: little-endian hex bytes; a text that cannot be that (odd length, wrong
    length for the type, non-hex digits) is read as a decimal number, as one vendor writes it."""
    s = "".join(text.split())
    if _HEX_PREFIX.match(s):
        return parse_number(s).to_bytes(max(nbytes, 1), "little", signed=False)
    if re.fullmatch(r"[0-9A-Fa-f]*", s) and len(s) % 2 == 0 and (nbytes == 0 or len(s) == 2 * nbytes):
        return bytes.fromhex(s)
    if re.fullmatch(r"-?[0-9]+", s):
        v = int(s)
        return v.to_bytes(max(nbytes, 1), "little", signed=v < 0)
    if re.fullmatch(r"[0-9A-Fa-f]*", s) and len(s) % 2 == 0:
        return bytes.fromhex(s)
    raise EsiError(f"DefaultData {text!r} is neither hex bytes nor a decimal number")


def _fix_assign_order(index: int, sub: int, data: bytes) -> bytes:
    """0x1C12/0x1C13 entries name PDOs (0x1600..0x17FF, 0x1A00..0x1BFF): a value that is none but
    is one byte-swapped was written big-endian (``1600``), as one vendor does."""
    if index not in (0x1C12, 0x1C13) or sub == 0 or len(data) != 2:
        return data
    lo, hi = (0x1600, 0x17FF) if index == 0x1C12 else (0x1A00, 0x1BFF)
    le, be = int.from_bytes(data, "little"), int.from_bytes(data, "big")
    return data[::-1] if not lo <= le <= hi and lo <= be <= hi else data
