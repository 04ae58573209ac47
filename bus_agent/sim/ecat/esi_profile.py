"""``ecat-sim`` slaves from ESI devices, and ESI devices from the built-in profiles.

:func:`profile_from_esi` turns an :class:`~bus_agent.devices.esi.EsiDevice` into an
:class:`~bus_agent.sim.ecat.profiles.EcatProfile`: identity and name (into the SII), the
mailbox and process SMs, every PDO (``Fixed`` = read-only mapping, ``<Exclude>``, the ``Sm``
default assignment, 0x1C12/0x1C13 writable unless the dictionary says ``ro``), the dictionary
(types, access, defaults; absent objects abort 0x06020000), the CoE flags (complete access, SDO
information) and DC (only SYNC0 op modes: OP needs SYNC0, else AL 0x0030). The CiA 402 drive
model runs on whatever the mapping holds; every other object is plain SDO data.

:func:`esi_from_profile` is the way back, for ``ecat-sim --write-esi``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Mapping

from bus_agent.devices.esi import (BASE_TYPES, INT_TYPES, CoeFlags, DcOpMode, EsiDevice, EsiEntry, EsiObject, EsiPdo, EsiSm,
                                   load_esi, parse_esi_spec, select_device)
from bus_agent.sim.drive_model import OBJECTS, ObjectEntry
from bus_agent.sim.drive_profiles import _COMMON_MODES, DriveProfile
from bus_agent.sim.ecat.profiles import ABORT_WRONG_STATE, EcatProfile, PdoCatalog
from bus_agent.sim.ecat.sii import (COE_COMPLETE_ACCESS, COE_DETAILS, COE_SDO_INFO, MAILBOX_PROTOCOL_BITS,
                                    SM_DEFAULTS, SmDefault, SmType)

#: Objects every CoE slave has (device type, identity), served from the built-in dictionary when a
#: file omits them (ESI dictionaries are documentation and some leave them out).
MANDATORY_OBJECTS = (0x1000, 0x1018)
_SM_TYPES = {"MBoxOut": SmType.MBX_OUT, "MBoxIn": SmType.MBX_IN, "Outputs": SmType.OUTPUTS, "Inputs": SmType.INPUTS}
_SM_KINDS = {v: k for k, v in _SM_TYPES.items()}
#: simulator datatype -> ESI base type (the way back)
ESI_TYPES = {"u8": "USINT", "u16": "UINT", "u32": "UDINT", "u64": "ULINT", "i8": "SINT", "i16": "INT",
             "i32": "DINT", "i64": "LINT"}
_COE_BITS = {"sdo_info": COE_SDO_INFO, "pdo_assign": 0x04, "pdo_config": 0x08, "pdo_upload": 0x10,
             "complete_access": COE_COMPLETE_ACCESS}


def object_entry(o: EsiObject) -> ObjectEntry:
    """A simulator dictionary entry from an ESI one (BOOL/BITn: a u8 of 1..7 bits; REAL, 24-bit
    and octet strings: raw bytes; STRING: text)."""
    access = o.access if o.access in ("ro", "rw", "wo") else "rw"
    kind = o.kind
    value = o.value()
    name = o.name
    if o.object_name and o.object_name != name and not name.startswith(o.object_name + ":"):
        name = f"{o.object_name}: {name}"  # a record's entry, named as the built-in ones: "object: entry"
    o = replace(o, name=name)
    if kind == "string":
        return ObjectEntry(o.index, o.subindex, o.name, "str", access, bool(o.pdo_mapping), str(value or ""))
    if kind in ("bool", "uint") and o.bits < 8:
        return ObjectEntry(o.index, o.subindex, o.name, "u8", access, bool(o.pdo_mapping), int(value or 0),
                           0, (1 << o.bits) - 1, bitsize=o.bits)
    dtype = INT_TYPES.get((kind, o.bits))
    if dtype is None:
        size = (o.bits + 7) // 8
        raw = (o.default or b"")[:size].ljust(size, b"\0")
        return ObjectEntry(o.index, o.subindex, o.name, "bytes", access, bool(o.pdo_mapping), raw, bitsize=o.bits)
    return ObjectEntry(o.index, o.subindex, o.name, dtype, access, bool(o.pdo_mapping), int(value or 0))


def _sms(dev: EsiDevice) -> tuple[SmDefault, ...]:
    """SM0..SM3 from the ESI (kinds in order MBoxOut, MBoxIn, Outputs, Inputs; an ``<Sm>``
    without kind, as `ethercat xml` writes them, by its position); a missing one takes the
    built-in drive's."""
    out = []
    for k, default in enumerate(SM_DEFAULTS):
        sm = next((s for s in dev.sms if _SM_TYPES.get(s.kind) == default.type), None)
        if sm is None and k < len(dev.sms) and not dev.sms[k].kind:
            sm = dev.sms[k]
        if sm is None:
            out.append(default)
            continue
        length = sm.default_size if k < 2 else 0  # process SMs: the mapping's size
        out.append(SmDefault(sm.start, length, sm.control or default.control, 1 if sm.enable else 0, default.type))
    return tuple(out)


