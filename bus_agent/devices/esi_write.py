"""Writing ESI files (ETG.2000) from :class:`~bus_agent.devices.esi.EsiDevice` descriptions.

The writer emits the schema's own forms (``#x`` hex, little-endian ``DefaultData``, one
DataType per record), so :func:`bus_agent.devices.esi.parse_esi` reads back what it wrote.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Sequence
from xml.etree.ElementTree import Element, SubElement, indent, tostring

from bus_agent.devices.esi import BASE_TYPES, EsiDevice, EsiObject, EsiPdo


def _hex(value: int, digits: int = 4) -> str:
    return f"#x{value:0{digits}X}"


def _add(parent: Element, tag: str, text: str | None = None, **attrs: str | None) -> Element:
    el = SubElement(parent, tag, {k: v for k, v in attrs.items() if v is not None})
    if text is not None:
        el.text = text
    return el


def _flags(parent: Element, o: EsiObject) -> None:
    flags = _add(parent, "Flags")
    _add(flags, "Access", o.access)
    if o.pdo_mapping:
        _add(flags, "PdoMapping", o.pdo_mapping)


def _dictionary(profile: Element, dev: EsiDevice) -> None:
    by_index: dict[int, list[EsiObject]] = defaultdict(list)
    for (index, _sub), o in sorted(dev.objects.items()):
        by_index[index].append(o)
    dictionary = _add(profile, "Dictionary")
    types = _add(dictionary, "DataTypes")
    objects = _add(dictionary, "Objects")
    used: set[str] = set()
    for index, subs in by_index.items():
        obj = _add(objects, "Object")
        _add(obj, "Index", _hex(index))
        first = subs[0]
        record = len(subs) > 1 or first.subindex != 0
        if not record:
            _add(obj, "Name", first.object_name or first.name)
            _add(obj, "Type", first.datatype)
            _add(obj, "BitSize", str(first.bits))
            if first.default is not None:
                _add(_add(obj, "Info"), "DefaultData", first.default.hex().upper())
            _flags(obj, first)
            used.add(first.datatype)
            continue
        tname = f"DT{index:04X}"
        dt = _add(types, "DataType")
        _add(dt, "Name", tname)
        offset = 0
        items = []
        for o in subs:
            si = SubElement(dt, "SubItem")
            _add(si, "SubIdx", str(o.subindex))
            _add(si, "Name", o.name)
            _add(si, "Type", o.datatype)
            _add(si, "BitSize", str(o.bits))
            _add(si, "BitOffs", str(offset))
            _flags(si, o)
            used.add(o.datatype)
            offset += 16 if o.subindex == 0 else o.bits  # subindex 0 is padded to 16 bits
            items.append(o)
        dt.insert(1, _make("BitSize", str(offset)))
        _add(obj, "Name", first.object_name or first.name)
        _add(obj, "Type", tname)
        _add(obj, "BitSize", str(offset))
        info = _add(obj, "Info")
        for o in items:
            si = _add(info, "SubItem")
            _add(si, "Name", o.name)
            if o.default is not None:
                _add(_add(si, "Info"), "DefaultData", o.default.hex().upper())
        flags = _add(obj, "Flags")
        _add(flags, "Access", "ro")
    for name in sorted(used):
        dt = Element("DataType")
        _add(dt, "Name", name)
        _add(dt, "BitSize", str(BASE_TYPES[name][1] if name in BASE_TYPES else int(name[7:-1]) * 8))
        types.insert(0, dt)


def _make(tag: str, text: str) -> Element:
    el = Element(tag)
    el.text = text
    return el


def _pdo(parent: Element, p: EsiPdo) -> None:
    attrs = {"Fixed": "1" if p.fixed else "0", "Mandatory": "1" if p.mandatory else None,
             "Sm": str(p.sm) if p.sm is not None else None}
    el = _add(parent, "RxPdo" if p.rx else "TxPdo", **attrs)
    _add(el, "Index", _hex(p.index))
    _add(el, "Name", p.name)
    for x in p.excludes:
        _add(el, "Exclude", _hex(x))
    for e in p.entries:
        entry = _add(el, "Entry")
        _add(entry, "Index", _hex(e.index))
        if not e.padding:
            _add(entry, "SubIndex", str(e.subindex))
        _add(entry, "BitLen", str(e.bits))
        if not e.padding:
            _add(entry, "Name", e.name)
            _add(entry, "DataType", e.datatype)


def write_esi(devices: Sequence[EsiDevice]) -> bytes:
    """One ESI file (UTF-8) describing ``devices`` (all of one vendor)."""
    root = Element("EtherCATInfo", {"Version": "1.6"})
    vendor = _add(root, "Vendor")
    _add(vendor, "Id", _hex(devices[0].vendor_id, 8))
    _add(vendor, "Name", devices[0].vendor_name or "unknown")
    desc = _add(root, "Descriptions")
    groups = _add(desc, "Groups")
    for g in sorted({d.group or "Drives" for d in devices}):
        group = _add(groups, "Group")
        _add(group, "Type", g)
        _add(group, "Name", g, LcId="1033")
    devs = _add(desc, "Devices")
    for d in devices:
        dev = _add(devs, "Device", Physics="YY")
        _add(dev, "Type", d.type_name, ProductCode=_hex(d.product_code, 8), RevisionNo=_hex(d.revision, 8))
        _add(dev, "Name", d.name, LcId="1033")
        _add(dev, "GroupType", d.group or "Drives")
        profile = _add(dev, "Profile")
        if d.profile_no is not None:
            _add(profile, "ProfileNo", str(d.profile_no))
        if d.objects:
            _dictionary(profile, d)
        for fmmu in ("Outputs", "Inputs", "MBoxState"):
            _add(dev, "Fmmu", fmmu)
        for sm in d.sms:
            _add(dev, "Sm", sm.kind, DefaultSize=str(sm.default_size) if sm.default_size else None,
                 StartAddress=_hex(sm.start), ControlByte=_hex(sm.control, 2), Enable="1" if sm.enable else "0")
        for p in d.rx_pdos + d.tx_pdos:
            _pdo(dev, p)
        mailbox = _add(dev, "Mailbox", DataLinkLayer="true")
        if d.coe is not None:
            c = d.coe
            coe = _add(mailbox, "CoE", SdoInfo=str(c.sdo_info).lower(), PdoAssign=str(c.pdo_assign).lower(),
                       PdoConfig=str(c.pdo_config).lower(), CompleteAccess=str(c.complete_access).lower(),
                       PdoUpload=str(c.pdo_upload).lower())
            for cmd in d.init_cmds:
                ic = _add(coe, "InitCmd", CompleteAccess="1" if cmd.complete_access else None)
                for t in cmd.transitions:
                    _add(ic, "Transition", t)
                _add(ic, "Index", _hex(cmd.index))
                _add(ic, "SubIndex", str(cmd.subindex))
                _add(ic, "Data", cmd.data.hex().upper())
                if cmd.comment:
                    _add(ic, "Comment", cmd.comment)
        if d.dc_modes:
            dc = _add(dev, "Dc")
            for m in d.dc_modes:
                op = _add(dc, "OpMode")
                _add(op, "Name", m.name)
                _add(op, "Desc", m.description)
                _add(op, "AssignActivate", _hex(m.assign_activate))
                _add(op, "CycleTimeSync0", str(m.cycle_time_sync0), Factor="1")
                _add(op, "ShiftTimeSync0", str(m.shift_time_sync0))
    indent(root)
    return b'<?xml version="1.0" encoding="UTF-8"?>\n' + tostring(root, encoding="utf-8") + b"\n"
