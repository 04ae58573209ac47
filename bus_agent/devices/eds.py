"""EDS files (CiA 306): a CANopen device's object dictionary as its vendor describes it.

Read through python-canopen's import (``canopen.import_od``), which resolves ``$NODEID``
expressions (also with spaces, any case, bits 30/31 added) and reads ``ObjectType``/``DataType``
as decimal or hex. Before the import the text is made readable: any encoding (UTF-8, else
Latin-1), decimal numbers with leading zeros (``0123``) as plain decimals. After it, what vendors
write differently is made uniform (docs/device-files.md, "EDS (CANopen)"):

- ``AccessType`` in any case, ``rwr``/``rww`` (read-write, mapped on the TPDO / RPDO side) as
  ``rw``, ``const`` as read-only;
- an empty or missing ``DefaultValue`` is no default (a mapping slot without one is 0);
- mapping objects as RECORD or ARRAY alike; a mapping's entries are the first sub 0 of them
  (sub 0 = 0: the PDO maps nothing, its entries stay values of their subindices);
- the identity from 0x1018 defaults, else ``[DeviceInfo]`` (vendor numbers decimal or hex);
- CiA 402 detected by the low 16 bits of 0x1000 only (0x0192): the byte above varies.

Pure but for reading the file: :func:`load` returns an :class:`EdsDevice` (its objects, identity,
default PDOs) for one node id. Used by ``canopen-sim --eds`` (the simulated node's dictionary) and
by the agent (``[[can.nodes]] eds``: object names and types, the ``eds`` PDO policy).
"""

from __future__ import annotations

import io
import os
import re
from dataclasses import dataclass
from typing import Any, Mapping

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes as dt

#: CiA 301 data types the agent decodes as integers: code -> (short name, bits, signed).
INTEGER_TYPES: dict[int, tuple[str, int, bool]] = {
    dt.BOOLEAN: ("bool", 1, False),
    dt.INTEGER8: ("i8", 8, True), dt.INTEGER16: ("i16", 16, True), dt.INTEGER24: ("i24", 24, True),
    dt.INTEGER32: ("i32", 32, True), dt.INTEGER64: ("i64", 64, True),
    dt.UNSIGNED8: ("u8", 8, False), dt.UNSIGNED16: ("u16", 16, False), dt.UNSIGNED24: ("u24", 24, False),
    dt.UNSIGNED32: ("u32", 32, False), dt.UNSIGNED64: ("u64", 64, False),
}
#: AccessType as written -> what it means for SDO (CiA 306 §4.6.3.2).
ACCESS = {"ro": "ro", "const": "ro", "wo": "wo", "rw": "rw", "rwr": "rw", "rww": "rw"}
CIA402_PROFILE = 0x0192
RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
MAX_PDOS = 512  # CiA 301: 0x1400..0x15FF, 0x1800..0x19FF
COB_ID_INVALID = 0x80000000


class EdsError(ValueError):
    """An EDS that cannot be used; the message names the file and what is wrong."""


@dataclass(frozen=True)
class EdsObject:
    """One entry (index, subindex) of an EDS: name, CiA 301 data type, access, default."""

    index: int
    subindex: int
    name: str
    data_type: int
    access: str              # "ro" | "wo" | "rw" (ACCESS)
    pdo_mappable: bool
    default: Any = None      # int | float | str | bytes | None (no default)
    low: int | None = None
    high: int | None = None
    var: ODVariable | None = None  # python-canopen's, for encoding and decoding values

    @property
    def key(self) -> tuple[int, int]:
        return (self.index, self.subindex)

    @property
    def integer(self) -> tuple[str, int, bool] | None:
        """(short name, bits, signed) for an integer type, else None."""
        return INTEGER_TYPES.get(self.data_type)

    @property
    def bits(self) -> int:
        """Size in bits (0: variable, a string or domain)."""
        if self.data_type in INTEGER_TYPES:
            return INTEGER_TYPES[self.data_type][1]
        return {dt.REAL32: 32, dt.REAL64: 64}.get(self.data_type, 0)

    def default_int(self) -> int:
        """The default as an integer (0 when there is none)."""
        return int(self.default) if isinstance(self.default, (int, float)) else 0

    def encode(self, value: Any) -> bytes:
        """``value`` as the bytes an SDO carries (little-endian, the type's size)."""
        if self.var is None:
            raise EdsError(f"0x{self.index:04X}:{self.subindex} has no type")
        return self.var.encode_raw(value)

    def default_bytes(self) -> bytes:
        """The default as SDO bytes (a number without default: 0; a string without: empty)."""
        if self.default is None:
            return self.encode(0) if self.bits else b""
        return self.encode(self.default)


@dataclass(frozen=True)
class EdsPdo:
    """A PDO as the EDS defaults it: number (1..), side, COB-ID, transmission type, entries."""

    tx: bool
    number: int
    cob_id: int
    transmission_type: int
    entries: tuple[int, ...]  # u32 mapping entries: index << 16 | subindex << 8 | bits

    @property
    def valid(self) -> bool:
        return not self.cob_id & COB_ID_INVALID and bool(self.entries)