def _catalog(dev: EsiDevice, objects: Mapping[tuple[int, int], EsiObject]) -> PdoCatalog:
    maps = {p.index: tuple(e.mapping for e in p.entries) for p in dev.rx_pdos + dev.tx_pdos}
    assign = {0x1C12: dev.default_assign(True), 0x1C13: dev.default_assign(False)}
    excludes: dict[int, set[int]] = {}
    for p in dev.rx_pdos + dev.tx_pdos:
        for x in p.excludes:
            excludes.setdefault(p.index, set()).add(x)
            excludes.setdefault(x, set()).add(p.index)
    writable_assign = frozenset(a for a in (0x1C12, 0x1C13)
                                if objects.get((a, 1)) is None or objects[(a, 1)].access != "ro")
    # sizes: the dictionary's mapping/assignment objects where it has them
    subs = lambda index: max((s for i, s in objects if i == index), default=0)  # noqa: E731
    max_entries = max([8] + [len(v) for v in maps.values()] + [subs(p) for p in maps])
    max_pdos = max([1, len(dev.rx_pdos), len(dev.tx_pdos), subs(0x1C12), subs(0x1C13)])
    return PdoCatalog(maps=maps, assign=assign, writable_maps=frozenset(p.index for p in dev.rx_pdos + dev.tx_pdos
                                                                        if not p.fixed),
                      writable_assign=writable_assign, sub0_first_abort=ABORT_WRONG_STATE, max_entries=max_entries,
                      max_pdos=max_pdos, excludes={k: frozenset(v) for k, v in excludes.items()})


def profile_from_esi(dev: EsiDevice, name: str | None = None) -> EcatProfile:
    """The simulated slave of one ESI device."""
    esi_objects = dev.objects
    if esi_objects:
        dictionary: dict[tuple[int, int], ObjectEntry] = {k: object_entry(o) for k, o in esi_objects.items()}
        for key, entry in OBJECTS.items():  # mandatory in every CoE slave (ETG.1000.6), whatever the file lists
            if key[0] in MANDATORY_OBJECTS and not any(i == key[0] for i, _s in esi_objects):
                dictionary[key] = entry
    else:  # a file without dictionary (e.g. from `ethercat xml`): the built-in objects
        dictionary = dict(OBJECTS)
    hidden = {}
    for p in dev.rx_pdos + dev.tx_pdos:
        for e in p.entries:
            if not e.padding and (e.index, e.subindex) not in dictionary and (e.index, e.subindex) not in OBJECTS:
                hidden[(e.index, e.subindex)] = 0
    modes = dictionary.get((0x6502, 0))
    power_on_mode = dictionary.get((0x6060, 0))
    drive = DriveProfile(
        name=dev.type_name or dev.name, vendor_id=dev.vendor_id, product_code=dev.product_code, revision=dev.revision,
        device_name=dev.name,
        supported_modes=(modes.default if modes and isinstance(modes.default, int) and modes.default else _COMMON_MODES),
        statusword_extra=0x0200, not_ready_on_power_up=False,
        power_on_mode=int(power_on_mode.default) if power_on_mode and isinstance(power_on_mode.default, int) else 0)
    coe = dev.coe or CoeFlags()
    details = 0x01 if dev.coe is not None else 0
    for attr, bit in _COE_BITS.items():
        details |= bit if getattr(coe, attr) else 0
    catalog = _catalog(dev, esi_objects)
    label = "".join(c if c.isalnum() or c in "-_." else "_" for c in dev.type_name or dev.name)  # one word
    return EcatProfile(name=name or f"esi:{label}", description=dev.label(), drive=drive,
                       pdos=catalog, dc=dev.dc_capable, dc_required=dev.dc_required, sync0_always=dev.dc_required,
                       dictionary=dictionary, hidden=hidden, sms=_sms(dev), coe_details=details,
                       sii_order=dev.type_name,
                       mailbox_protocols=sum(MAILBOX_PROTOCOL_BITS.get(p, 0) for p in set(dev.mailbox_protocols)))


def profiles_from_specs(specs: list[str]) -> list[EcatProfile]:
    """One profile per slave from ``--esi FILE[@PRODUCT[:REVISION]][*COUNT]`` arguments, in order."""
    out: list[EcatProfile] = []
    for spec in specs:
        path, product, revision, count = parse_esi_spec(spec)
        dev = select_device(load_esi(path), product, revision, path)
        out.extend([profile_from_esi(dev)] * count)
    return out


# ---------------------------------------------------------------------------------------------
# The way back: built-in profiles as ESI devices


