"""ecat-sim's malformed SII (``bad_sii``) and mailbox-less SII, read as SOEM reads them.

``soem_siifind`` follows SOEM's ``ecx_siifind``: a signed 16-bit byte address, a category's
length added as ``len << 1``. The loop category must send it back to its own header for ever,
and only a search for a category placed after it."""

from __future__ import annotations

import struct

import pytest

from bus_agent.sim.ecat.esc import Esc
from bus_agent.sim.ecat.profiles import PROFILES, as_ecat
from bus_agent.sim.ecat.sii import SiiCategory, categories, looping_sii, without_mailbox


def soem_siifind(image: bytes, cat: int, max_steps: int = 10_000) -> int | None:
    """Byte address after the header of ``cat`` (0 when absent), None when the walk loops."""
    def byte(a: int) -> int:
        a &= 0xFFFF
        return image[a] if a < len(image) else 0xFF

    a = 0x40 << 1
    p = byte(a) | byte(a + 1) << 8
    a += 2
    for _ in range(max_steps):
        if p in (cat, 0xFFFF):
            return a if p == cat else 0
        length = byte(a) | byte(a + 1) << 8
        a += 2
        a = ((a + (length << 1)) + 0x8000) % 0x10000 - 0x8000  # int16 wrap-around
        p = byte(a) | byte(a + 1) << 8
        a += 2
    return None


def _sii() -> bytes:
    return bytes(Esc(0, PROFILES["generic"]).sii)


def test_a_good_sii_has_every_category_soem_looks_for():
    image = _sii()
    for cat in (SiiCategory.STRINGS, SiiCategory.GENERAL, SiiCategory.FMMU, SiiCategory.SM, SiiCategory.TXPDO):
        assert soem_siifind(image, cat), cat


@pytest.mark.parametrize("before, loops, found", [
    ("general", (SiiCategory.GENERAL, SiiCategory.SM, SiiCategory.TXPDO), (SiiCategory.STRINGS,)),
    ("pdo", (SiiCategory.TXPDO, SiiCategory.RXPDO), (SiiCategory.GENERAL, SiiCategory.FMMU, SiiCategory.SM)),
])
def test_the_loop_category_sends_soem_round_for_ever_after_it_only(before, loops, found):
    bad = looping_sii(_sii(), before)
    assert len(bad) == len(_sii())
    for cat in loops:
        assert soem_siifind(bad, cat) is None, cat
    for cat in found:
        assert soem_siifind(bad, cat), cat


def test_an_unknown_place_is_refused():
    with pytest.raises(ValueError, match="before must be one of general, pdo"):
        looping_sii(_sii(), "strings")


def test_a_slave_without_mailbox_has_no_mailbox_words_and_no_mailbox_sms():
    image = without_mailbox(_sii())
    assert struct.unpack_from("<5H", image, 0x18 * 2) == (0, 0, 0, 0, 0)
    sm = next(a for a, cat, _ in categories(image) if cat == SiiCategory.SM)
    assert [image[sm + 4 + 8 * k + 7] for k in range(4)] == [0, 0, 3, 4]  # SM types: unused, unused, out, in
    esc = Esc(0, as_ecat("generic:no-mailbox"))
    assert bytes(esc.sii) == image and not esc.has_mailbox
    coe = Esc(0, as_ecat("generic:no-coe"))
    assert struct.unpack_from("<H", coe.sii, 0x1C * 2)[0] == 0x0008 and not coe.mailbox.coe
