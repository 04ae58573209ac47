"""A CANopen node's PDOs (CiA 301 §7.2.2): its process image, the policies that configure it by
SDO, and the frames the cycle exchanges.

The process image is the project's :class:`~bus_agent.bus.mapping.SlaveMapping` (the EtherCAT
backend's too), built from the node's valid PDOs: RPDO n is mapping object 0x1600 + n-1, TPDO n
0x1A00 + n-1, each carried by one CAN frame under its COB-ID (``SlaveMapping.cob_ids``) and
starting on a byte of the image. One :class:`~bus_agent.bus.codec.DriveCodec` packs and unpacks
that image; :class:`PdoFrames` slices it into frames (:func:`bus_agent.bus.mapping.pdo_spans`).

Policies, with the EtherCAT backend's names (``[[can.nodes]] pdo = ...``):

- ``default`` (the default on CAN): write :data:`DEFAULT_RPDOS` / :data:`DEFAULT_TPDOS`;
- ``drive``: read and use the node's own mapping (0x1400.., 0x1600.., 0x1800.., 0x1A00..);
- ``explicit``: write the configured entries (PDO n of the list = RPDO/TPDO n);
- ``eds``: write the default mapping of the node's EDS (:func:`eds_mapping`).

(``predefined`` assigns fixed EtherCAT PDOs to sync managers; CAN has no assignment object.)
Writing follows CiA 301's order: COB-ID not valid (bit 31), mapping count 0, entries, count,
transmission type (synchronous: the cycle's SYNC drives every PDO), COB-ID valid. A PDO the
node does not have (abort 0x06020000 on its communication object) is neither read nor invalidated. Whatever the policy, the mapping is checked
before use (:func:`check_frames` and the EtherCAT backend's :func:`~bus_agent.bus.mapping.check_mapping`).
Runs before the loop (start-up, a rebooted node); takes SDO functions bound to one node, so tests
drive it against a simulated node.
"""

from __future__ import annotations

from collections import Counter
from typing import Mapping, Sequence

from bus_agent.bus.canopen.cob import (COB_ID_INVALID, COB_ID_MASK, MAX_PDO_BITS, MAX_PDOS, RPDO_COMM, RPDO_MAP,
                                       TPDO_COMM, TPDO_MAP, TRANSMISSION_SYNC, default_cob_id)
from bus_agent.bus.canopen.sdo import SdoError, SdoRead, SdoWrite, read_uint, write_uint
from bus_agent.bus.codec import DriveCodec
from bus_agent.bus.mapping import (MappingError, ObjectInfo, SlaveMapping, check_mapping, describe, mapping_of,
                                   pdo_spans)
from bus_agent.bus.pdo import DriveInputs, DriveOutputs, mapping_entry
from bus_agent.devices.eds import EdsDevice

#: The policies a CAN node takes (bus_agent.bus.mapping.POLICIES without ``predefined``, plus
#: ``eds``: the default mapping of the node's EDS).
POLICIES = ("drive", "default", "explicit", "eds")
#: SDO abort: object does not exist (a node with fewer than 4 PDOs has no 0x1403, ...).
ABORT_NO_OBJECT = 0x06020000

#: The project's layout on CAN, per PDO (u32 mapping entries): 7+6 bytes out, 7+8 bytes in.
DEFAULT_RPDOS: tuple[tuple[int, ...], ...] = (
    (mapping_entry(0x6040, 0, 16), mapping_entry(0x607A, 0, 32), mapping_entry(0x6060, 0, 8)),
    (mapping_entry(0x60FF, 0, 32), mapping_entry(0x6071, 0, 16)),
)
DEFAULT_TPDOS: tuple[tuple[int, ...], ...] = (
    (mapping_entry(0x6041, 0, 16), mapping_entry(0x6064, 0, 32), mapping_entry(0x6061, 0, 8)),
    (mapping_entry(0x606C, 0, 32), mapping_entry(0x6077, 0, 16), mapping_entry(0x603F, 0, 16)),
)


def pdos_mapping(node_id: int, rpdos: Sequence[Sequence[int]], tpdos: Sequence[Sequence[int]]) -> SlaveMapping:
    """The mapping of RPDO/TPDO 1..n (``rpdos[n-1]``: its u32 entries) with the COB-IDs of the
    pre-defined connection set. Raises MappingError for more PDOs than the set has."""
    for name, pdos in (("RPDO", rpdos), ("TPDO", tpdos)):
        if len(pdos) > MAX_PDOS:
            raise MappingError(f"{len(pdos)} {name}s, the pre-defined connection set has {name} 1..{MAX_PDOS}")
    rx = [(RPDO_MAP + n, list(e)) for n, e in enumerate(rpdos)]
    tx = [(TPDO_MAP + n, list(e)) for n, e in enumerate(tpdos)]
    cobs = ([(RPDO_MAP + n, default_cob_id(False, n + 1, node_id)) for n in range(len(rpdos))]
            + [(TPDO_MAP + n, default_cob_id(True, n + 1, node_id)) for n in range(len(tpdos))])
    return mapping_of(rx, tx, cobs)


