"""PDO mapping: the drive's own assignment -> PDOs -> entries -> bit offsets, and mapping policies.

Pure logic (no I/O): the SDO transfers are passed in as callables, so the same code reads a
drive over pysoem, over any other bus, or from a table in a test. ETG.1000.6 §5.6.7.4 (PDO
assignment 0x1C12/0x1C13 and mapping 0x16xx/0x1Axx), CiA 402 object numbers.

A mapping entry is the CoE u32 ``index << 16 | subindex << 8 | bit length``; index 0 is padding
and still takes its bits. Outputs (RxPDO, SM2) and inputs (TxPDO, SM3) each start at bit 0 of
the slave's process image and accumulate in assignment order.

The CANopen backend (bus_agent/bus/canopen) builds the same :class:`SlaveMapping` from its
PDOs (mapping objects 0x1600+n / 0x1A00+n, each carried by one CAN frame of at most 8 bytes
under the COB-ID in :attr:`SlaveMapping.cob_ids`): ``layout(..., pdo_bytes=True)`` starts every
PDO on a byte, so each frame is one slice of the process image (:func:`pdo_spans`).

Mapping policies (``[drives.mapping] policy = ...`` in the agent's TOML; on CAN ``pdo = ...``
per node, without ``predefined``):

- ``drive`` (default): read and use the drive's own mapping; refused when it lacks a required
  object (0x6040 in the outputs, 0x6041 in the inputs).
- ``default``: write the project's flexible layout (:data:`bus_agent.bus.pdo.RXPDO_DEFAULT` /
  ``TXPDO_DEFAULT``) into ``rx_pdo``/``tx_pdo`` (0x1600/0x1A00).
- ``predefined``: assign the drive's fixed PDOs ``rx = [0x1701]``, ``tx = [0x1B01]``.
- ``explicit``: write the given entries into ``rx_pdo``/``tx_pdo``.

Writes follow the order drives require: assignment sub 0 = 0, PDO sub 0 = 0, entries, PDO
sub 0 = n, assignment entries, assignment sub 0 = n; sub 0 is u8, assignment entries u16,
mapping entries u32. A write that is already what the drive holds is skipped (as IgH does), so
a drive with read-only objects works with a policy that matches it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Callable, Sequence

from bus_agent.bus.pdo import RXPDO_DEFAULT, RXPDO_INDEX, TXPDO_DEFAULT, TXPDO_INDEX, mapping_entry

RX_ASSIGN = 0x1C12
TX_ASSIGN = 0x1C13
POLICIES = ("drive", "default", "predefined", "explicit")


@dataclass(frozen=True)
class ObjectInfo:
    """A CiA 402 / CiA 301 object as mapped in PDOs: its name and CoE data type."""

    name: str
    datatype: str  # "u8","i8","u16","i16","u32","i32","u64","i64"


#: Objects the agent knows by name (CiA 402 part 2, CiA 301). Mapped objects not listed here
#: are named by index ("0x2205:01") and decoded unsigned.
OBJECTS: dict[tuple[int, int], ObjectInfo] = {
    (0x1001, 0): ObjectInfo("error_register", "u8"),
    (0x603F, 0): ObjectInfo("error_code", "u16"),
    (0x6040, 0): ObjectInfo("controlword", "u16"),
    (0x6041, 0): ObjectInfo("statusword", "u16"),
    (0x6060, 0): ObjectInfo("modes_of_operation", "i8"),
    (0x6061, 0): ObjectInfo("modes_of_operation_display", "i8"),
    (0x6062, 0): ObjectInfo("position_demand_value", "i32"),
    (0x6063, 0): ObjectInfo("position_actual_internal_value", "i32"),
    (0x6064, 0): ObjectInfo("position_actual_value", "i32"),
    (0x606B, 0): ObjectInfo("velocity_demand_value", "i32"),
    (0x606C, 0): ObjectInfo("velocity_actual_value", "i32"),
    (0x6071, 0): ObjectInfo("target_torque", "i16"),
    (0x6072, 0): ObjectInfo("max_torque", "u16"),
    (0x6074, 0): ObjectInfo("torque_demand", "i16"),
    (0x6077, 0): ObjectInfo("torque_actual_value", "i16"),
    (0x6078, 0): ObjectInfo("current_actual_value", "i16"),
    (0x607A, 0): ObjectInfo("target_position", "i32"),
    (0x607F, 0): ObjectInfo("max_profile_velocity", "u32"),
    (0x6081, 0): ObjectInfo("profile_velocity", "u32"),
    (0x6083, 0): ObjectInfo("profile_acceleration", "u32"),
    (0x6084, 0): ObjectInfo("profile_deceleration", "u32"),
    (0x60B1, 0): ObjectInfo("velocity_offset", "i32"),
    (0x60B2, 0): ObjectInfo("torque_offset", "i16"),
    (0x60B8, 0): ObjectInfo("touch_probe_function", "u16"),
    (0x60B9, 0): ObjectInfo("touch_probe_status", "u16"),
    (0x60BA, 0): ObjectInfo("touch_probe_1_positive_edge", "i32"),
    (0x60BB, 0): ObjectInfo("touch_probe_1_negative_edge", "i32"),
    (0x60BC, 0): ObjectInfo("touch_probe_2_positive_edge", "i32"),
    (0x60BD, 0): ObjectInfo("touch_probe_2_negative_edge", "i32"),
    (0x60C1, 1): ObjectInfo("interpolation_data_record", "i32"),
    (0x60F4, 0): ObjectInfo("following_error_actual_value", "i32"),
    (0x60FA, 0): ObjectInfo("control_effort", "i32"),
    (0x60FC, 0): ObjectInfo("position_demand_internal_value", "i32"),
    (0x6069, 0): ObjectInfo("velocity_sensor_actual_value", "i32"),
    (0x6079, 0): ObjectInfo("dc_link_circuit_voltage", "u32"),
    (0x60E0, 0): ObjectInfo("positive_torque_limit_value", "u16"),
    (0x60E1, 0): ObjectInfo("negative_torque_limit_value", "u16"),
    (0x60D5, 0): ObjectInfo("touch_probe_1_positive_edge_counter", "u16"),
    (0x60D6, 0): ObjectInfo("touch_probe_1_negative_edge_counter", "u16"),
    (0x60D7, 0): ObjectInfo("touch_probe_2_positive_edge_counter", "u16"),
    (0x60D8, 0): ObjectInfo("touch_probe_2_negative_edge_counter", "u16"),
    (0x60FD, 0): ObjectInfo("digital_inputs", "u32"),
    (0x60FE, 1): ObjectInfo("physical_outputs", "u32"),
    (0x60FE, 2): ObjectInfo("physical_outputs_bit_mask", "u32"),
    (0x60FF, 0): ObjectInfo("target_velocity", "i32"),
}

#: Output objects the cycle writes (RxPDO) -> DriveOutputs field.
RX_FIELDS: dict[tuple[int, int], str] = {
    (0x6040, 0): "controlword", (0x607A, 0): "target_position", (0x60FF, 0): "target_velocity",
    (0x6071, 0): "target_torque", (0x6060, 0): "modes_of_operation",
}
#: Input objects the cycle reads (TxPDO) -> DriveInputs field.
TX_FIELDS: dict[tuple[int, int], str] = {
    (0x6041, 0): "statusword", (0x6064, 0): "position_actual", (0x606C, 0): "velocity_actual",
    (0x6077, 0): "torque_actual", (0x6061, 0): "modes_of_operation_display", (0x603F, 0): "error_code",
}
#: DriveStatus field of each actual value, for the ``absent`` list.
STATUS_FIELD_OF = {(0x6064, 0): "position", (0x606C, 0): "velocity", (0x6077, 0): "torque",
                   (0x6061, 0): "mode_display", (0x603F, 0): "error_code"}

#: What to do about a refused mapping write, by SDO abort code (CiA 301 Table 22).
ABORT_HINTS: dict[int, str] = {
    0x06010002: "the drive's PDO mapping is fixed: use policy 'drive' (its own mapping) or 'predefined' "
                "(one of its fixed PDOs, see `bus-agent scan`)",
    0x06010003: "the drive refuses changes to this object: use policy 'drive' or 'predefined'",
    0x06010000: "the drive refuses this access: use policy 'drive' or 'predefined'",
    0x06020000: "the drive has no such object: check the PDO index with `bus-agent scan`",
    0x06090011: "the drive has no such subindex: fewer entries, or policy 'predefined'",
    0x06090030: "the drive does not offer this PDO or value: check the indices with `bus-agent scan`, "
                "or use policy 'drive'",
    0x06040041: "an object cannot be mapped: map other objects, or use policy 'predefined'",
    0x06040042: "the PDO would be too long: fewer entries, or policy 'predefined'",
    0x06070010: "wrong data size for the object: check the entry's bit length",
    0x08000021: "the drive is under local control: switch it to EtherCAT (fieldbus) control",
    0x08000022: "the drive accepts mapping changes only in PRE-OP",
}


def abort_hint(code: int) -> str:
    return ABORT_HINTS.get(code & 0xFFFFFFFF, "use policy 'drive' (the drive's own mapping)")


class MappingError(ValueError):
    """A mapping the agent cannot run with; the message names the slave side and what is missing."""


@dataclass(frozen=True)
class MappedEntry:
    """One mapped object: where it sits in the slave's outputs or inputs."""

    index: int
    subindex: int
    bits: int
    bit_offset: int
    pdo: int

    @property
    def key(self) -> tuple[int, int]:
        return (self.index, self.subindex)

    @property
    def padding(self) -> bool:
        return self.index == 0

    @property
    def name(self) -> str:
        return object_name(self.index, self.subindex)


