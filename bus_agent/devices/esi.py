"""EtherCAT Slave Information (ESI, ETG.2000) files: a pure parser into small device descriptions.

:func:`parse_esi` reads one file (bytes or text) and returns every ``<Device>`` in it as an
:class:`EsiDevice`: identity, name, sync managers, RxPdo/TxPdo with every entry (padding and
1-bit entries included), ``Fixed``/``Mandatory``/``Sm``/``<Exclude>``, the object dictionary of
``<Profile><Dictionary>`` (types, access, defaults), the CoE flags, DC op modes and InitCmds.

Vendors' files differ from the schema in known ways (docs/device-files.md); the parser takes:
numbers as ``#x1A00``, ``0x1A00``, ``#x0x6041`` or decimal, booleans ``1``/``true``, XML
namespaces, a trailing space in ``<Type>``, ``DefaultData`` written in decimal or (for
0x1C12/0x1C13) in the wrong byte order, ``ProfileNo`` inside ``<ChannelInfo>``, and files
without CoE section or dictionary. Untrusted input: parsed with ``defusedxml`` (no entity
expansion, no external references).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence
from xml.etree.ElementTree import Element

import defusedxml.ElementTree as SafeET

from bus_agent.devices.values import (EsiError, _fix_assign_order, decode_value, parse_bool, parse_default_data,
                                      parse_number)

# re-exported: the value formats are part of this module's API
__all__ = ["BASE_TYPES", "INT_TYPES", "CoeFlags", "DcOpMode", "EsiDevice", "EsiEntry", "EsiError", "EsiObject",
           "EsiPdo", "EsiSm", "InitCmd", "decode_value", "load_esi", "match_identity", "parse_bool",
           "parse_default_data", "parse_esi", "parse_esi_spec", "parse_number", "select_device"]


#: ETG.1000.6 base data types: ESI name -> (kind, bits). ``STRING(n)`` and arrays are derived.
BASE_TYPES: Mapping[str, tuple[str, int]] = {
    "BOOL": ("bool", 1), "BIT": ("bool", 1),
    **{f"BIT{n}": ("uint", n) for n in range(1, 9)},
    "SINT": ("int", 8), "INT": ("int", 16), "INT24": ("int", 24), "DINT": ("int", 32), "LINT": ("int", 64),
    "USINT": ("uint", 8), "UINT": ("uint", 16), "UINT24": ("uint", 24), "UDINT": ("uint", 32),
    "ULINT": ("uint", 64), "BYTE": ("uint", 8), "WORD": ("uint", 16), "DWORD": ("uint", 32),
    "REAL": ("real", 32), "LREAL": ("real", 64),
}
#: (kind, bits) of the integer types -> the project's short type names (u8..i64)
INT_TYPES: Mapping[tuple[str, int], str] = {
    ("uint", 8): "u8", ("uint", 16): "u16", ("uint", 32): "u32", ("uint", 64): "u64",
    ("int", 8): "i8", ("int", 16): "i16", ("int", 32): "i32", ("int", 64): "i64"}
#: InitCmd ``<Transition>`` codes (ETG.2000): I=INIT, P=PRE-OP, S=SAFE-OP, O=OP, B=BOOT.
TRANSITIONS = frozenset({"IP", "PS", "SO", "SP", "OS", "OP", "PI", "SI", "OI", "IB", "BI", "II", "PP", "SS"})


# ---------------------------------------------------------------------------------------------
# The description


@dataclass(frozen=True)
class EsiEntry:
    """One PDO entry. ``index`` 0 is padding (no subindex, no type)."""

    index: int
    subindex: int
    bits: int
    name: str = ""
    datatype: str = ""

    @property
    def padding(self) -> bool:
        return self.index == 0

    @property
    def mapping(self) -> int:
        """The u32 mapping entry (index << 16 | subindex << 8 | bits)."""
        return (self.index << 16) | (self.subindex << 8) | self.bits


@dataclass(frozen=True)
class EsiPdo:
    """One ``<RxPdo>``/``<TxPdo>``. ``sm`` is the default assignment (None: an alternative)."""

    index: int
    name: str
    entries: tuple[EsiEntry, ...]
    rx: bool
    sm: int | None = None
    fixed: bool = False
    mandatory: bool = False
    excludes: tuple[int, ...] = ()

    @property
    def bits(self) -> int:
        return sum(e.bits for e in self.entries)


@dataclass(frozen=True)
class EsiSm:
    """One ``<Sm>``: kind is MBoxOut, MBoxIn, Outputs or Inputs."""

    kind: str
    start: int
    default_size: int
    control: int
    enable: bool


@dataclass(frozen=True)
class EsiObject:
    """One dictionary entry (an object's subindex). ``default`` is its little-endian bytes."""

    index: int
    subindex: int
    name: str
    datatype: str        # the ESI base type name (UINT, BOOL, STRING(8), OCTET_STRING...)
    bits: int
    access: str          # "ro" | "rw" | "wo"
    pdo_mapping: str     # "" | "R" | "T" | "RT"
    default: bytes | None = None
    object_name: str = ""

    @property
    def kind(self) -> str:
        """bool | int | uint | real | string | octets."""
        if self.datatype.startswith("STRING"):
            return "string"
        return BASE_TYPES.get(self.datatype, ("octets", self.bits))[0]

    def value(self, data: bytes | None = None) -> int | float | str | bytes | None:
        """``data`` (default: the default bytes) decoded by the entry's type."""
        data = self.default if data is None else data
        if data is None:
            return None
        return decode_value(self.kind, self.bits, data)


@dataclass(frozen=True)
class CoeFlags:
    """``<Mailbox><CoE>`` attributes (absent: False)."""

    sdo_info: bool = False
    pdo_assign: bool = False
    pdo_config: bool = False
    complete_access: bool = False
    pdo_upload: bool = False


@dataclass(frozen=True)
class DcOpMode:
    """One ``<Dc><OpMode>``. ``assign_activate`` 0x300 = SYNC0 (0x700 SYNC0+1), 0 = free run/SM."""

    name: str
    description: str
    assign_activate: int
    cycle_time_sync0: int = 0
    shift_time_sync0: int = 0

    @property
    def sync0(self) -> bool:
        return bool(self.assign_activate & 0x0200)


@dataclass(frozen=True)
class InitCmd:
    """One CoE ``<InitCmd>``: an SDO download made at the named transitions."""

    transitions: tuple[str, ...]
    index: int
    subindex: int
    data: bytes
    complete_access: bool = False
    comment: str = ""


@dataclass(frozen=True)
class EsiDevice:
    """One ``<Device>`` of an ESI file."""

    vendor_id: int
    product_code: int
    revision: int
    type_name: str
    name: str
    vendor_name: str = ""
    group: str = ""
    profile_no: int | None = None
    sms: tuple[EsiSm, ...] = ()
    rx_pdos: tuple[EsiPdo, ...] = ()
    tx_pdos: tuple[EsiPdo, ...] = ()
    objects: Mapping[tuple[int, int], EsiObject] = field(default_factory=dict)
    coe: CoeFlags | None = None
    mailbox_protocols: tuple[str, ...] = ()
    dc_modes: tuple[DcOpMode, ...] = ()
    init_cmds: tuple[InitCmd, ...] = ()
    eeprom: bytes | None = None
    source: str = field(default="", compare=False)

    @property
    def identity(self) -> tuple[int, int, int]:
        return self.vendor_id, self.product_code, self.revision

    def label(self) -> str:
        return (f"{self.name!r} (vendor 0x{self.vendor_id:08X} product 0x{self.product_code:08X} "
                f"revision 0x{self.revision:08X})")

    def pdos(self, rx: bool) -> tuple[EsiPdo, ...]:
        return self.rx_pdos if rx else self.tx_pdos

    def pdo(self, index: int) -> EsiPdo | None:
        return next((p for p in self.rx_pdos + self.tx_pdos if p.index == index), None)

    def default_assign(self, rx: bool) -> tuple[int, ...]:
        """The PDOs assigned at power-on: those with an ``Sm`` attribute, in file order."""
        return tuple(p.index for p in self.pdos(rx) if p.sm is not None)

    def sm_index(self, kind: str) -> int | None:
        return next((k for k, sm in enumerate(self.sms) if sm.kind == kind), None)

    @property
    def cia402(self) -> bool:
        """Carries CiA 402 objects: 0x6040/0x6041 in its dictionary or its PDOs, or profile 402."""
        keys = set(self.objects) | {(e.index, e.subindex) for p in self.rx_pdos + self.tx_pdos for e in p.entries}
        return ((0x6040, 0) in keys and (0x6041, 0) in keys) or self.profile_no == 402

    @property
    def dc_required(self) -> bool:
        """Only DC (SYNC0) op modes are offered: OP needs SYNC0."""
        return bool(self.dc_modes) and all(m.sync0 for m in self.dc_modes)

    @property
    def dc_capable(self) -> bool:
        return any(m.sync0 for m in self.dc_modes)


# ---------------------------------------------------------------------------------------------
# XML helpers (namespace-blind)


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1] if isinstance(tag, str) else ""


