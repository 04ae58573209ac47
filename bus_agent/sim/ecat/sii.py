"""SII EEPROM image of a simulated CiA 402 drive (ETG.1000.6 §5.4, ETG.2010).

Pure functions: build the word image that the ESC serves through its EEPROM interface
(registers 0x0502..0x050F). Layout: identity words 0x00..0x3F, then categories from word 0x40
(STRINGS 10, GENERAL 30, FMMU 40, SM 41, TXPDO 50, RXPDO 51), ended by 0xFFFF.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Sequence

# Mailbox and process-data layout offered by every simulated drive (ESC process RAM).
MBX_OUT_START = 0x1000  # SM0: master -> slave mailbox
MBX_OUT_SIZE = 128
MBX_IN_START = 0x1080  # SM1: slave -> master mailbox
MBX_IN_SIZE = 128
PD_OUT_START = 0x1100  # SM2: RxPDO buffer
PD_IN_START = 0x1400  # SM3: TxPDO buffer

# SM control bytes (register 0x0804 + 8n): mode bits 0-1, direction bits 2-3, irq bits 4-6.
SM_CTRL_MBX_OUT = 0x26  # mailbox, ECAT writes, ECAT irq
SM_CTRL_MBX_IN = 0x22  # mailbox, ECAT reads, ECAT irq
SM_CTRL_PD_OUT = 0x64  # buffered, ECAT writes, ECAT irq, watchdog trigger
SM_CTRL_PD_IN = 0x20  # buffered, ECAT reads, ECAT irq

PDI_CONTROL = 0x0005  # word 0x00 (register 0x0140)
MBX_PROTO_COE = 0x0004
MBX_PROTO_FOE = 0x0008
#: SII word 0x1C bits of the ESI's <Mailbox> children (ETG.1000.6 Table 18)
MAILBOX_PROTOCOL_BITS = {"AoE": 0x01, "EoE": 0x02, "CoE": 0x04, "FoE": 0x08, "SoE": 0x10, "VoE": 0x20}
# GENERAL byte 5, CoE details: 0x01 SDO, 0x04 PDO assign, 0x08 PDO configuration (no SDO info,
# no complete access: SOEM then reads the mapping one subindex at a time).
COE_DETAILS = 0x0D


class SiiCategory(IntEnum):
    """SII category types (ETG.1000.6 Table 19)."""

    STRINGS = 10
    GENERAL = 30
    FMMU = 40
    SM = 41
    TXPDO = 50
    RXPDO = 51
    END = 0xFFFF


class SmType(IntEnum):
    """SII SM category type byte / 0x1C00 communication type."""

    UNUSED = 0
    MBX_OUT = 1
    MBX_IN = 2
    OUTPUTS = 3
    INPUTS = 4


@dataclass(frozen=True)
class SmDefault:
    start: int
    length: int
    control: int
    enable: int
    type: SmType


SM_DEFAULTS: tuple[SmDefault, ...] = (
    SmDefault(MBX_OUT_START, MBX_OUT_SIZE, SM_CTRL_MBX_OUT, 1, SmType.MBX_OUT),
    SmDefault(MBX_IN_START, MBX_IN_SIZE, SM_CTRL_MBX_IN, 1, SmType.MBX_IN),
    SmDefault(PD_OUT_START, 0, SM_CTRL_PD_OUT, 1, SmType.OUTPUTS),
    SmDefault(PD_IN_START, 0, SM_CTRL_PD_IN, 1, SmType.INPUTS),
)

# CoE data type codes used in the SII PDO entries (ETG.1000.6 Table 64).
DATATYPE_CODES = {"i8": 0x02, "i16": 0x03, "i32": 0x04, "u8": 0x05, "u16": 0x06, "u32": 0x07, "i64": 0x15,
                  "u64": 0x1B, "str": 0x09, "bytes": 0x0A}
COE_SDO_INFO = 0x02
COE_COMPLETE_ACCESS = 0x20


def type_code(entry) -> int:
    """The CoE data type code of an object entry (BOOL 0x01, BITn 0x30+n-1); 0 for None."""
    if entry is None:
        return 0
    if entry.datatype == "u8" and entry.bitsize == 1:
        return 0x01
    if entry.datatype == "u8" and 1 < entry.bitsize < 8:
        return 0x30 + entry.bitsize - 1
    return DATATYPE_CODES.get(entry.datatype, 0)


def _crc8(data: bytes) -> int:
    """SII checksum over words 0..6 (polynomial x^8+x^2+x+1, initial 0xFF)."""
    crc = 0xFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _category(cat: SiiCategory, payload: bytes) -> bytes:
    if len(payload) % 2:
        payload += b"\0"
    return struct.pack("<HH", cat, len(payload) // 2) + payload


def _pdo_category(pdo_index: int, sm: int, entries: Sequence[tuple[int, int, int, "str | int"]]) -> bytes:
    """One PDO: index, entry count, SM, sync, name, flags; then 8 bytes per entry."""
    out = struct.pack("<HBBBBH", pdo_index, len(entries), sm, 0, 0, 0)
    for index, sub, bits, dtype in entries:
        code = dtype if isinstance(dtype, int) else DATATYPE_CODES.get(dtype, 0)
        out += struct.pack("<HBBBBH", index, sub, 0, code, bits, 0)
    return out


def build_sii(*, vendor_id: int, product_code: int, revision: int, serial: int, name: str,
              rx_entries: Sequence[tuple[int, int, int, str]] = (),
              tx_entries: Sequence[tuple[int, int, int, str]] = (),
              alias: int = 0, order: str = "", sms: Sequence[SmDefault] = SM_DEFAULTS,
              pdos: Sequence[tuple[int, int, Sequence[tuple[int, int, int, "str | int"]]]] | None = None,
              coe_details: int = COE_DETAILS, mailbox_protocols: int = MBX_PROTO_COE) -> bytes:
    """The EEPROM byte image (little-endian words) of one drive (ETG.2010 layout).

    ``pdos``: (PDO index, SM or 0xFF, entries) for the TXPDO/RXPDO categories, entries as
    (index, subindex, bits, datatype name or code); SOEM uses them only without CoE mapping.
    Without ``pdos``, ``rx_entries``/``tx_entries`` are published as 0x1600/0x1A00.
    ``sms``: SM0..SM3 (the mailbox words 0x18..0x1B follow SM0/SM1).
    """
    if pdos is None:
        pdos = [(0x1A00, 3, tx_entries)] if tx_entries else []
        pdos += [(0x1600, 2, rx_entries)] if rx_entries else []
    words = [0] * 0x40
    words[0x00] = PDI_CONTROL
    words[0x04] = alias & 0xFFFF
    head = struct.pack("<7H", *words[:7])
    words[0x07] = _crc8(head)
    words[0x08], words[0x09] = vendor_id & 0xFFFF, vendor_id >> 16
    words[0x0A], words[0x0B] = product_code & 0xFFFF, product_code >> 16
    words[0x0C], words[0x0D] = revision & 0xFFFF, revision >> 16
    words[0x0E], words[0x0F] = serial & 0xFFFF, (serial >> 16) & 0xFFFF
    words[0x18], words[0x19] = sms[0].start, sms[0].length
    words[0x1A], words[0x1B] = sms[1].start, sms[1].length
    words[0x1C] = mailbox_protocols
    words[0x3E] = 0x000F  # EEPROM size: (15 + 1) KiBit
    words[0x3F] = 0x0001  # SII version
    image = struct.pack("<64H", *words)

    strings = [name.encode("latin-1", "replace")[:255], b"Drives", (order or name).encode("latin-1", "replace")[:255]]
    payload = bytes([len(strings)]) + b"".join(bytes([len(s)]) + s for s in strings)
    image += _category(SiiCategory.STRINGS, payload)
    general = bytearray(32)
    general[0] = 2  # group string index
    general[1] = 0  # image
    general[2] = 3  # order
    general[3] = 1  # name
    general[5] = coe_details
    general[9] = 1  # DS402 channels
    general[11] = 0  # flags: LRW allowed
    image += _category(SiiCategory.GENERAL, bytes(general))
    image += _category(SiiCategory.FMMU, bytes([1, 2, 3, 0xFF]))
    sm = b"".join(struct.pack("<HHBBBB", d.start, d.length, d.control, 0, d.enable, d.type)
                  for d in sms)
    image += _category(SiiCategory.SM, sm)
    for pdo_index, pdo_sm, entries in pdos:
        kind = SiiCategory.RXPDO if pdo_index < 0x1A00 else SiiCategory.TXPDO
        image += _category(kind, _pdo_category(pdo_index, pdo_sm, entries))
    image += struct.pack("<H", SiiCategory.END)
    # pad to the declared size with 0xFF (erased EEPROM)
    return image + b"\xff" * max(0, 2048 - len(image))


#: Where ``looping_sii`` puts its loop: before the category a master looks for in that step
#: (config_init reads GENERAL, FMMU and SM; SOEM's config_map reads TXPDO/RXPDO only for a
#: slave whose PDO sizes CoE did not give).
LOOP_BEFORE = {"general": SiiCategory.GENERAL, "pdo": SiiCategory.TXPDO}


def categories(image: bytes) -> list[tuple[int, int, int]]:
    """(byte offset, type, length in words) of each category from word 0x40 up to END."""
    out = []
    a = 0x40 * 2
    while a + 4 <= len(image):
        cat, words = struct.unpack_from("<HH", image, a)
        if cat == SiiCategory.END:
            break
        out.append((a, cat, words))
        a += 4 + 2 * words
    return out


def looping_sii(image: bytes, before: str) -> bytes:
    """A malformed SII image: a category whose length word (0xFFFE) sends a reader that walks
    the categories with 16-bit byte addresses (SOEM's ``ecx_siifind``) back to that category's
    own header, for ever, placed before the category ``before`` names (:data:`LOOP_BEFORE`).
    A reader that looks for a category placed earlier is not affected."""
    if before not in LOOP_BEFORE:
        raise ValueError(f"before must be one of {', '.join(LOOP_BEFORE)}, got {before!r}")
    want = LOOP_BEFORE[before]
    at = next((a for a, cat, _ in categories(image) if cat == want), None)
    if at is None:
        raise ValueError(f"the SII has no {want.name} category")
    # 0x0001 (NOP): a category type no master looks for; 4 + 2 * 0xFFFE = 0x20000 bytes = 0 mod 2^16
    loop = struct.pack("<HH", 0x0001, 0xFFFE)
    return (bytes(image[:at]) + loop + bytes(image[at:]))[:len(image)]


def without_mailbox(image: bytes) -> bytes:
    """The SII of a slave without a mailbox: no mailbox offsets and sizes (words 0x18-0x1B), no
    mailbox protocol (0x1C), SM0/SM1 unused in the SM category (process data stays in SM2/SM3)."""
    out = bytearray(image)
    struct.pack_into("<5H", out, 0x18 * 2, 0, 0, 0, 0, 0)
    for a, cat, words in categories(out):
        if cat == SiiCategory.SM:
            for k in range(min(2, words // 4)):
                struct.pack_into("<HHBBBB", out, a + 4 + 8 * k, 0, 0, 0, 0, 0, SmType.UNUSED)
    return bytes(out)
