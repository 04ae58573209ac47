"""EMCY: emergency messages (CiA 301 §7.2.7): decoded into an error code, register and text.

Frame on 0x080 + node id: error code u16, error register u8 (0x1001), 5 manufacturer bytes.
An error code 0x00xx is "error reset / no error". The text comes from the project's one table
of CiA 301 / CiA 402 error codes (:mod:`schemas.error_codes`), as for the EtherCAT backend's
0x603F; an unknown code is named by its class. Pure.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from bus_agent.bus.emergency import error_text

__all__ = ["EMCY_STRUCT", "Emergency", "decode", "encode", "error_text"]

EMCY_STRUCT = struct.Struct("<HB5s")


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
