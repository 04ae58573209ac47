"""The simulated CiA 402 drive's object dictionary (a constant table), its CoE SDO abort codes
and the error codes it produces: the data :class:`bus_agent.sim.drive_model.DriveModel`
(and canopen-sim's object dictionary, ecat-sim's CoE) are built on. Pure data.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Mapping

from bus_agent.bus.pdo import RXPDO_DEFAULT, RXPDO_INDEX, TXPDO_DEFAULT, TXPDO_INDEX, mapping_entry

# --------------------------------------------------------------------------------------------
# CoE SDO abort codes (ETG.1000.6 Table 41 / CiA 301 Table 22)

ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_LENGTH_MISMATCH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_DEVICE_STATE = 0x08000022

SDO_ABORT_TEXT: dict[int, str] = {
    ABORT_WRITE_ONLY: "attempt to read a write only object",
    ABORT_READ_ONLY: "attempt to write a read only object",
    ABORT_NO_OBJECT: "object does not exist in the object dictionary",
    ABORT_NOT_MAPPABLE: "object cannot be mapped to the PDO",
    ABORT_LENGTH_MISMATCH: "data type does not match, length of service parameter does not match",
    ABORT_NO_SUBINDEX: "subindex does not exist",
    ABORT_VALUE_RANGE: "value range of parameter exceeded",
    ABORT_DEVICE_STATE: "data cannot be transferred because of the present device state",
}


class SdoAbort(Exception):
    """An SDO request the drive refuses; ``code`` is the u32 CoE abort code."""

    def __init__(self, code: int, message: str = "") -> None:
        self.code = code
        text = message or SDO_ABORT_TEXT.get(code, "SDO abort")
        super().__init__(f"SDO abort 0x{code:08X}: {text}")


# --------------------------------------------------------------------------------------------
# Error codes (CiA 301 Table 21 / CiA 402 error codes) the model produces

ERROR_COMMUNICATION_LOST = 0x8130   # CiA 301: life guard error or heartbeat error
ERROR_FOLLOWING_ERROR = 0x8611      # CiA 402: control, position controller, following error
ERROR_GENERIC = 0x1000              # CiA 301: generic error

# 0x1001 error register bits (CiA 301 7.5.2.2)
ERR_REG_GENERIC = 0x01
ERR_REG_CURRENT = 0x02
ERR_REG_VOLTAGE = 0x04
ERR_REG_TEMPERATURE = 0x08
ERR_REG_COMMUNICATION = 0x10
ERR_REG_PROFILE = 0x20
ERR_REG_MANUFACTURER = 0x80


def error_register_for(error_code: int) -> int:
    """0x1001 value for an active error code (bit 0 always; the class bit by the code's group)."""
    if error_code == 0:
        return 0
    reg = ERR_REG_GENERIC
    group = error_code >> 12
    if group == 0x2:
        reg |= ERR_REG_CURRENT
    elif group == 0x3:
        reg |= ERR_REG_VOLTAGE
    elif group == 0x4:
        reg |= ERR_REG_TEMPERATURE
    elif error_code >> 8 == 0x81:
        reg |= ERR_REG_COMMUNICATION
    elif group in (0x6, 0x7, 0x8, 0x9):
        reg |= ERR_REG_PROFILE
    elif error_code >> 8 == 0xFF:
        reg |= ERR_REG_MANUFACTURER
    return reg


# --------------------------------------------------------------------------------------------
# Object dictionary

_INT_FORMATS: dict[str, str] = {"u8": "<B", "i8": "<b", "u16": "<H", "i16": "<h", "u32": "<I", "i32": "<i",
                                "u64": "<Q", "i64": "<q"}
_INT_RANGES: dict[str, tuple[int, int]] = {
    "u8": (0, 0xFF), "i8": (-0x80, 0x7F), "u16": (0, 0xFFFF), "i16": (-0x8000, 0x7FFF),
    "u32": (0, 0xFFFFFFFF), "i32": (-0x80000000, 0x7FFFFFFF),
    "u64": (0, (1 << 64) - 1), "i64": (-(1 << 63), (1 << 63) - 1),
}


@dataclass(frozen=True)
class ObjectEntry:
    """One object dictionary entry: (index, subindex), type, access and PDO mappability.

    ``low``/``high`` narrow the value range the drive accepts (SDO abort 0x06090030 beyond);
    ``default`` is the power-on value (identity values come from the profile instead).
    ``bitsize`` is the size in bits where it is not the type's (BOOL and BITn entries of a
    device file: 1..8 bits in a u8; "bytes" entries: raw octets of this size).
    """

    index: int
    subindex: int
    name: str
    datatype: str           # "u8","i8","u16","i16","u32","i32","str"
    access: str             # "ro","rw","wo"
    pdo_mappable: bool
    default: int | str | bytes = 0
    low: int | None = None
    high: int | None = None
    bitsize: int = 0

    @property
    def size(self) -> int:
        """Size in bytes; 0 for "str" (variable: the length of the current value)."""
        fmt = _INT_FORMATS.get(self.datatype)
        if fmt:
            return struct.calcsize(fmt)
        return (self.bitsize + 7) // 8 if self.datatype == "bytes" else 0

    @property
    def bits(self) -> int:
        return self.bitsize or self.size * 8

    def value_range(self) -> tuple[int, int]:
        lo, hi = _INT_RANGES[self.datatype]
        return (lo if self.low is None else self.low, hi if self.high is None else self.high)


def _e(index: int, sub: int, name: str, dt: str, access: str, pdo: bool = False,
       default: int | str = 0, low: int | None = None, high: int | None = None) -> ObjectEntry:
    return ObjectEntry(index, sub, name, dt, access, pdo, default, low, high)


_MAX_MAP_ENTRIES = 8

#: The object dictionary (constant). Values live per DriveModel instance.
OBJECT_TABLE: tuple[ObjectEntry, ...] = (
    _e(0x1000, 0, "device type", "u32", "ro", default=0x00020192),
    _e(0x1001, 0, "error register", "u8", "ro", pdo=True),
    _e(0x1008, 0, "manufacturer device name", "str", "ro", default=""),
    _e(0x1018, 0, "identity: number of entries", "u8", "ro", default=4),
    _e(0x1018, 1, "vendor id", "u32", "ro"),
    _e(0x1018, 2, "product code", "u32", "ro"),
    _e(0x1018, 3, "revision number", "u32", "ro"),
    _e(0x1018, 4, "serial number", "u32", "ro"),
    # Sync manager communication types (ETG.1000.6): mailbox out/in, outputs, inputs
    _e(0x1C00, 0, "sync manager types: number", "u8", "ro", default=4),
    _e(0x1C00, 1, "SM0 type", "u8", "ro", default=1),
    _e(0x1C00, 2, "SM1 type", "u8", "ro", default=2),
    _e(0x1C00, 3, "SM2 type", "u8", "ro", default=3),
    _e(0x1C00, 4, "SM3 type", "u8", "ro", default=4),
    # PDO assignment and mapping: data only (the model always exchanges the default layout);
    # writable only while the PDO configuration is unlocked (PRE-OP), else 0x08000022.
    _e(0x1C12, 0, "RxPDO assign: number", "u8", "rw", default=1, low=0, high=1),
    _e(0x1C12, 1, "RxPDO assign 1", "u16", "rw", default=RXPDO_INDEX, low=0x1600, high=0x17FF),
    _e(0x1C13, 0, "TxPDO assign: number", "u8", "rw", default=1, low=0, high=1),
    _e(0x1C13, 1, "TxPDO assign 1", "u16", "rw", default=TXPDO_INDEX, low=0x1A00, high=0x1BFF),
    _e(RXPDO_INDEX, 0, "RxPDO mapping: number", "u8", "rw", default=len(RXPDO_DEFAULT), low=0, high=_MAX_MAP_ENTRIES),
    *(_e(RXPDO_INDEX, i + 1, f"RxPDO mapping {i + 1}", "u32", "rw",
         default=(mapping_entry(*RXPDO_DEFAULT[i][:3]) if i < len(RXPDO_DEFAULT) else 0))
      for i in range(_MAX_MAP_ENTRIES)),
    _e(TXPDO_INDEX, 0, "TxPDO mapping: number", "u8", "rw", default=len(TXPDO_DEFAULT), low=0, high=_MAX_MAP_ENTRIES),
    *(_e(TXPDO_INDEX, i + 1, f"TxPDO mapping {i + 1}", "u32", "rw",
         default=(mapping_entry(*TXPDO_DEFAULT[i][:3]) if i < len(TXPDO_DEFAULT) else 0))
      for i in range(_MAX_MAP_ENTRIES)),
    # CiA 402
    _e(0x603F, 0, "error code", "u16", "ro", pdo=True),
    _e(0x6040, 0, "controlword", "u16", "rw", pdo=True),
    _e(0x6041, 0, "statusword", "u16", "ro", pdo=True),
    _e(0x605A, 0, "quick stop option code", "i16", "rw", default=2, low=0, high=8),
    _e(0x605B, 0, "shutdown option code", "i16", "rw", default=0, low=0, high=1),
    _e(0x605C, 0, "disable operation option code", "i16", "rw", default=1, low=0, high=1),
    _e(0x605D, 0, "halt option code", "i16", "rw", default=1, low=1, high=4),
    _e(0x605E, 0, "fault reaction option code", "i16", "rw", default=2, low=0, high=4),
    _e(0x6060, 0, "modes of operation", "i8", "rw", pdo=True),
    _e(0x6061, 0, "modes of operation display", "i8", "ro", pdo=True),
    _e(0x6064, 0, "position actual value", "i32", "ro", pdo=True),
    _e(0x6065, 0, "following error window", "u32", "rw", default=10_000),
    _e(0x606C, 0, "velocity actual value", "i32", "ro", pdo=True),
    _e(0x6071, 0, "target torque", "i16", "rw", pdo=True),
    _e(0x6072, 0, "max torque", "u16", "rw", default=3000),
    _e(0x6077, 0, "torque actual value", "i16", "ro", pdo=True),
    _e(0x607A, 0, "target position", "i32", "rw", pdo=True),
    _e(0x607C, 0, "home offset", "i32", "rw"),
    _e(0x607D, 0, "software position limit: number", "u8", "ro", default=2),
    _e(0x607D, 1, "min position limit", "i32", "rw", default=-0x80000000),
    _e(0x607D, 2, "max position limit", "i32", "rw", default=0x7FFFFFFF),
    _e(0x607F, 0, "max profile velocity", "u32", "rw", default=1_000_000),
    _e(0x6081, 0, "profile velocity", "u32", "rw", pdo=True, default=100_000),
    _e(0x6083, 0, "profile acceleration", "u32", "rw", pdo=True, default=1_000_000),
    _e(0x6084, 0, "profile deceleration", "u32", "rw", pdo=True, default=1_000_000),
    _e(0x6085, 0, "quick stop deceleration", "u32", "rw", default=10_000_000),
    _e(0x6098, 0, "homing method", "i8", "rw", default=37),
    _e(0x6099, 0, "homing speeds: number", "u8", "ro", default=2),
    _e(0x6099, 1, "speed during search for switch", "u32", "rw", default=10_000),
    _e(0x6099, 2, "speed during search for zero", "u32", "rw", default=1_000),
    _e(0x609A, 0, "homing acceleration", "u32", "rw", default=100_000),
    _e(0x60B8, 0, "touch probe function", "u16", "rw", pdo=True),
    _e(0x60B9, 0, "touch probe status", "u16", "ro", pdo=True),
    _e(0x60BA, 0, "touch probe 1 positive edge", "i32", "ro", pdo=True),
    _e(0x60BC, 0, "touch probe 2 positive edge", "i32", "ro", pdo=True),
    _e(0x60F4, 0, "following error actual value", "i32", "ro", pdo=True),
    _e(0x60FD, 0, "digital inputs", "u32", "ro", pdo=True),
    _e(0x60FE, 0, "digital outputs: number", "u8", "ro", default=2),
    _e(0x60FE, 1, "physical outputs", "u32", "rw", pdo=True),
    _e(0x60FE, 2, "digital outputs bit mask", "u32", "rw"),
    _e(0x60FF, 0, "target velocity", "i32", "rw", pdo=True),
    _e(0x6502, 0, "supported drive modes", "u32", "ro"),
)

OBJECTS: Mapping[tuple[int, int], ObjectEntry] = {(e.index, e.subindex): e for e in OBJECT_TABLE}
_INDEXES = frozenset(e.index for e in OBJECT_TABLE)
_PDO_CONFIG_INDEXES = frozenset({0x1C12, 0x1C13, RXPDO_INDEX, TXPDO_INDEX})