def _children(el: Element | None, name: str) -> list[Element]:
    return [c for c in el if _local(c.tag) == name] if el is not None else []


def _child(el: Element | None, name: str) -> Element | None:
    return next(iter(_children(el, name)), None)


def _text(el: Element | None, name: str, default: str = "") -> str:
    c = _child(el, name)
    return c.text.strip() if c is not None and c.text else default


def _path(el: Element | None, *names: str) -> Element | None:
    for n in names:
        el = _child(el, n)
    return el


def _attr(el: Element, name: str) -> str | None:
    for k, v in el.attrib.items():
        if _local(k) == name:
            return v
    return None


def _name(el: Element | None) -> str:
    """The English ``<Name>`` (LcId 1033) or the first one."""
    names = _children(el, "Name")
    for n in names:
        if _attr(n, "LcId") in (None, "1033") and n.text:
            return n.text.strip()
    return (names[0].text or "").strip() if names else ""


# ---------------------------------------------------------------------------------------------
# Parsing


def _type_bits(name: str, types: Mapping[str, Element]) -> int:
    if name in BASE_TYPES:
        return BASE_TYPES[name][1]
    m = re.fullmatch(r"STRING\((\d+)\)", name)
    if m:
        return 8 * int(m.group(1))
    dt = types.get(name)
    if dt is not None and _text(dt, "BitSize"):
        return parse_number(_text(dt, "BitSize"), f"DataType {name} BitSize")
    return 0