def default_mapping(node_id: int) -> SlaveMapping:
    """:data:`DEFAULT_RPDOS` / :data:`DEFAULT_TPDOS` on PDO 1 and 2 of ``node_id``."""
    return pdos_mapping(node_id, DEFAULT_RPDOS, DEFAULT_TPDOS)


def eds_mapping(device: EdsDevice) -> SlaveMapping:
    """The default mapping of a node's EDS: its valid PDOs (COB-ID without bit 31, entries), with
    their COB-IDs (``$NODEID`` resolved; bit 30, no RTR, dropped)."""
    sides = [[p for p in device.pdos(tx) if p.valid] for tx in (False, True)]
    rx = [(RPDO_MAP + p.number - 1, list(p.entries)) for p in sides[0]]
    tx = [(TPDO_MAP + p.number - 1, list(p.entries)) for p in sides[1]]
    cobs = [((TPDO_MAP if p.tx else RPDO_MAP) + p.number - 1, p.cob_id & COB_ID_MASK) for p in sides[0] + sides[1]]
    return mapping_of(rx, tx, cobs)


#: The integer types the codec decodes by name (others go unsigned, by their size).
_CODEC_TYPES = frozenset({"u8", "i8", "u16", "i16", "u32", "i32", "u64", "i64"})


def eds_dictionary(device: EdsDevice) -> dict[tuple[int, int], ObjectInfo]:
    """Names and integer types of a node's objects from its EDS (for the codec and ``objects``)."""
    out = {}
    for key, o in device.objects.items():
        if o.integer is not None:
            short, bits, _signed = o.integer
            out[key] = ObjectInfo(o.name, short if short in _CODEC_TYPES else f"u{bits}")
    return out


def pdo_entries(m: SlaveMapping, pdo: int) -> list[int]:
    """The u32 mapping entries of one PDO (without the padding that fills it to a byte)."""
    return [mapping_entry(e.index, e.subindex, e.bits) for e in m.rx + m.tx if e.pdo == pdo and not e.padding]


def check_frames(m: SlaveMapping) -> list[str]:
    """What makes a mapping unusable on CAN (empty: usable): a PDO longer than a frame, more
    PDOs than the connection set has, a PDO without COB-ID, an object mapped twice; then what
    the cycle needs (:func:`~bus_agent.bus.mapping.check_mapping`)."""
    problems = []
    cobs = dict(m.cob_ids)
    for name, base, pdos, entries in (("RPDO", RPDO_MAP, m.rx_pdos, m.rx), ("TPDO", TPDO_MAP, m.tx_pdos, m.tx)):
        if any(not base <= p < base + MAX_PDOS for p in pdos):
            problems.append(f"{name}s: mapping objects {', '.join(f'0x{p:04X}' for p in pdos)}, "
                            f"CAN has 0x{base:04X}..0x{base + MAX_PDOS - 1:04X}")
        for pdo, _start, size in pdo_spans(entries):
            if pdo not in cobs:
                problems.append(f"{name} 0x{pdo:04X} has no COB-ID")
            if size * 8 > MAX_PDO_BITS:
                problems.append(f"{name} 0x{pdo:04X} maps {size * 8} bits, a CAN frame carries {MAX_PDO_BITS}")
        twice = [k for k, n in Counter(e.key for e in entries if not e.padding).items() if n > 1]
        problems += [f"0x{i:04X}:{s:02X} is mapped twice in the {name}s" for i, s in twice]
    return problems + check_mapping(m)


def read_mapping(sdo_read: SdoRead) -> SlaveMapping:
    """The valid PDOs of a node as it has them now (a PDO with no entries is left out)."""
    sides: list[list[tuple[int, list[int]]]] = []
    cobs: list[tuple[int, int]] = []
    for comm, mp in ((RPDO_COMM, RPDO_MAP), (TPDO_COMM, TPDO_MAP)):
        pdos = []
        for n in range(MAX_PDOS):
            try:
                cob = read_uint(sdo_read, comm + n, 1)
            except SdoError as e:
                if e.abort_code == ABORT_NO_OBJECT:
                    continue  # the node has fewer PDOs
                raise
            if cob & COB_ID_INVALID:
                continue
            entries = [read_uint(sdo_read, mp + n, i) for i in range(1, read_uint(sdo_read, mp + n, 0) + 1)]
            if entries:
                pdos.append((mp + n, entries))
                cobs.append((mp + n, cob & COB_ID_MASK))
        sides.append(pdos)
    return mapping_of(sides[0], sides[1], cobs)