@dataclass(frozen=True)
class EdsDevice:
    """What an EDS says about one node (its ``$NODEID`` expressions resolved for ``node_id``)."""

    path: str
    node_id: int
    objects: Mapping[tuple[int, int], EdsObject]
    vendor_id: int
    product_code: int
    revision: int
    product_name: str
    device_type: int
    od: Any  # python-canopen's ObjectDictionary

    @property
    def cia402(self) -> bool:
        """CiA 402 by the low 16 bits of 0x1000 (the byte above varies by vendor)."""
        return self.device_type & 0xFFFF == CIA402_PROFILE

    def name_of(self, index: int, subindex: int) -> str | None:
        obj = self.objects.get((index, subindex))
        return obj.name if obj else None

    def pdos(self, tx: bool) -> tuple[EdsPdo, ...]:
        """The default PDOs of one side (RPDOs, or TPDOs with ``tx``) the EDS defines, in order."""
        comm_base, map_base = (TPDO_COMM, TPDO_MAP) if tx else (RPDO_COMM, RPDO_MAP)
        out = []
        for n in range(MAX_PDOS):
            if (comm_base + n, 1) not in self.objects and (map_base + n, 0) not in self.objects:
                continue
            count = self._int(map_base + n, 0)
            entries = tuple(self._int(map_base + n, i) for i in range(1, count + 1))
            out.append(EdsPdo(tx, n + 1, self._int(comm_base + n, 1), self._int(comm_base + n, 2), entries))
        return tuple(out)

    def _int(self, index: int, subindex: int) -> int:
        obj = self.objects.get((index, subindex))
        return obj.default_int() if obj else 0

    def identity_mismatch(self, vendor_id: int, product_code: int, revision: int) -> str | None:
        """Why a node with this identity is not the EDS's device (None: it is). The revision is
        compared only when the EDS gives one (not 0)."""
        wrong = [f"{what} 0x{got:08X}, the EDS says 0x{want:08X}"
                 for what, got, want in (("vendor id", vendor_id, self.vendor_id),
                                         ("product code", product_code, self.product_code),
                                         ("revision", revision, self.revision))
                 if want and got != want]
        return "; ".join(wrong) or None


_LEADING_ZEROS = re.compile(r"^(\s*[A-Za-z0-9_]+\s*=\s*)0+(\d+)[ \t]*$", re.MULTILINE)


def _text(path: str) -> str:
    with open(path, "rb") as f:
        raw = f.read()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")  # vendors' tools write their locale's code page
    text = text.replace("\r\n", "\n").replace("\r", "\n")  # CRLF (most vendors' files), or CR
    # "VendorNumber=0123": decimal, not an octal Python refuses (a lone 0 stays 0)
    return _LEADING_ZEROS.sub(r"\1\2", text)


def _entries(od: Any) -> list[tuple[ODVariable, str]]:
    """Every variable of ``od`` with its name (a sub-entry's prefixed by its object's)."""
    out = []
    for obj in od.values():
        if isinstance(obj, (ODRecord, ODArray)):
            out += [(v, f"{obj.name}: {v.name}" if v.subindex else v.name) for v in obj.subindices.values()]
        elif isinstance(obj, ODVariable):
            out.append((obj, obj.name))
    return out


def load(path: str | os.PathLike[str], node_id: int) -> EdsDevice:
    """Read ``path`` for node ``node_id`` (1..127). Raises EdsError naming the file."""
    path = os.fspath(path)
    if not 1 <= node_id <= 127:
        raise EdsError(f"EDS {path}: node id {node_id} outside 1..127")
    try:
        stream = io.StringIO(_text(path))
    except OSError as e:
        raise EdsError(f"EDS {path}: cannot read: {e.strerror or e}") from None
    stream.name = "device.eds"  # python-canopen picks the format by the name's suffix
    try:
        od = canopen.import_od(stream, node_id)
    except Exception as e:  # configparser, ValueError, KeyError: whatever the file breaks
        raise EdsError(f"EDS {path}: not a readable EDS: {type(e).__name__}: {e}") from None
    objects: dict[tuple[int, int], EdsObject] = {}
    for var, name in _entries(od):
        access = ACCESS.get((var.access_type or "").strip().lower())
        if access is None:
            raise EdsError(f"EDS {path}: 0x{var.index:04X}:{var.subindex} ({name}): AccessType "
                           f"{var.access_type!r} is not one of {', '.join(ACCESS)}")
        default = None if getattr(var, "default_raw", "") in ("", None) else var.default
        objects[(var.index, var.subindex)] = EdsObject(var.index, var.subindex, name, var.data_type or 0, access,
                                                       bool(var.pdo_mappable), default, var.min, var.max, var)
    if not objects:
        raise EdsError(f"EDS {path}: no objects (no [IIII] sections)")
    info = od.device_information

    def ident(sub: int, fallback: int | None) -> int:
        obj = objects.get((0x1018, sub))
        return obj.default_int() if obj is not None and obj.default is not None else int(fallback or 0)

    dev_type = objects.get((0x1000, 0))
    return EdsDevice(path=path, node_id=node_id, objects=objects,
                     vendor_id=ident(1, info.vendor_number), product_code=ident(2, info.product_number),
                     revision=ident(3, info.revision_number), product_name=info.product_name or "",
                     device_type=dev_type.default_int() if dev_type else 0, od=od)


def parse_spec(spec: str) -> tuple[str, int]:
    """``FILE[*COUNT]`` (``canopen-sim --eds``) -> (file, count). Raises EdsError."""
    path, star, count = spec.rpartition("*") if "*" in spec else (spec, "", "1")
    if not star:
        path = spec
    try:
        n = int(count)
    except ValueError:
        raise EdsError(f"--eds {spec!r}: COUNT {count!r} is not a number (FILE[*COUNT])") from None
    if not path or not 1 <= n <= 127:
        raise EdsError(f"--eds {spec!r}: FILE[*COUNT] with COUNT 1..127")
    return path, n