def _flags(el: Element | None) -> tuple[str | None, str | None]:
    flags = _child(el, "Flags")
    access = _text(flags, "Access") or None
    mapping = _text(flags, "PdoMapping") or None
    return (access.lower() if access else None), (mapping.upper() if mapping else None)


def _subitems(dt: Element, types: Mapping[str, Element]) -> list[tuple[int, str, str, int, Element]]:
    """(subindex, name, base type, bits, the SubItem element) of a record/array type; array
    elements expanded with their subindices (LBound...)."""
    out: list[tuple[int, str, str, int, Element]] = []
    next_sub = 0
    for si in _children(dt, "SubItem"):
        tname = _text(si, "Type")
        sub_text = _text(si, "SubIdx")
        arr = types.get(tname)
        info = _child(arr, "ArrayInfo") if arr is not None else None
        if info is not None and not sub_text:
            base = _text(arr, "BaseType")
            lbound = parse_number(_text(info, "LBound", "1"), "LBound")
            count = parse_number(_text(info, "Elements", "0"), "Elements")
            bits = _type_bits(base, types)
            for k in range(count):
                out.append((lbound + k, f"SubIndex {lbound + k:03d}", base, bits, si))
            next_sub = lbound + count
            continue
        sub = parse_number(sub_text, "SubIdx") if sub_text else next_sub
        bits = parse_number(_text(si, "BitSize"), "SubItem BitSize") if _text(si, "BitSize") else _type_bits(tname, types)
        out.append((sub, _name(si), tname, bits, si))
        next_sub = sub + 1
    return out


