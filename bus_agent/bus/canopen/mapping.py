"""PDO layout of a CANopen drive and its codec (CiA 301 §7.2.2, CiA 402 §9).

A CAN frame carries at most 8 bytes, so the drive's process image is split over several PDOs.
Each PDO has a communication parameter (0x1400 + n RPDO, 0x1800 + n TPDO: sub 1 COB-ID, sub 2
transmission type) and a mapping (0x1600 + n, 0x1A00 + n: sub 0 count, subs 1.. entries
``index << 16 | subindex << 8 | bits``). :data:`DEFAULT_LAYOUT` is the layout this project
writes (policy ``default``) and the simulator powers up with. :class:`Codec` is built once
from a layout at start-up and packs :class:`DriveOutputs` into RPDO frames and unpacks TPDO
frames into :class:`DriveInputs` every cycle, object by object. Pure.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from bus_agent.bus.pdo import RXPDO_DEFAULT, TXPDO_DEFAULT, DriveInputs, DriveOutputs

RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
MAX_PDOS = 4            # the pre-defined connection set has COB-IDs for PDO 1..4
MAX_PDO_BITS = 64
COB_ID_INVALID = 0x80000000  # bit 31 of sub 1: PDO does not exist / is not valid
TRANSMISSION_SYNC = 1   # synchronous, every SYNC (TPDO: sampled at the SYNC; RPDO: applied at the next)
SYNC_COB_ID = 0x080
EMCY_COB_BASE = 0x080   # + node id
SDO_TX_BASE, SDO_RX_BASE = 0x580, 0x600

Entry = tuple[int, int, int]  # (index, subindex, bits)

#: The objects a PDO may carry, by direction: name of the DriveOutputs/DriveInputs field and
#: its struct code (the single source is bus_agent.bus.pdo).
RX_OBJECTS: dict[tuple[int, int], tuple[str, str, int]] = {(i, s): (name, code, bits)
                                                           for i, s, bits, code, name in RXPDO_DEFAULT}
TX_OBJECTS: dict[tuple[int, int], tuple[str, str, int]] = {(i, s): (name, code, bits)
                                                           for i, s, bits, code, name in TXPDO_DEFAULT}


def default_cob_id(tx: bool, pdo: int, node_id: int) -> int:
    """Pre-defined connection set: TPDO n 0x180 + 0x100 (n-1) + id, RPDO n 0x200 + 0x100 (n-1) + id."""
    if not 1 <= pdo <= MAX_PDOS:
        raise ValueError(f"PDO number {pdo} outside 1..{MAX_PDOS}")
    return (0x180 if tx else 0x200) + 0x100 * (pdo - 1) + node_id


def mapping_value(entry: Entry) -> int:
    index, sub, bits = entry
    return (index << 16) | (sub << 8) | bits


def entry_of(value: int) -> Entry:
    return (value >> 16) & 0xFFFF, (value >> 8) & 0xFF, value & 0xFF


@dataclass(frozen=True)
class PdoMap:
    """One PDO: its COB-ID and mapped entries, in order."""

    cob_id: int
    entries: tuple[Entry, ...]

    @property
    def bits(self) -> int:
        return sum(e[2] for e in self.entries)


@dataclass(frozen=True)
class Layout:
    """Every valid RPDO (master -> drive) and TPDO (drive -> master) of one node."""

    rpdos: tuple[PdoMap, ...]
    tpdos: tuple[PdoMap, ...]

    def describe(self) -> str:
        def one(p: PdoMap) -> str:
            return f"0x{p.cob_id:03X}[" + ",".join(f"{i:04X}:{s}" for i, s, _b in p.entries) + "]"
        return "rpdo " + " ".join(one(p) for p in self.rpdos) + "; tpdo " + " ".join(one(p) for p in self.tpdos)


#: Entries of the default layout, per PDO number (1-based order). 7+6 bytes out, 7+8 bytes in.
DEFAULT_RPDO_ENTRIES: tuple[tuple[Entry, ...], ...] = (
    ((0x6040, 0, 16), (0x607A, 0, 32), (0x6060, 0, 8)),
    ((0x60FF, 0, 32), (0x6071, 0, 16)),
)
DEFAULT_TPDO_ENTRIES: tuple[tuple[Entry, ...], ...] = (
    ((0x6041, 0, 16), (0x6064, 0, 32), (0x6061, 0, 8)),
    ((0x606C, 0, 32), (0x6077, 0, 16), (0x603F, 0, 16)),
)


def default_layout(node_id: int) -> Layout:
    """The layout of :data:`DEFAULT_RPDO_ENTRIES` / :data:`DEFAULT_TPDO_ENTRIES` with the
    pre-defined connection set's COB-IDs."""
    return Layout(
        rpdos=tuple(PdoMap(default_cob_id(False, n + 1, node_id), e) for n, e in enumerate(DEFAULT_RPDO_ENTRIES)),
        tpdos=tuple(PdoMap(default_cob_id(True, n + 1, node_id), e) for n, e in enumerate(DEFAULT_TPDO_ENTRIES)),
    )


