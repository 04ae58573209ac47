"""What one simulated CANopen node serves: the built-in drive's dictionary, or a vendor's EDS.

A :class:`NodeDictionary` splits a node's objects three ways, by who holds their values:

- ``comm``: the communication objects the node itself runs (SYNC and EMCY COB-IDs, heartbeat
  time, SYNC counter, PDO 1..4 communication and mapping), integers, reset by reset
  communication;
- ``drive``: the CiA 402 objects the drive model (:mod:`bus_agent.sim.drive_model`) holds and
  acts on;
- ``plain``: everything else an EDS lists (vendor objects, PDOs beyond 4, objects the model
  does not model): stored as SDO bytes, defaults at power-on, access as the EDS says.

An object in none of them does not exist (SDO abort 0x06020000, or 0x06090011 for a missing
subindex of an existing object). ``comm_defaults`` also holds values for communication objects
an EDS leaves out (no heartbeat, PDO not valid): the node runs on them, SDO cannot reach them.
Pure: built once per node.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from dataclasses import dataclass, field
from typing import Any, Mapping

from bus_agent.bus.canopen import cob as c
from bus_agent.devices.eds import EdsDevice, EdsError, EdsObject
from bus_agent.sim.canopen import od
from bus_agent.sim.drive_model import DriveProfile, ObjectEntry
from bus_agent.sim.drive_profiles import PROFILES

log = logging.getLogger(__name__)

Key = tuple[int, int]

#: Communication objects a node runs itself (besides PDO 1..4's 0x1400/0x1600/0x1800/0x1A00 + n).
COMM_INDEXES = frozenset({0x1005, 0x1014, 0x1017, 0x1019} | {
    base + n for base in (c.RPDO_COMM, c.RPDO_MAP, c.TPDO_COMM, c.TPDO_MAP) for n in range(c.MAX_PDOS)})
#: Objects whose value the drive model computes (an EDS default does not replace it).
#: Nor do the identity, name, mode and supported modes: the drive's profile (built from the EDS) holds them.
COMPUTED = frozenset({(0x1001, 0), (0x1018, 4), (0x603F, 0), (0x6041, 0), (0x6061, 0), (0x6064, 0), (0x606C, 0),
                      (0x6077, 0), (0x60F4, 0), (0x60FD, 0), (0x60B9, 0), (0x60BA, 0), (0x60BC, 0)})
_PROFILE_OBJECTS = frozenset({(0x1008, 0), (0x1018, 1), (0x1018, 2), (0x1018, 3), (0x6060, 0), (0x6502, 0)})
_SHORT = {8: "u8", 16: "u16", 32: "u32"}


@dataclass(frozen=True)
class NodeDictionary:
    """One node's objects by holder (module docstring) and its drive's profile."""

    source: str
    profile: DriveProfile
    comm: Mapping[Key, ObjectEntry]
    comm_defaults: Mapping[Key, int]
    drive: Mapping[Key, ObjectEntry | EdsObject]
    plain: Mapping[Key, EdsObject] = field(default_factory=dict)
    model_defaults: Mapping[Key, int | str] = field(default_factory=dict)
    od: Any = None  # python-canopen's ObjectDictionary (its SdoServer holds one)

    @functools.cached_property
    def indexes(self) -> frozenset[int]:
        return frozenset(k[0] for d in (self.comm, self.drive, self.plain) for k in d)

    def has_index(self, index: int) -> bool:
        return index in self.indexes


def builtin(node_id: int, profile: DriveProfile) -> NodeDictionary:
    """The project's simulated drive (``canopen-sim --profile``)."""
    return NodeDictionary(f"built-in {profile.name}", profile, od.COMM_OBJECTS, od.comm_defaults(node_id),
                          od.DRIVE_OBJECTS, od=od.build(node_id, profile))