def object_name(index: int, subindex: int) -> str:
    """The table name of an object, else ``0xIIII:SS``."""
    info = OBJECTS.get((index, subindex))
    return info.name if info else f"0x{index:04X}:{subindex:02X}"


def split_entry(entry: int) -> tuple[int, int, int]:
    """(index, subindex, bits) of a u32 mapping entry."""
    return entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF


@dataclass(frozen=True)
class SlaveMapping:
    """A slave's process image: the PDOs assigned to SM2/SM3 and every mapped entry with its offset."""

    rx_pdos: tuple[int, ...]
    tx_pdos: tuple[int, ...]
    rx: tuple[MappedEntry, ...]
    tx: tuple[MappedEntry, ...]
    #: CAN: (PDO mapping index, COB-ID) of every PDO; empty on EtherCAT (PDOs go by sync manager).
    cob_ids: tuple[tuple[int, int], ...] = ()

    @property
    def out_bits(self) -> int:
        return sum(e.bits for e in self.rx)

    @property
    def in_bits(self) -> int:
        return sum(e.bits for e in self.tx)

    @property
    def out_bytes(self) -> int:
        return (self.out_bits + 7) // 8

    @property
    def in_bytes(self) -> int:
        return (self.in_bits + 7) // 8

    def has_rx(self, index: int, subindex: int = 0) -> bool:
        return any(e.key == (index, subindex) for e in self.rx)

    def has_tx(self, index: int, subindex: int = 0) -> bool:
        return any(e.key == (index, subindex) for e in self.tx)