class LayoutError(ValueError):
    """A layout the cycle cannot use; the message names the PDO and object."""


def check_layout(layout: Layout, node_id: int) -> None:
    """Raise :class:`LayoutError` unless every PDO fits a frame, every object is one the cycle
    exchanges in that direction with the right size, no object is mapped twice, and the
    controlword and statusword are mapped."""
    for what, pdos, objects in (("RPDO", layout.rpdos, RX_OBJECTS), ("TPDO", layout.tpdos, TX_OBJECTS)):
        if len(pdos) > MAX_PDOS:
            raise LayoutError(f"node {node_id}: {len(pdos)} {what}s, at most {MAX_PDOS}")
        seen: set[tuple[int, int]] = set()
        for p in pdos:
            if p.bits > MAX_PDO_BITS:
                raise LayoutError(f"node {node_id}: {what} 0x{p.cob_id:03X} maps {p.bits} bits, a CAN frame "
                                  f"carries {MAX_PDO_BITS}")
            for index, sub, bits in p.entries:
                known = objects.get((index, sub))
                if known is None:
                    raise LayoutError(f"node {node_id}: {what} 0x{p.cob_id:03X} maps 0x{index:04X}:{sub}, "
                                      f"which the cycle does not exchange in that direction")
                if known[2] != bits:
                    raise LayoutError(f"node {node_id}: {what} 0x{p.cob_id:03X} maps 0x{index:04X}:{sub} with "
                                      f"{bits} bits, the object has {known[2]}")
                if (index, sub) in seen:
                    raise LayoutError(f"node {node_id}: 0x{index:04X}:{sub} mapped twice in the {what}s")
                seen.add((index, sub))
        must = (0x6040, 0) if what == "RPDO" else (0x6041, 0)
        if must not in seen:
            raise LayoutError(f"node {node_id}: no {what} maps 0x{must[0]:04X} "
                              f"({'controlword' if what == 'RPDO' else 'statusword'})")


class Codec:
    """Packs and unpacks one node's PDOs (built once; cycle-safe: one struct call per PDO)."""

    def __init__(self, layout: Layout, node_id: int) -> None:
        check_layout(layout, node_id)
        self.layout = layout
        self.tpdo_cob_ids = tuple(p.cob_id for p in layout.tpdos)
        self._rx = [(p.cob_id, struct.Struct("<" + "".join(RX_OBJECTS[e[:2]][1] for e in p.entries)),
                     tuple(RX_OBJECTS[e[:2]][0] for e in p.entries)) for p in layout.rpdos]
        self._tx = {p.cob_id: (struct.Struct("<" + "".join(TX_OBJECTS[e[:2]][1] for e in p.entries)),
                               tuple(TX_OBJECTS[e[:2]][0] for e in p.entries)) for p in layout.tpdos}

    def rpdo_frames(self, outputs: DriveOutputs) -> list[tuple[int, bytes]]:
        """(COB-ID, data) of every RPDO for ``outputs``."""
        return [(cob, st.pack(*(getattr(outputs, f) for f in fields))) for cob, st, fields in self._rx]

    def apply_tpdo(self, cob_id: int, data: bytes | bytearray, inputs: DriveInputs) -> bool:
        """Decode one TPDO into ``inputs``; False when the frame is not one of this node's
        TPDOs or too short (nothing changes)."""
        spec = self._tx.get(cob_id)
        if spec is None or len(data) < spec[0].size:
            return False
        for name, value in zip(spec[1], spec[0].unpack_from(data)):
            setattr(inputs, name, value)
        return True

    @staticmethod
    def outputs_from(values: dict[tuple[int, int], int]) -> DriveOutputs:
        """DriveOutputs from object values (device side, the simulator)."""
        out = DriveOutputs()
        for key, value in values.items():
            spec = RX_OBJECTS.get(key)
            if spec is not None:
                setattr(out, spec[0], value)
        return out


def decode_pdo(entries: tuple[Entry, ...], data: bytes | bytearray,
               codes: dict[tuple[int, int], tuple[str, str, int]]) -> dict[tuple[int, int], int]:
    """Object values of one PDO frame (device side: RPDO into objects)."""
    st = struct.Struct("<" + "".join(codes[e[:2]][1] for e in entries))
    return dict(zip((e[:2] for e in entries), st.unpack_from(data)))