def _comm_entry(o: EdsObject) -> ObjectEntry | None:
    integer = o.integer
    if integer is None or integer[1] not in _SHORT or integer[2]:
        return None
    return ObjectEntry(o.index, o.subindex, o.name, _SHORT[integer[1]], o.access, o.pdo_mappable, o.default_int(),
                       o.low, o.high)


def _same_type(o: EdsObject, model: ObjectEntry) -> bool:
    if model.datatype == "str":
        return o.bits == 0 and o.integer is None
    integer = o.integer
    return integer is not None and integer[1] == model.bits and integer[2] == model.datatype.startswith("i")


def _internal_comm(node_id: int) -> dict[Key, int]:
    """What a node runs on when its EDS leaves a communication object out."""
    values = {(0x1005, 0): c.SYNC_COB_ID, (0x1014, 0): c.EMCY_COB_BASE + node_id, (0x1017, 0): 0, (0x1019, 0): 0}
    for tx, comm, mp in ((False, c.RPDO_COMM, c.RPDO_MAP), (True, c.TPDO_COMM, c.TPDO_MAP)):
        for n in range(c.MAX_PDOS):
            values[(comm + n, 1)] = c.default_cob_id(tx, n + 1, node_id) | c.COB_ID_INVALID
            values[(comm + n, 2)] = c.TRANSMISSION_SYNC
            values[(mp + n, 0)] = 0
    return values


def from_eds(device: EdsDevice) -> NodeDictionary:
    """A node whose dictionary is ``device``'s (one node id). Raises EdsError when the drive model
    cannot run on it (no controlword 0x6040 or statusword 0x6041)."""
    where = f"EDS {device.path}"
    missing = [f"0x{i:04X}" for i in (0x6040, 0x6041) if (i, 0) not in device.objects]
    if missing:
        raise EdsError(f"{where}: not a CiA 402 drive the simulator can run: no {' and no '.join(missing)} "
                       f"(device type 0x{device.device_type:08X})")
    comm: dict[Key, ObjectEntry] = {}
    drive: dict[Key, ObjectEntry | EdsObject] = {}
    plain: dict[Key, EdsObject] = {}
    defaults: dict[Key, int | str] = {}
    for key, o in device.objects.items():
        model = od.DRIVE_OBJECTS.get(key)
        if o.index in COMM_INDEXES and (entry := _comm_entry(o)) is not None:
            comm[key] = entry
        elif model is not None and _same_type(o, model):
            drive[key] = o
            if key not in COMPUTED and o.default is not None:
                if model.datatype == "str":
                    defaults[key] = str(o.default)
                elif model.value_range()[0] <= o.default_int() <= model.value_range()[1]:
                    defaults[key] = o.default_int()
                else:
                    log.info("%s: 0x%04X:%d default %s outside the model's range %s: the model's kept", where,
                             *key, o.default, model.value_range())
        else:
            plain[key] = o
    profile_values = {k: defaults.pop(k) for k in _PROFILE_OBJECTS if k in defaults}
    comm_defaults = _internal_comm(device.node_id)
    comm_defaults.update({k: e.default for k, e in comm.items()})  # type: ignore[misc]
    modes = profile_values.get((0x6502, 0)) or PROFILES["generic"].supported_modes  # 0 or none: the model's
    mode = profile_values.get((0x6060, 0), 0)
    profile = dataclasses.replace(
        PROFILES["generic"], name=f"eds:{device.product_name or device.path}", vendor_id=device.vendor_id,
        product_code=device.product_code, revision=device.revision,
        device_name=str(profile_values.get((0x1008, 0)) or device.product_name or "EDS drive"), supported_modes=int(modes),
        power_on_mode=int(mode) if isinstance(mode, int) else 0)
    return NodeDictionary(where, profile, comm, comm_defaults, drive, plain, defaults, device.od)


def signed(entry: ObjectEntry | EdsObject) -> bool:
    """Whether an entry's integer type is signed."""
    if isinstance(entry, ObjectEntry):
        return entry.datatype.startswith("i")
    integer = entry.integer
    return bool(integer and integer[2])