def _default(info: Element | None, bits: int) -> bytes | None:
    if info is None:
        return None
    nbytes = (bits + 7) // 8
    data = _text(info, "DefaultData")
    if data:
        return parse_default_data(data, nbytes)
    value = _text(info, "DefaultValue")
    if value:
        v = parse_number(value, "DefaultValue")
        return v.to_bytes(max(nbytes, 1), "little", signed=v < 0)
    string = _child(info, "DefaultString")
    if string is not None:
        return (string.text or "").encode("latin-1", "replace")
    return None


def _dictionary(profile: Element | None) -> dict[tuple[int, int], EsiObject]:
    dictionary = _child(profile, "Dictionary")
    if dictionary is None:
        return {}
    types = {_text(dt, "Name"): dt for dt in _children(_child(dictionary, "DataTypes"), "DataType")}
    objects: dict[tuple[int, int], EsiObject] = {}
    for obj in _children(_child(dictionary, "Objects"), "Object"):
        index = parse_number(_text(obj, "Index"), "Object Index")
        oname = _name(obj)
        tname = _text(obj, "Type")
        access, mapping = _flags(obj)
        info = _child(obj, "Info")
        dt = types.get(tname)
        subs = _subitems(dt, types) if dt is not None and _children(dt, "SubItem") else []
        if not subs:
            bits = (parse_number(_text(obj, "BitSize"), "Object BitSize") if _text(obj, "BitSize")
                    else _type_bits(tname, types))
            base = _text(dt, "BaseType") if dt is not None and _text(dt, "BaseType") else tname
            objects[(index, 0)] = EsiObject(index, 0, oname, base, bits, access or "ro", mapping or "",
                                            _fix_assign_order(index, 0, _default(info, bits) or b"") or None, oname)
            continue
        infos = _children(info, "SubItem")
        for k, (sub, sname, stype, bits, si) in enumerate(subs):
            s_access, s_mapping = _flags(si)  # a subitem's access overrides the object's
            sinfo = infos[k] if k < len(infos) else None
            default = _default(_child(sinfo, "Info"), bits) if sinfo is not None else None
            if default is not None:
                default = _fix_assign_order(index, sub, default)
            objects[(index, sub)] = EsiObject(index, sub, sname or f"SubIndex {sub:03d}", stype, bits,
                                              s_access or access or "ro", s_mapping or mapping or "", default, oname)
    return objects


def _pdo(el: Element, rx: bool) -> EsiPdo:
    index = parse_number(_text(el, "Index"), "Pdo Index")
    entries = []
    for e in _children(el, "Entry"):
        ei = parse_number(_text(e, "Index", "0"), f"Pdo 0x{index:04X} Entry Index")
        bits = parse_number(_text(e, "BitLen"), f"Pdo 0x{index:04X} Entry BitLen")
        sub = parse_number(_text(e, "SubIndex"), "SubIndex") if ei and _text(e, "SubIndex") else 0
        entries.append(EsiEntry(ei, sub, bits, _name(e), _text(e, "DataType")))
    sm = _attr(el, "Sm")
    return EsiPdo(index=index, name=_name(el), entries=tuple(entries), rx=rx,
                  sm=parse_number(sm, "Pdo Sm") if sm not in (None, "") else None,
                  fixed=parse_bool(_attr(el, "Fixed")), mandatory=parse_bool(_attr(el, "Mandatory")),
                  excludes=tuple(parse_number(x.text, "Exclude") for x in _children(el, "Exclude") if x.text))


def _init_cmds(coe: Element | None) -> tuple[InitCmd, ...]:
    out = []
    for c in _children(coe, "InitCmd"):
        trans = tuple(t.text.strip().upper() for t in _children(c, "Transition") if t.text)
        unknown = [t for t in trans if t not in TRANSITIONS]
        if unknown:
            raise EsiError(f"InitCmd {_text(c, 'Index')}: unknown transition {unknown[0]!r}")
        raw = "".join(_text(c, "Data").split())
        if not re.fullmatch(r"(?:[0-9A-Fa-f]{2})*", raw):
            raise EsiError(f"InitCmd {_text(c, 'Index')}: Data {raw!r} is not hex bytes")
        out.append(InitCmd(trans, parse_number(_text(c, "Index"), "InitCmd Index"),
                           parse_number(_text(c, "SubIndex", "0"), "InitCmd SubIndex"), bytes.fromhex(raw),
                           parse_bool(_attr(c, "CompleteAccess")), _text(c, "Comment")))
    return tuple(out)