def write_mapping(sdo_write: SdoWrite, m: SlaveMapping) -> None:
    """Write ``m`` (its PDOs valid and synchronous, the other PDOs of the node not valid)."""
    cobs = dict(m.cob_ids)
    for comm, mp, pdos in ((RPDO_COMM, RPDO_MAP, m.rx_pdos), (TPDO_COMM, TPDO_MAP, m.tx_pdos)):
        for n in range(MAX_PDOS):
            used = mp + n in pdos
            cob = cobs[mp + n] if used else 0
            try:
                write_uint(sdo_write, comm + n, 1, cob | COB_ID_INVALID, 32)
            except SdoError as e:
                if used or e.abort_code != ABORT_NO_OBJECT:
                    raise
            if not used:
                continue
            entries = pdo_entries(m, mp + n)
            write_uint(sdo_write, mp + n, 0, 0, 8)
            for i, entry in enumerate(entries, start=1):
                write_uint(sdo_write, mp + n, i, entry, 32)
            write_uint(sdo_write, mp + n, 0, len(entries), 8)
            write_uint(sdo_write, comm + n, 2, TRANSMISSION_SYNC, 8)
            write_uint(sdo_write, comm + n, 1, cob, 32)


def mapping_for(policy: str, node_id: int, sdo_read: SdoRead, sdo_write: SdoWrite,
                explicit: SlaveMapping | None = None) -> SlaveMapping:
    """Apply ``policy`` to one node; the mapping the cycle runs with (checked). Raises
    MappingError (naming the node, the policy and what is wrong), SdoError or SdoNoAnswer."""
    if policy == "drive":
        m = read_mapping(sdo_read)
    elif policy == "default":
        m = default_mapping(node_id)
    elif policy in ("explicit", "eds"):
        if explicit is None:
            raise MappingError(f"node {node_id}: PDO policy {policy!r} without " +
                               ("rpdo/tpdo" if policy == "explicit" else "an EDS"))
        m = explicit
    else:
        raise MappingError(f"node {node_id}: PDO policy {policy!r} is not one of {', '.join(POLICIES)}")
    problems = check_frames(m)
    if problems:
        raise MappingError(f"node {node_id}: PDO policy {policy!r}: {'; '.join(problems)} ({describe(m)})")
    if policy != "drive":
        write_mapping(sdo_write, m)
    return m


class PdoFrames:
    """One node's PDOs as CAN frames: the shared codec over its image, one slice per PDO.

    Built once per node at start-up (raises MappingError for a mapping :func:`check_frames`
    refuses). Cycle-safe: :meth:`rpdo_frames` is one encode and one slice per RPDO;
    :meth:`store_tpdo` copies a frame into the image, :meth:`decode_into` decodes it once."""

    def __init__(self, mapping: SlaveMapping, objects: Mapping[tuple[int, int], ObjectInfo] | None = None) -> None:
        problems = check_frames(mapping)
        if problems:
            raise MappingError("; ".join(problems))
        self.mapping = mapping
        self.codec = DriveCodec(mapping, objects)
        cobs = dict(mapping.cob_ids)
        self._rx = tuple((cobs[pdo], slice(start, start + size)) for pdo, start, size in pdo_spans(mapping.rx))
        self._tx = {cobs[pdo]: (slice(start, start + size), size) for pdo, start, size in pdo_spans(mapping.tx)}
        self.tpdo_cob_ids: tuple[int, ...] = tuple(self._tx)
        self.rpdo_cob_ids: tuple[int, ...] = tuple(cob for cob, _s in self._rx)
        self._image = bytearray(self.codec.in_size)
        self._stored: set[int] = set()

    def rpdo_frames(self, outputs: DriveOutputs) -> list[tuple[int, bytes]]:
        """(COB-ID, data) of every RPDO for ``outputs``."""
        image = self.codec.encode(outputs)
        return [(cob, image[span]) for cob, span in self._rx]

    def store_tpdo(self, cob_id: int, data: bytes | bytearray) -> bool:
        """Put one TPDO into the image; True when the image changed. False (nothing changes) when
        it is not one of this node's TPDOs, shorter than its mapping, or the same data again (a
        drive at rest: nothing to decode, its inputs stay; ``CanopenBus.inputs_changed``)."""
        spec = self._tx.get(cob_id)
        if spec is None:
            return False
        span, size = spec
        n = len(data)
        if n < size:
            return False
        new = data if n == size else data[:size]
        image = self._image
        if image[span] == new and cob_id in self._stored:
            return False
        image[span] = new
        self._stored.add(cob_id)  # the first frame of each TPDO is decoded even if all zero
        return True

    def decode_into(self, inputs: DriveInputs) -> None:
        """The image (the TPDOs stored so far) into ``inputs``."""
        self.codec.decode_into(inputs, self._image)
