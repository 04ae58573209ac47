"""The simulated ESC without a network: EEPROM interface, mailbox link layer, AL codes.

No root needed: datagram-level accesses go straight to :class:`Esc` / :class:`Segment`.
"""

from __future__ import annotations

import struct

from bus_agent.bus.base import ALState
from bus_agent.sim.drive_model import PROFILES
from bus_agent.sim.ecat.esc import Esc
from bus_agent.sim.ecat.segment import Cmd, Segment
from bus_agent.sim.ecat.sii import SiiCategory

SM0_CONFIG = struct.pack("<HHBBBB", 0x1000, 128, 0x26, 0, 1, 0) + struct.pack("<HHBBBB", 0x1080, 128, 0x22, 0, 1, 0)


def _write(esc: Esc, ado: int, data: bytes) -> bool:
    return esc.write(ado, memoryview(bytearray(data)))


def _read(esc: Esc, ado: int, n: int) -> bytes | None:
    buf = bytearray(n)
    return bytes(buf) if esc.read(ado, memoryview(buf)) else None


def _preop() -> Esc:
    esc = Esc(0, PROFILES["generic"])
    _write(esc, 0x0800, SM0_CONFIG)
    _write(esc, 0x0120, b"\x02\x00")
    assert esc.al_state == ALState.PREOP
    return esc


def _upload_request(index: int, sub: int, counter: int) -> bytes:
    body = struct.pack("<HBHBI", 0x2000, 0x40, index, sub, 0)
    return (struct.pack("<HHBB", len(body), 0, 0, 0x03 | counter << 4) + body).ljust(128, b"\0")


def test_eeprom_interface_reads_identity():
    esc = Esc(4, PROFILES["indy7"])
    assert _read(esc, 0x0502, 2) == b"\x40\x00"  # 8-byte reads, not busy
    _write(esc, 0x0502, struct.pack("<HI", 0x0100, 0x08))
    vendor, product = struct.unpack("<II", _read(esc, 0x0508, 8))
    assert (vendor, product) == (PROFILES["indy7"].vendor_id, PROFILES["indy7"].product_code)
    _write(esc, 0x0502, struct.pack("<HI", 0x0100, 0x0E))
    assert struct.unpack("<I", _read(esc, 0x0508, 4))[0] == 5  # serial = position + 1


def test_sii_categories_in_order():
    sii = Esc(0).sii
    word, cats = 0x40, []
    while True:
        cat, size = struct.unpack_from("<HH", sii, word * 2)
        cats.append(cat)
        if cat == SiiCategory.END:
            break
        word += 2 + size
    assert cats == [10, 30, 40, 41, 50, 51, 0xFFFF]
    assert struct.unpack_from("<H", sii, 0x1C * 2)[0] == 0x0004


def test_read_only_registers_survive_writes():
    esc = Esc(0)
    _write(esc, 0x0000, b"\xff" * 16)
    _write(esc, 0x0130, b"\x08\x00")
    assert _read(esc, 0x0000, 1) == b"\x11" and _read(esc, 0x0130, 2) == b"\x01\x00"


def test_mailbox_counter_dedupe_and_repeat_request():
    esc = _preop()
    assert _read(esc, 0x1080, 128) is None  # empty SM1: no WKC
    assert _write(esc, 0x1000, _upload_request(0x1018, 1, counter=1))
    reply = _read(esc, 0x1080, 128)
    assert reply is not None and reply[8] == 0x43
    assert struct.unpack_from("<I", reply, 12)[0] == PROFILES["generic"].vendor_id
    assert _write(esc, 0x1000, _upload_request(0x1018, 1, counter=1))  # resend: ignored
    assert _read(esc, 0x1080, 128) is None
    act = _read(esc, 0x080D, 2)
    _write(esc, 0x080D, bytes([act[0], act[1] ^ 0x02]))  # repeat request
    assert _read(esc, 0x080F, 1)[0] & 0x02 == (act[1] ^ 0x02) & 0x02
    assert _read(esc, 0x1080, 128) == reply


def test_mailbox_refused_in_init_and_unknown_protocol():
    esc = Esc(0)
    _write(esc, 0x0800, SM0_CONFIG)
    assert not _write(esc, 0x1000, _upload_request(0x1018, 1, 1))  # INIT: no WKC
    esc = _preop()
    _write(esc, 0x1000, (struct.pack("<HHBB", 4, 0, 0, 0x14) + b"\0" * 4).ljust(128, b"\0"))  # FoE
    reply = _read(esc, 0x1080, 128)
    assert reply[5] & 0x0F == 0 and struct.unpack_from("<HH", reply, 6) == (1, 2)  # unsupported protocol


def test_invalid_state_change_and_ack():
    esc = Esc(0)
    _write(esc, 0x0120, b"\x08\x00")  # INIT -> OP
    assert _read(esc, 0x0130, 6) == struct.pack("<HHH", 0x11, 0, 0x0011)
    _write(esc, 0x0120, b"\x02\x00")  # no ack: ignored while the error is shown
    assert esc.al_state == ALState.INIT and esc.al_error
    _write(esc, 0x0120, b"\x12\x00")  # ack + PRE-OP, but SM0/SM1 not configured
    assert _read(esc, 0x0130, 6) == struct.pack("<HHH", 0x11, 0, 0x0016)


def test_broadcast_read_counts_and_auto_increment():
    seg = Segment(3)
    frame = bytearray(b"\xff" * 6 + b"\x01" * 6 + b"\x88\xa4")
    frame += struct.pack("<H", (10 + 2 + 2) | 0x1000)
    frame += struct.pack("<BBHHHH", Cmd.BRD, 0, 0, 0x0000, 2, 0) + b"\0\0" + b"\0\0"
    frame = frame.ljust(60, b"\0")
    assert seg.process(memoryview(frame), len(frame), 0.0)
    assert struct.unpack_from("<H", frame, 28)[0] == 3  # WKC = slave count
    assert frame[6] & 0x02  # source MAC marked
    seg.unplug(1)
    frame[28:30] = b"\0\0"
    seg.process(memoryview(frame), len(frame), 0.0)
    assert struct.unpack_from("<H", frame, 28)[0] == 2
