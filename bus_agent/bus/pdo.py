"""Process data objects: the default CiA 402 mapping and the per-drive I/O records.

Shared by the master side (bus backends) and the device side (simulators), so both agree on
one layout. RxPDO = master -> drive (outputs), TxPDO = drive -> master (inputs).
Mapping entries are CoE u32 values: index << 16 | subindex << 8 | bit length (ETG.1000.6).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

# (index, subindex, bits, struct code, field name)
RXPDO_DEFAULT = (
    (0x6040, 0, 16, "H", "controlword"),
    (0x607A, 0, 32, "i", "target_position"),
    (0x60FF, 0, 32, "i", "target_velocity"),
    (0x6071, 0, 16, "h", "target_torque"),
    (0x6060, 0, 8, "b", "modes_of_operation"),
)
TXPDO_DEFAULT = (
    (0x6041, 0, 16, "H", "statusword"),
    (0x6064, 0, 32, "i", "position_actual"),
    (0x606C, 0, 32, "i", "velocity_actual"),
    (0x6077, 0, 16, "h", "torque_actual"),
    (0x6061, 0, 8, "b", "modes_of_operation_display"),
    (0x603F, 0, 16, "H", "error_code"),
)
RXPDO_INDEX = 0x1600
TXPDO_INDEX = 0x1A00

RX_STRUCT = struct.Struct("<" + "".join(e[3] for e in RXPDO_DEFAULT))  # 13 bytes
TX_STRUCT = struct.Struct("<" + "".join(e[3] for e in TXPDO_DEFAULT))  # 15 bytes


def mapping_entry(index: int, subindex: int, bits: int) -> int:
    """The u32 a 0x16xx/0x1Axx subindex holds for one mapped object."""
    return (index << 16) | (subindex << 8) | bits


@dataclass(slots=True)
class DriveOutputs:
    """RxPDO content, written by the master each cycle."""

    controlword: int = 0
    target_position: int = 0
    target_velocity: int = 0
    target_torque: int = 0
    modes_of_operation: int = 0

    def pack(self) -> bytes:
        return RX_STRUCT.pack(self.controlword, self.target_position, self.target_velocity,
                              self.target_torque, self.modes_of_operation)

    @classmethod
    def unpack(cls, data: bytes | memoryview) -> "DriveOutputs":
        return cls(*RX_STRUCT.unpack_from(data))


@dataclass(slots=True)
class DriveInputs:
    """TxPDO content, read by the master each cycle."""

    statusword: int = 0
    position_actual: int = 0
    velocity_actual: int = 0
    torque_actual: int = 0
    modes_of_operation_display: int = 0
    error_code: int = 0
    #: Other mapped input objects, in the order of the drive codec's ``extra_names``.
    extra: tuple = ()

    def pack(self) -> bytes:
        return TX_STRUCT.pack(self.statusword, self.position_actual, self.velocity_actual,
                              self.torque_actual, self.modes_of_operation_display, self.error_code)

    @classmethod
    def unpack(cls, data: bytes | memoryview) -> "DriveInputs":
        return cls(*TX_STRUCT.unpack_from(data))  # type: ignore[arg-type]