def layout(pdos: Sequence[tuple[int, Sequence[int]]], pdo_bytes: bool = False) -> tuple[MappedEntry, ...]:
    """Entries with bit offsets, in assignment order, from ``(pdo index, [u32 entries])``.
    ``pdo_bytes`` (CAN: one frame per PDO): a padding entry fills each PDO to a whole byte."""
    out = []
    offset = 0
    for pdo, entries in pdos:
        for raw in entries:
            index, sub, bits = split_entry(raw)
            out.append(MappedEntry(index, sub, bits, offset, pdo))
            offset += bits
        if pdo_bytes and offset % 8:
            out.append(MappedEntry(0, 0, 8 - offset % 8, offset, pdo))
            offset += 8 - offset % 8
    return tuple(out)


def mapping_of(rx: Sequence[tuple[int, Sequence[int]]], tx: Sequence[tuple[int, Sequence[int]]],
               cob_ids: Sequence[tuple[int, int]] = ()) -> SlaveMapping:
    """The mapping of these PDOs; with ``cob_ids`` (CAN) every PDO starts on a byte."""
    pdo_bytes = bool(cob_ids)
    return SlaveMapping(tuple(p for p, _ in rx), tuple(p for p, _ in tx), layout(rx, pdo_bytes),
                        layout(tx, pdo_bytes), tuple(cob_ids))


