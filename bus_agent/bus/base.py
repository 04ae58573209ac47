"""The bus interface: what the cycle needs from an EtherCAT segment (real or simulated).

Two backends implement it: ``bus_agent.bus.pysoem_bus.PysoemBus`` (a NIC or a veth end facing
``ecat-sim``) and ``bus_agent.bus.sim_bus.SimBus`` (in-process drive models, no root).
The cycle thread calls ``exchange``, ``inputs`` and ``set_outputs`` (the hot path: no allocation
beyond what it must, never blocking longer than one receive timeout); the cycle's management
thread calls ``read_al_status``, ``request_al_state`` and ``recover`` concurrently (SOEM's frame
indices make concurrent datagrams safe), each bounded to a few milliseconds. ``open``, ``start``,
the SDO calls and ``close`` run before or after the loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Mapping, Protocol, Sequence

from bus_agent.bus.pdo import DriveInputs, DriveOutputs


class ALState(IntEnum):
    """EtherCAT application-layer states, register 0x0120/0x0130 (ETG.1000.6 Table 9)."""

    NONE = 0
    INIT = 1
    PREOP = 2
    BOOT = 3
    SAFEOP = 4
    OP = 8

    @property
    def wire_name(self) -> str:
        return {0: "none", 1: "init", 2: "preop", 3: "boot", 4: "safeop", 8: "op"}[int(self)]


AL_ERROR_FLAG = 0x10

#: AL status codes (register 0x0134), ETG.1000.6 Table 11 (the ones this project meets).
AL_STATUS_CODES = {
    0x0000: "no error",
    0x0001: "unspecified error",
    0x0011: "invalid requested state change",
    0x0012: "unknown requested state",
    0x0013: "bootstrap not supported",
    0x0014: "no valid firmware",
    0x0016: "invalid mailbox configuration",
    0x0017: "invalid sync manager configuration",
    0x0018: "no valid inputs available",
    0x0019: "no valid outputs",
    0x001A: "synchronization error",
    0x001B: "sync manager watchdog",
    0x001D: "invalid output configuration",
    0x001E: "invalid input configuration",
    0x001F: "invalid watchdog configuration",
}


def al_status_text(code: int) -> str:
    return AL_STATUS_CODES.get(code, f"unknown AL status code 0x{code:04X}")


@dataclass(frozen=True)
class SlaveIdentity:
    """0x1018 identity as read from the SII / CoE."""

    vendor_id: int
    product_code: int
    revision: int = 0
    serial: int = 0


@dataclass(frozen=True)
class SlaveInfo:
    position: int  # 0-based position on the segment
    name: str
    identity: SlaveIdentity


@dataclass(frozen=True)
class SlaveALStatus:
    state: ALState
    error: bool
    status_code: int


class BusError(RuntimeError):
    """Start-up or management failure; the message names the slave and the AL status code."""


class Bus(Protocol):
    """An EtherCAT segment of CiA 402 drives, one per slave position."""

    backend: str  # "pysoem" or "sim"

    def open(self) -> list[SlaveInfo]:
        """Find and identify the slaves (INIT -> PRE-OP). Raises BusError."""

    def start(self, mapping_override: Mapping[int, object] | None = None) -> int:
        """Map PDOs and bring every slave to OP (SAFE-OP then OP, each with a deadline).
        Returns the expected working counter. Raises BusError naming slave and AL code."""

    @property
    def expected_wkc(self) -> int: ...

    def exchange(self) -> int:
        """Send outputs, receive inputs: one process-data cycle. Returns the working counter
        (negative or 0 if nothing came back). Cycle-safe."""

    def inputs(self, position: int) -> DriveInputs:
        """Last received TxPDO of the slave at ``position``. Cycle-safe."""

    def set_outputs(self, position: int, outputs: DriveOutputs) -> None:
        """RxPDO to send at the next exchange. Cycle-safe."""

    def read_al_status(self) -> Sequence[SlaveALStatus]:
        """AL status of every slave (one management round trip; call every N cycles or on a WKC error)."""

    def request_al_state(self, position: int | None, state: ALState) -> None:
        """Request an AL state for one slave or all (None); does not wait. Acks an error flag."""

    def recover(self, position: int) -> bool:
        """Try to bring a lost or fallen slave back to OP (reconfigure if it was reset).
        Returns True when it is back in OP. Must not take longer than a few cycles per call."""

    def sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes: ...

    def sdo_write(self, position: int, index: int, subindex: int, data: bytes) -> None: ...

    def close(self) -> None:
        """All slaves to INIT, release the NIC. Idempotent."""
