"""The object dictionary of a simulated CANopen drive: CiA 301 communication objects plus the
drive model's objects (bus_agent.sim.drive_model.OBJECT_TABLE), as python-canopen's
``ObjectDictionary`` for its SDO server and as an EDS file (``canopen-sim --write-eds``).

The EtherCAT-only objects of the model (sync manager types and assignment 0x1C00-0x1C13, and its
single 13/15-byte PDO mappings 0x1600/0x1A00) are replaced by CANopen's PDO communication and
mapping objects (0x1400/0x1600/0x1800/0x1A00 + n, n = 0..3, at most 8 bytes per PDO).
"""

from __future__ import annotations

import canopen
from canopen import objectdictionary as odm

from bus_agent.bus.canopen import cob as c
from bus_agent.bus.canopen.pdo import DEFAULT_RPDOS, DEFAULT_TPDOS
from bus_agent.sim.drive_model import OBJECT_TABLE, DriveProfile, ObjectEntry, _e

_DATATYPES = {"u8": odm.UNSIGNED8, "i8": odm.INTEGER8, "u16": odm.UNSIGNED16, "i16": odm.INTEGER16,
              "u32": odm.UNSIGNED32, "i32": odm.INTEGER32, "str": odm.VISIBLE_STRING}
_EXCLUDED = frozenset({0x1C00, 0x1C12, 0x1C13, 0x1600, 0x1A00})
MAX_MAP_ENTRIES = 8
DEFAULT_HEARTBEAT_MS = 100

#: Defaults that depend on the node id are filled in by :func:`comm_defaults`.
COMM_TABLE: tuple[ObjectEntry, ...] = (
    _e(0x1005, 0, "COB-ID SYNC", "u32", "rw", default=c.SYNC_COB_ID),
    _e(0x1014, 0, "COB-ID EMCY", "u32", "ro"),
    _e(0x1017, 0, "producer heartbeat time", "u16", "rw", default=DEFAULT_HEARTBEAT_MS),
    _e(0x1019, 0, "synchronous counter overflow value", "u8", "rw", default=0),
    *(x for n in range(c.MAX_PDOS) for x in (
        _e(c.RPDO_COMM + n, 0, f"RPDO{n + 1} communication: highest sub", "u8", "ro", default=2),
        _e(c.RPDO_COMM + n, 1, f"RPDO{n + 1} COB-ID", "u32", "rw"),
        _e(c.RPDO_COMM + n, 2, f"RPDO{n + 1} transmission type", "u8", "rw", default=c.TRANSMISSION_SYNC),
        _e(c.RPDO_MAP + n, 0, f"RPDO{n + 1} mapping: number", "u8", "rw", low=0, high=MAX_MAP_ENTRIES),
        *(_e(c.RPDO_MAP + n, i, f"RPDO{n + 1} mapping {i}", "u32", "rw") for i in range(1, MAX_MAP_ENTRIES + 1)),
        _e(c.TPDO_COMM + n, 0, f"TPDO{n + 1} communication: highest sub", "u8", "ro", default=2),
        _e(c.TPDO_COMM + n, 1, f"TPDO{n + 1} COB-ID", "u32", "rw"),
        _e(c.TPDO_COMM + n, 2, f"TPDO{n + 1} transmission type", "u8", "rw", default=c.TRANSMISSION_SYNC),
        _e(c.TPDO_MAP + n, 0, f"TPDO{n + 1} mapping: number", "u8", "rw", low=0, high=MAX_MAP_ENTRIES),
        *(_e(c.TPDO_MAP + n, i, f"TPDO{n + 1} mapping {i}", "u32", "rw") for i in range(1, MAX_MAP_ENTRIES + 1)),
    )),
)
COMM_OBJECTS: dict[tuple[int, int], ObjectEntry] = {(e.index, e.subindex): e for e in COMM_TABLE}
DRIVE_OBJECTS: dict[tuple[int, int], ObjectEntry] = {(e.index, e.subindex): e for e in OBJECT_TABLE
                                                     if e.index not in _EXCLUDED}