def _eeprom(el: Element | None) -> bytes | None:
    if el is None:
        return None
    data = _text(el, "Data") or _text(el, "ConfigData")
    return bytes.fromhex("".join(data.split())) if data and re.fullmatch(r"[0-9A-Fa-f\s]+", data) else None


def _profile_no(profile: Element | None) -> int | None:
    text = _text(profile, "ProfileNo") or _text(_child(profile, "ChannelInfo"), "ProfileNo")
    return parse_number(text, "ProfileNo") if text else None


def _device(dev: Element, vendor_id: int, vendor_name: str, source: str) -> EsiDevice:
    typ = _child(dev, "Type")
    if typ is None:
        raise EsiError(f"{source}: a <Device> without <Type>")
    product = parse_number(_attr(typ, "ProductCode"), "ProductCode")
    revision = parse_number(_attr(typ, "RevisionNo") or "0", "RevisionNo")
    type_name = (typ.text or "").strip()
    profiles = _children(dev, "Profile")
    objects: dict[tuple[int, int], EsiObject] = {}
    profile_no = None
    for p in profiles:
        objects.update(_dictionary(p))
        profile_no = profile_no or _profile_no(p)
    sms = tuple(EsiSm(kind=(sm.text or "").strip(), start=parse_number(_attr(sm, "StartAddress") or "0", "Sm"),
                      default_size=parse_number(_attr(sm, "DefaultSize") or "0", "Sm DefaultSize"),
                      control=parse_number(_attr(sm, "ControlByte") or "0", "Sm ControlByte"),
                      enable=parse_bool(_attr(sm, "Enable"), True))
                for sm in _children(dev, "Sm"))
    mailbox = _child(dev, "Mailbox")
    coe_el = _child(mailbox, "CoE")
    coe = None if coe_el is None else CoeFlags(
        sdo_info=parse_bool(_attr(coe_el, "SdoInfo")), pdo_assign=parse_bool(_attr(coe_el, "PdoAssign")),
        pdo_config=parse_bool(_attr(coe_el, "PdoConfig")), complete_access=parse_bool(_attr(coe_el, "CompleteAccess")),
        pdo_upload=parse_bool(_attr(coe_el, "PdoUpload")))
    dc_modes = tuple(DcOpMode(_text(m, "Name"), _text(m, "Desc"),
                              parse_number(_text(m, "AssignActivate", "0"), "AssignActivate"),
                              parse_number(_text(m, "CycleTimeSync0", "0"), "CycleTimeSync0"),
                              parse_number(_text(m, "ShiftTimeSync0", "0"), "ShiftTimeSync0"))
                     for m in _children(_child(dev, "Dc"), "OpMode"))
    return EsiDevice(
        vendor_id=vendor_id, product_code=product, revision=revision, type_name=type_name,
        name=_name(dev) or type_name, vendor_name=vendor_name, group=_text(dev, "GroupType"),
        profile_no=profile_no, sms=sms,
        rx_pdos=tuple(_pdo(p, True) for p in _children(dev, "RxPdo")),
        tx_pdos=tuple(_pdo(p, False) for p in _children(dev, "TxPdo")),
        objects=objects, coe=coe,
        mailbox_protocols=tuple(_local(c.tag) for c in mailbox) if mailbox is not None else (),
        dc_modes=dc_modes, init_cmds=_init_cmds(coe_el), eeprom=_eeprom(_child(dev, "Eeprom")), source=source)