def _esi_object(e: ObjectEntry, value, object_name: str) -> EsiObject:
    if e.datatype == "str":
        text = str(value).encode("latin-1", "replace")
        return EsiObject(e.index, e.subindex, e.name, f"STRING({max(1, len(text))})", 8 * max(1, len(text)), e.access,
                         "", text, object_name)
    if e.bitsize and e.bitsize < 8:
        base = "BOOL" if e.bitsize == 1 else f"BIT{e.bitsize}"
    else:
        base = ESI_TYPES[e.datatype]
    bits = BASE_TYPES[base][1]
    mapping = ("R" if e.access != "ro" else "T") if e.pdo_mappable else ""
    data = int(value).to_bytes((bits + 7) // 8, "little", signed=int(value) < 0)
    return EsiObject(e.index, e.subindex, e.name, base, bits, e.access, mapping, data, object_name)


def esi_from_profile(profile: EcatProfile) -> EsiDevice:
    """The ESI device of a built-in profile: what ``ecat-sim --write-esi`` writes."""
    from bus_agent.sim.drive_model import DriveModel
    from bus_agent.sim.ecat.pdo_config import SM_COMM_TYPES

    drive = profile.drive
    model = DriveModel(drive, serial=0)
    objects: dict[tuple[int, int], EsiObject] = {}
    for key, e in sorted(model.objects.items()):
        if key[0] in (0x1C12, 0x1C13) or 0x1600 <= key[0] <= 0x1BFF:
            continue  # the PDO objects follow from the catalogue below
        head = model.objects.get((key[0], 0), e)  # a record's name: its subindex 0's, before ':'
        objects[key] = _esi_object(e, model.value(*key), head.name.split(":")[0])
    objects[(0x1C00, 0)] = EsiObject(0x1C00, 0, "Number of SM types", "USINT", 8, "ro", "", bytes([4]), "Sync manager type")
    for k, t in enumerate(SM_COMM_TYPES, 1):
        objects[(0x1C00, k)] = EsiObject(0x1C00, k, f"SM{k - 1} type", "USINT", 8, "ro", "", bytes([t]),
                                         "Sync manager type")
    c = profile.pdos
    for assign in (0x1C12, 0x1C13):
        access = "rw" if assign in c.writable_assign else "ro"
        pdos = c.assign[assign]
        objects[(assign, 0)] = EsiObject(assign, 0, "Number of assigned PDOs", "USINT", 8, access, "",
                                         bytes([len(pdos)]), "PDO assign")
        for k in range(c.max_pdos):
            value = pdos[k] if k < len(pdos) else 0
            objects[(assign, k + 1)] = EsiObject(assign, k + 1, f"SubIndex {k + 1:03d}", "UINT", 16, access, "",
                                                 value.to_bytes(2, "little"), "PDO assign")
    for pdo, entries in c.maps.items():
        access = "rw" if pdo in c.writable_maps else "ro"
        objects[(pdo, 0)] = EsiObject(pdo, 0, "Number of entries", "USINT", 8, access, "", bytes([len(entries)]),
                                      f"PDO 0x{pdo:04X} mapping")
        for k in range(c.max_entries):
            value = entries[k] if k < len(entries) else 0
            objects[(pdo, k + 1)] = EsiObject(pdo, k + 1, f"SubIndex {k + 1:03d}", "UDINT", 32, access, "",
                                              value.to_bytes(4, "little"), f"PDO 0x{pdo:04X} mapping")

    def pdo_of(index: int, rx: bool, assign: int) -> EsiPdo:
        entries = []
        for m in c.maps[index]:
            i, s, b = m >> 16, (m >> 8) & 0xFF, m & 0xFF
            o = objects.get((i, s))
            entries.append(EsiEntry(i, s, b, o.name if o else "", o.datatype if o else ""))
        return EsiPdo(index=index, name=f"{'Rx' if rx else 'Tx'}PDO 0x{index:04X}", entries=tuple(entries), rx=rx,
                      sm=(2 if rx else 3) if index in c.assign[assign] else None,
                      fixed=index not in c.writable_maps, excludes=tuple(sorted(c.excludes.get(index, ()))))

    rx = tuple(pdo_of(p, True, 0x1C12) for p in sorted(c.maps) if p < 0x1A00)
    tx = tuple(pdo_of(p, False, 0x1C13) for p in sorted(c.maps) if p >= 0x1A00)
    sms = tuple(EsiSm(_SM_KINDS[d.type], d.start, d.length, d.control, bool(d.enable)) for d in profile.sms)
    dc: tuple[DcOpMode, ...] = ()
    if profile.dc:
        dc = (DcOpMode("DC", "DC-Synchron", 0x300),) + (() if profile.dc_required else (DcOpMode("SM", "SM-Synchron", 0),))
    coe = CoeFlags(**{attr: bool(COE_DETAILS & bit) for attr, bit in _COE_BITS.items()})
    return EsiDevice(vendor_id=drive.vendor_id, product_code=drive.product_code, revision=drive.revision,
                     type_name=drive.device_name, name=drive.device_name, vendor_name="zenoh-drives simulator",
                     group="Drives", profile_no=402, sms=sms, rx_pdos=rx, tx_pdos=tx, objects=objects, coe=coe,
                     mailbox_protocols=("CoE",), dc_modes=dc)