def pdo_spans(entries: Sequence[MappedEntry]) -> tuple[tuple[int, int, int], ...]:
    """``(pdo, first byte, byte count)`` of each PDO in the image, in order; for a layout whose
    PDOs start on a byte (``pdo_bytes``), each span is what one CAN frame carries."""
    spans: list[tuple[int, int, int]] = []
    for e in entries:
        end = (e.bit_offset + e.bits + 7) // 8
        if spans and spans[-1][0] == e.pdo:
            pdo, start, _n = spans[-1]
            spans[-1] = (pdo, start, end - start)
        else:
            spans.append((e.pdo, e.bit_offset // 8, end - e.bit_offset // 8))
    return tuple(spans)


def _default_pdo(entries: Sequence[tuple[int, int, int, str, str]]) -> list[int]:
    return [mapping_entry(i, s, b) for i, s, b, _c, _n in entries]


#: The project's flexible layout (what ``ecat-sim``'s generic drive holds at power-on).
DEFAULT_MAPPING = mapping_of([(RXPDO_INDEX, _default_pdo(RXPDO_DEFAULT))], [(TXPDO_INDEX, _default_pdo(TXPDO_DEFAULT))])

SdoRead = Callable[[int, int, int], bytes]       # (index, subindex, size) -> data
SdoWrite = Callable[[int, int, bytes], None]     # (index, subindex, data)


def read_mapping(read: SdoRead) -> SlaveMapping:
    """Read 0x1C12/0x1C13, each assigned PDO's sub 0 and its u32 entries (single-subindex
    uploads, as SOEM does without complete access). Raises whatever ``read`` raises."""
    sides = []
    for assign in (RX_ASSIGN, TX_ASSIGN):
        n = read(assign, 0, 1)[0]
        pdos = []
        for k in range(1, n + 1):
            (pdo,) = struct.unpack("<H", bytes(read(assign, k, 2))[:2])
            count = read(pdo, 0, 1)[0]
            entries = [struct.unpack("<I", bytes(read(pdo, j, 4))[:4])[0] for j in range(1, count + 1)]
            pdos.append((pdo, entries))
        sides.append(pdos)
    return mapping_of(sides[0], sides[1])


def check_mapping(m: SlaveMapping) -> list[str]:
    """What makes a mapping unusable for the cycle (empty: usable)."""
    problems = []
    if not m.has_rx(0x6040):
        problems.append("0x6040 (controlword) is not in the outputs (RxPDO)")
    if not m.has_tx(0x6041):
        problems.append("0x6041 (statusword) is not in the inputs (TxPDO)")
    for side, entries in (("outputs (RxPDO)", m.rx), ("inputs (TxPDO)", m.tx)):
        seen: set[tuple[int, int]] = set()
        for e in entries:
            if not e.padding and e.key in seen:
                problems.append(f"0x{e.index:04X}:{e.subindex:02X} is mapped twice in the {side}")
            seen.add(e.key)
    if m.has_rx(0x607A) and not m.has_tx(0x6064):
        problems.append("0x607A (target position) is mapped but 0x6064 (position actual value) is not: "
                        "the target could not be held at the actual position on enable")
    return problems


def describe(m: SlaveMapping) -> str:
    """``RxPDO 0x1701 [6040 607A 60B8 60FE:01], TxPDO 0x1B01 [...]`` for error messages; on CAN
    each PDO with its COB-ID: ``RxPDO 0x1600@0x201 [6040 607A 6060] 0x1601@0x301 [...]``."""
    def items(entries: Sequence[MappedEntry]) -> str:
        return " ".join(f"{e.index:04X}" + (f":{e.subindex:02X}" if e.subindex else "") for e in entries)

    def side(name: str, pdos: tuple[int, ...], entries: tuple[MappedEntry, ...]) -> str:
        if not cobs:
            return f"{name} {','.join(f'0x{p:04X}' for p in pdos) or 'none'} [{items(entries)}]"
        return f"{name} " + (" ".join(f"0x{p:04X}@0x{cobs.get(p, 0):03X} [{items([e for e in entries if e.pdo == p and not e.padding])}]"
                                      for p in pdos) or "none")
    cobs = dict(m.cob_ids)
    return side("RxPDO", m.rx_pdos, m.rx) + ", " + side("TxPDO", m.tx_pdos, m.tx)


# ---- policies --------------------------------------------------------------------------------


@dataclass(frozen=True)
class MappingPolicy:
    """How the agent gets a drive's process image (see the module docstring).

    ``rx``/``tx``: PDO indices (predefined). ``rx_entries``/``tx_entries``: ``(index, subindex,
    bits)`` (explicit), written into ``rx_pdo``/``tx_pdo``; ``default`` writes the project's layout
    there."""

    policy: str = "drive"
    rx: tuple[int, ...] = ()
    tx: tuple[int, ...] = ()
    rx_entries: tuple[tuple[int, int, int], ...] = ()
    tx_entries: tuple[tuple[int, int, int], ...] = ()
    rx_pdo: int = RXPDO_INDEX
    tx_pdo: int = TXPDO_INDEX

    def __post_init__(self) -> None:
        problems = validate_policy(self)
        if problems:
            raise MappingError("; ".join(problems))

    def wanted(self) -> tuple[list[tuple[int, list[int]]], list[tuple[int, list[int]]]] | None:
        """(rx pdos, tx pdos) to write as ``(pdo, [u32 entries])``; entries None-like ([]) for a
        predefined PDO (only assigned); None for ``drive`` (nothing written)."""
        if self.policy == "drive":
            return None
        if self.policy == "predefined":
            return [(p, []) for p in self.rx], [(p, []) for p in self.tx]
        if self.policy == "default":
            return ([(self.rx_pdo, _default_pdo(RXPDO_DEFAULT))], [(self.tx_pdo, _default_pdo(TXPDO_DEFAULT))])
        return ([(self.rx_pdo, [mapping_entry(*e) for e in self.rx_entries])],
                [(self.tx_pdo, [mapping_entry(*e) for e in self.tx_entries])])


def validate_policy(p: MappingPolicy) -> list[str]:
    problems = []
    if p.policy not in POLICIES:
        return [f"policy {p.policy!r} is not one of {', '.join(POLICIES)}"]
    for name, pdos, lo, hi in (("rx", p.rx, 0x1600, 0x17FF), ("tx", p.tx, 0x1A00, 0x1BFF)):
        for v in pdos:
            if not isinstance(v, int) or not lo <= v <= hi:
                problems.append(f"{name}: {v!r} is not a {'Rx' if name == 'rx' else 'Tx'}PDO index (0x{lo:04X}..0x{hi:04X})")
        if p.policy == "predefined" and not pdos:
            problems.append(f"{name}: policy 'predefined' needs at least one PDO index")
        if p.policy == "predefined" and len(pdos) > 8:
            problems.append(f"{name}: at most 8 PDOs")
    if p.policy != "predefined" and (p.rx or p.tx):
        problems.append(f"rx/tx (PDO indices) belong to policy 'predefined', not {p.policy!r}")
    if p.policy != "explicit" and (p.rx_entries or p.tx_entries):
        problems.append(f"rx_entries/tx_entries belong to policy 'explicit', not {p.policy!r}")
    if not 0x1600 <= p.rx_pdo <= 0x17FF:
        problems.append(f"rx_pdo: 0x{p.rx_pdo:04X} is not an RxPDO mapping (0x1600..0x17FF)")
    if not 0x1A00 <= p.tx_pdo <= 0x1BFF:
        problems.append(f"tx_pdo: 0x{p.tx_pdo:04X} is not a TxPDO mapping (0x1A00..0x1BFF)")
    if p.policy == "explicit":
        for name, entries in (("rx_entries", p.rx_entries), ("tx_entries", p.tx_entries)):
            if not entries:
                problems.append(f"{name}: policy 'explicit' needs at least one entry")
            for k, e in enumerate(entries):
                if (len(e) != 3 or not all(isinstance(x, int) for x in e) or not 0 <= e[0] <= 0xFFFF
                        or not 0 <= e[1] <= 0xFF or not 1 <= e[2] <= 64):
                    problems.append(f"{name}[{k}]: {e!r} must be [index 0..0xFFFF, subindex 0..255, bits 1..64]")
            if len(entries) > 254:
                problems.append(f"{name}: at most 254 entries")
    return problems


@dataclass(frozen=True)
class SdoWriteStep:
    """One SDO download of a mapping write: object, size (struct format) and value."""

    index: int
    subindex: int
    fmt: str
    value: int

    @property
    def data(self) -> bytes:
        return struct.pack(self.fmt, self.value)

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X}"


def plan_writes(policy: MappingPolicy, current: SlaveMapping) -> list[SdoWriteStep]:
    """The SDO downloads that turn ``current`` into what ``policy`` wants, in the order drives
    require; empty when the drive already holds it (nothing is written then)."""
    wanted = policy.wanted()
    if wanted is None:
        return []
    rx, tx = wanted
    cur_entries = {e.pdo: [] for e in current.rx + current.tx}  # type: dict[int, list[int]]
    for e in current.rx + current.tx:
        cur_entries[e.pdo].append(mapping_entry(e.index, e.subindex, e.bits))
    same_assign = (tuple(p for p, _ in rx) == current.rx_pdos and tuple(p for p, _ in tx) == current.tx_pdos)
    same_maps = all(not entries or cur_entries.get(p) == entries for p, entries in rx + tx)
    if same_assign and same_maps:
        return []
    steps = [SdoWriteStep(RX_ASSIGN, 0, "<B", 0), SdoWriteStep(TX_ASSIGN, 0, "<B", 0)]
    for pdo, entries in rx + tx:
        if not entries or cur_entries.get(pdo) == entries:
            continue  # a predefined PDO, or already mapped so: only assigned
        steps.append(SdoWriteStep(pdo, 0, "<B", 0))
        steps.extend(SdoWriteStep(pdo, k, "<I", v) for k, v in enumerate(entries, start=1))
        steps.append(SdoWriteStep(pdo, 0, "<B", len(entries)))
    for assign, pdos in ((RX_ASSIGN, rx), (TX_ASSIGN, tx)):
        steps.extend(SdoWriteStep(assign, k, "<H", p) for k, (p, _e) in enumerate(pdos, start=1))
        steps.append(SdoWriteStep(assign, 0, "<B", len(pdos)))
    return steps


# ---- start-up SDOs ---------------------------------------------------------------------------

#: CoE data types of start-up SDO values -> struct format.
SDO_TYPES: dict[str, str] = {"u8": "<B", "i8": "<b", "u16": "<H", "i16": "<h", "u32": "<I", "i32": "<i",
                             "u64": "<Q", "i64": "<q"}


@dataclass(frozen=True)
class StartupSdo:
    """One SDO download applied in PRE-OP before SAFE-OP (and again after a lost slave returns)."""

    index: int
    subindex: int
    type: str
    value: int

    def __post_init__(self) -> None:
        fmt = SDO_TYPES.get(self.type)
        if fmt is None:
            raise MappingError(f"type {self.type!r} is not one of {', '.join(SDO_TYPES)}")
        if not 0 <= self.index <= 0xFFFF or not 0 <= self.subindex <= 0xFF:
            raise MappingError(f"object 0x{self.index:X}:{self.subindex} outside 0..0xFFFF:0..255")
        try:
            struct.pack(fmt, self.value)
        except struct.error:
            raise MappingError(f"0x{self.index:04X}:{self.subindex:02X} value {self.value} does not fit {self.type}") from None

    @property
    def data(self) -> bytes:
        return struct.pack(SDO_TYPES[self.type], self.value)

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X} ({self.type}) = {self.value}"


@dataclass(frozen=True)
class SlaveSetup:
    """What the agent does to one slave in PRE-OP: its mapping policy, then its start-up SDOs."""

    policy: MappingPolicy = MappingPolicy()
    sdos: tuple[StartupSdo, ...] = ()
    #: DC: (SYNC0 cycle ns, shift ns) to start before OP, None = no SYNC0 (bus_agent.bus.dc)
    sync0: tuple[int, int] | None = None
    sync0_before_safeop: bool = False     # start SYNC0 in PRE-OP (drives that need it before SAFE-OP)
    #: SDOs made in SAFE-OP just before OP (the ESI's ``SO`` InitCmds, bus_agent.bus.esi_setup)
    safeop_sdos: tuple[StartupSdo, ...] = ()
    #: names and types of vendor objects (from the slave's ESI) for the codec and ``objects``
    objects: tuple[tuple[tuple[int, int], ObjectInfo], ...] = ()