def _parse_xml(data: bytes, source: str) -> Element:
    try:
        return SafeET.fromstring(data)
    except SafeET.ParseError as exc:
        # A file whose bytes do not match its declared encoding (UTF-8 declared, Latin-1
        # written): read it as the Latin-1 it is, declaration dropped.
        if "not well-formed" in str(exc) or "encoding" in str(exc):
            text = data.decode("latin-1")
            text = re.sub(r"^\ufeff?<\?xml[^>]*\?>", "", text.lstrip("\ufeff").lstrip())
            try:
                return SafeET.fromstring(text)
            except SafeET.ParseError:
                pass
        raise EsiError(f"{source}: not well-formed XML: {exc}") from None
    except Exception as exc:  # defusedxml refusals (entities, DTDs)
        raise EsiError(f"{source}: refused: {exc}") from None


def parse_esi(data: bytes | str, source: str = "<esi>") -> list[EsiDevice]:
    """Every ``<Device>`` of one ESI file, in file order. Raises :class:`EsiError`."""
    raw = data.encode("utf-8") if isinstance(data, str) else data
    root = _parse_xml(raw, source)
    if _local(root.tag) != "EtherCATInfo":
        raise EsiError(f"{source}: root element is <{_local(root.tag)}>, not <EtherCATInfo>")
    vendor = _child(root, "Vendor")
    vendor_id = parse_number(_text(vendor, "Id"), f"{source}: Vendor Id")
    devices = [_device(d, vendor_id, _name(vendor), source)
               for d in _children(_child(_child(root, "Descriptions"), "Devices"), "Device")]
    if not devices:
        raise EsiError(f"{source}: no <Device> in <Descriptions><Devices>")
    return devices


def load_esi(path: str | Path) -> list[EsiDevice]:
    """The devices of an ESI file, or of every ``*.xml`` in a directory (sorted by name)."""
    p = Path(path)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() == ".xml")
        if not files:
            raise EsiError(f"{p}: no *.xml ESI file in this directory")
    elif p.is_file():
        files = [p]
    else:
        raise EsiError(f"{p}: no such file or directory")
    out: list[EsiDevice] = []
    for f in files:
        out.extend(parse_esi(f.read_bytes(), str(f)))
    return out


def select_device(devices: Sequence[EsiDevice], product: int | None = None,
                  revision: int | None = None, source: str = "") -> EsiDevice:
    """The device with this product code (and revision); by default the first with CiA 402
    objects (else the first)."""
    if product is None:
        return next((d for d in devices if d.cia402), devices[0])
    found = [d for d in devices if d.product_code == product and (revision is None or d.revision == revision)]
    if not found:
        have = ", ".join(f"0x{d.product_code:08X}:0x{d.revision:08X}" for d in devices)
        want = f"0x{product:08X}" + ("" if revision is None else f":0x{revision:08X}")
        raise EsiError(f"{source or 'ESI'}: no device {want}; the file has {have}")
    return found[0]


def match_identity(devices: Iterable[EsiDevice], vendor_id: int, product_code: int,
                   revision: int) -> EsiDevice | None:
    """The device of this exact identity, else one with the same vendor and product code and the
    highest revision not above the slave's (ETG.2000: a newer revision stays compatible)."""
    candidates = [d for d in devices if d.vendor_id == vendor_id and d.product_code == product_code]
    exact = next((d for d in candidates if d.revision == revision), None)
    if exact is not None:
        return exact
    older = [d for d in candidates if d.revision < revision]
    return max(older, key=lambda d: d.revision) if older else None


def parse_esi_spec(spec: str) -> tuple[str, int | None, int | None, int]:
    """``FILE[@PRODUCT[:REVISION]][*COUNT]`` -> (file, product, revision, count)."""
    rest, _, count_text = spec.rpartition("*") if "*" in spec else (spec, "", "")
    if count_text and (not count_text.isdigit() or int(count_text) < 1):
        raise EsiError(f"--esi {spec!r}: the count after '*' must be a positive integer")
    path, _, ident = rest.rpartition("@") if "@" in rest else (rest, "", "")
    product = revision = None
    if ident:
        p_text, _, r_text = ident.partition(":")
        product = parse_number(p_text, f"--esi {spec!r}: product code")
        revision = parse_number(r_text, f"--esi {spec!r}: revision") if r_text else None
    if not path:
        raise EsiError(f"--esi {spec!r}: no file")
    return path, product, revision, int(count_text) if count_text else 1
