"""The bus interface: what the cycle needs from an EtherCAT segment (real or simulated).

Two backends implement it: ``bus_agent.bus.pysoem_bus.PysoemBus`` (a NIC or a veth end facing
``ecat-sim``) and ``bus_agent.bus.sim_bus.SimBus`` (in-process drive models, no root).
The cycle thread calls ``exchange``, ``inputs`` and ``set_outputs`` (the hot path: no allocation
beyond what it must, never blocking longer than one receive timeout); the cycle's management
thread calls ``read_al_status``, ``request_al_state`` and ``recover`` concurrently (SOEM's frame
indices make concurrent datagrams safe), each bounded to a few milliseconds. ``open``, ``start``,
the SDO calls and ``close`` run before or after the loop.

Optional hook (looked up with ``getattr``): ``inputs_changed()`` -> the positions whose inputs
changed at the last ``exchange`` (the other slaves' records hold the same values), or None when
the backend cannot tell. With it the cycle skips the drives at rest (docs/agent-cycle.md, "Fast
paths"); without it every drive is stepped every cycle.
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
    0x0020: "slave needs cold start",
    0x0021: "slave needs INIT",
    0x0022: "slave needs PRE-OP",
    0x0023: "slave needs SAFE-OP",
    0x0024: "invalid input mapping",
    0x0025: "invalid output mapping",
    0x0026: "inconsistent settings",
    0x0027: "free run not supported",
    0x0028: "synchronization not supported",
    0x0029: "free run needs 3-buffer mode",
    0x002A: "background watchdog",
    0x002B: "no valid inputs and outputs",
    0x002C: "fatal sync error",
    0x002D: "no sync error",
    0x002E: "cycle time too small",
    0x0030: "invalid DC SYNC configuration",
    0x0031: "invalid DC latch configuration",
    0x0032: "PLL error",
    0x0033: "DC sync IO error",
    0x0034: "DC sync timeout error",
    0x0035: "DC invalid sync cycle time",
}

#: What usually causes a sync or mapping AL status code, and what to do (vendor manuals,
#: SOEM/pysoem/ethercat_driver_ros2 reports).
AL_STATUS_HINTS = {
    0x001A: "the drive lost synchronisation: SYNC0 not running or process data not in step with it "
            "([dc] mode = \"auto\"; keep the cycle free of stalls)",
    0x001B: "outputs stopped arriving within the SM watchdog time (the master stalled or stopped)",
    0x001D: "the output SM length does not match the drive's RxPDO mapping (mapping policy, PDO sizes)",
    0x001E: "the input SM length does not match the drive's TxPDO mapping (mapping policy, PDO sizes)",
    0x0024: "the drive refuses the TxPDO mapping: use mapping policy 'drive' or one of its predefined PDOs",
    0x0025: "the drive refuses the RxPDO mapping: use mapping policy 'drive' or one of its predefined PDOs",
    0x0028: "the drive needs DC SYNC0 in this mode: [dc] mode = \"auto\" (SYNC0 before OP)",
    0x002C: "SYNC0/SYNC1 settings the drive cannot run: check [dc] sync0_cycle_ns/shift",
    0x002D: "no SYNC0 received: enable DC ([dc] mode = \"auto\"), or start SYNC0 before SAFE-OP "
            "([dc] before_safeop = true)",
    0x0030: "the drive needs DC SYNC0 in cyclic synchronous modes (8/9/10): [dc] mode = \"auto\", "
            "or a free-run mode (1/3/4)",
    0x0035: "the drive does not accept this SYNC0 cycle time: choose cycle_us / [dc] sync0_cycle_ns it supports",
}


def al_status_text(code: int) -> str:
    """The AL status code's meaning (ETG.1000.6 Table 11), with a hint for sync and mapping codes."""
    text = AL_STATUS_CODES.get(code, f"unknown AL status code 0x{code:04X}")
    hint = AL_STATUS_HINTS.get(code)
    return f"{text} ({hint})" if hint else text


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


class NoAnswer(BusError):
    """A transfer that got no answer in time: the answer may have been lost, so it may be made
    again. Every other BusError of a transfer is the slave's definite answer (an SDO abort, a
    mailbox error, a slave without CoE): made again, it gets the same answer."""


class Bus(Protocol):
    """An EtherCAT segment of CiA 402 drives, one per slave position."""

    backend: str  # "pysoem" or "sim"
    #: An exchange between two cycles is harmless (EtherCAT: one more frame; a drive latches
    #: outputs at SM2 or SYNC0 either way), so the cycle may send a group reflex in an express
    #: exchange (docs/agent-cycle.md, Timing). False on CANopen: every exchange sends a SYNC,
    #: which every node takes as a cycle of its own. Read with ``getattr(bus, ..., False)``.
    express_exchange: bool

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