def comm_defaults(node_id: int) -> dict[tuple[int, int], int]:
    """Power-on / reset-communication values of the communication objects of ``node_id``:
    the project's layout (bus_agent.bus.canopen.pdo) on PDO 1 and 2, PDO 3 and 4 invalid."""
    values = {k: int(e.default) for k, e in COMM_OBJECTS.items()}
    values[(0x1014, 0)] = c.EMCY_COB_BASE + node_id
    for tx, comm, mp, defaults in ((False, c.RPDO_COMM, c.RPDO_MAP, DEFAULT_RPDOS),
                                   (True, c.TPDO_COMM, c.TPDO_MAP, DEFAULT_TPDOS)):
        for n in range(c.MAX_PDOS):
            cob = c.default_cob_id(tx, n + 1, node_id)
            entries = defaults[n] if n < len(defaults) else ()
            values[(comm + n, 1)] = cob if entries else cob | c.COB_ID_INVALID
            values[(mp + n, 0)] = len(entries)
            for i, e in enumerate(entries, start=1):
                values[(mp + n, i)] = e
    return values


def _node_relative(key: tuple[int, int], value: int, node_id: int) -> str | None:
    """``$NODEID+0x...`` for the COB-IDs of the pre-defined connection set (so the EDS fits any
    node id), else None."""
    index, sub = key
    if key == (0x1014, 0) or (sub == 1 and (c.RPDO_COMM <= index < c.RPDO_COMM + c.MAX_PDOS
                                            or c.TPDO_COMM <= index < c.TPDO_COMM + c.MAX_PDOS)):
        return f"$NODEID+0x{value - node_id:X}"
    return None


def build(node_id: int, profile: DriveProfile) -> canopen.ObjectDictionary:
    """python-canopen's object dictionary of one simulated node (no values: the node's read
    and write callbacks serve them), with the defaults the node powers on with: identity from
    the profile, node-id-relative COB-IDs as ``$NODEID`` expressions."""
    od = canopen.ObjectDictionary()
    od.node_id = node_id
    info = od.device_information
    info.product_name = profile.device_name
    info.vendor_number, info.product_number, info.revision_number = (profile.vendor_id, profile.product_code,
                                                                     profile.revision)
    records: dict[int, odm.ODRecord] = {}
    entries = sorted({**DRIVE_OBJECTS, **COMM_OBJECTS}.values(), key=lambda e: (e.index, e.subindex))
    multi = {e.index for e in entries if e.subindex > 0}
    defaults: dict[tuple[int, int], int | str] = {
        **comm_defaults(node_id), (0x1008, 0): profile.device_name, (0x1018, 1): profile.vendor_id,
        (0x1018, 2): profile.product_code, (0x1018, 3): profile.revision, (0x6502, 0): profile.supported_modes,
        (0x6060, 0): profile.power_on_mode, (0x6061, 0): profile.power_on_mode}
    for e in entries:
        var = odm.ODVariable(e.name, e.index, e.subindex)
        var.data_type = _DATATYPES[e.datatype]
        var.access_type = e.access
        default = defaults.get((e.index, e.subindex), e.default)
        var.default = default  # type: ignore[assignment]  # str for VISIBLE_STRING
        relative = _node_relative((e.index, e.subindex), int(default), node_id) if isinstance(default, int) else None
        if relative is not None:
            var.default_raw = relative  # type: ignore[attr-defined]  # python-canopen's EDS exporter reads it
        var.pdo_mappable = e.pdo_mappable
        if e.index in multi:
            rec = records.get(e.index)
            if rec is None:
                rec = records[e.index] = odm.ODRecord(e.name.split(":")[0], e.index)
                od.add_object(rec)
            rec.add_member(var)
        else:
            od.add_object(var)
    return od


def write_eds(path: str, profile: DriveProfile) -> None:
    """Write the simulated drive's EDS (what ``canopen-sim --eds`` runs and ``bus-agent`` may
    load per node): every object with its type, access, PDO mappability and default."""
    odm.export_od(build(1, profile), path, doc_type="eds")
