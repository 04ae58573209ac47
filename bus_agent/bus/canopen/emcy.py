"""EMCY: emergency messages (CiA 301 §7.2.7): decoded into an error code, register and text.

Frame on 0x080 + node id: error code u16, error register u8 (0x1001), 5 manufacturer bytes.
An error code 0x0000 (class 0x00xx) is "error reset / no error". The text is the most specific
entry of :data:`ERROR_TEXTS` (CiA 301 Table 21 classes, CiA 402 codes this project meets).
Pure.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

EMCY_STRUCT = struct.Struct("<HB5s")

#: (code, mask, text): the first entry with ``error_code & mask == code`` names the error.
ERROR_TEXTS: tuple[tuple[int, int, str], ...] = (
    (0x8130, 0xFFFF, "life guard error or heartbeat error"),
    (0x8611, 0xFFFF, "following error"),
    (0x2310, 0xFFFF, "continuous over current"),
    (0x3210, 0xFFFF, "DC link over-voltage"),
    (0x4310, 0xFFFF, "drive temperature too high"),
    (0x8110, 0xFFFF, "CAN overrun (objects lost)"),
    (0x8120, 0xFFFF, "CAN in error passive mode"),
    (0x8140, 0xFFFF, "recovered from bus off"),
    (0x8210, 0xFFFF, "PDO not processed due to length error"),
    (0x8250, 0xFFFF, "RPDO timeout"),
    (0x0000, 0xFF00, "error reset or no error"),
    (0x1000, 0xFF00, "generic error"),
    (0x2000, 0xF000, "current"),
    (0x3000, 0xF000, "voltage"),
    (0x4000, 0xF000, "temperature"),
    (0x5000, 0xFF00, "device hardware"),
    (0x6000, 0xF000, "device software"),
    (0x7000, 0xFF00, "additional modules"),
    (0x8100, 0xFF00, "communication"),
    (0x8200, 0xFF00, "protocol error"),
    (0x8600, 0xFF00, "positioning controller"),
    (0x8000, 0xF000, "monitoring"),
    (0x9000, 0xFF00, "external error"),
    (0xF000, 0xFF00, "additional functions"),
    (0xFF00, 0xFF00, "device specific"),
)


def error_text(code: int) -> str:
    """The meaning of an EMCY / 0x603F error code; "unknown error code 0x...." otherwise."""
    for value, mask, text in ERROR_TEXTS:
        if code & mask == value:
            return text
    return f"unknown error code 0x{code:04X}"


@dataclass(frozen=True)
class Emergency:
    """One decoded EMCY frame."""

    node_id: int
    error_code: int
    error_register: int
    data: bytes

    @property
    def reset(self) -> bool:
        return self.error_code & 0xFF00 == 0

    @property
    def text(self) -> str:
        return error_text(self.error_code)


def decode(node_id: int, data: bytes | bytearray) -> Emergency:
    """Decode an EMCY frame (shorter frames are padded with zeros, as some devices send them)."""
    raw = bytes(data[:8]).ljust(8, b"\0")
    code, register, extra = EMCY_STRUCT.unpack(raw)
    return Emergency(node_id, code, register, extra)


def encode(error_code: int, error_register: int, data: bytes = b"") -> bytes:
    """An EMCY frame's 8 bytes (device side)."""
    return EMCY_STRUCT.pack(error_code, error_register, data[:5].ljust(5, b"\0"))
