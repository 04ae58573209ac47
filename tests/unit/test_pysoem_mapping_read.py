"""The pysoem backend's reading of a drive's PDO mapping when mailbox answers come late.

SOEM's SDO upload first reads one message out of the slave's mailbox (a leftover), sends the
request, then takes the next answer whose index matches: not its subindex. An answer that comes
after SOEM gave up on its upload can so be taken for a later upload of the same object. A
stand-in slave (a unit test of the reading logic; test_real_drives runs the real thing over
ecat-sim) models that mailbox; the backend must never build a codec from such a read."""

from __future__ import annotations

import collections
import struct

import pysoem
import pytest

from bus_agent.bus.base import BusError
from bus_agent.bus.mapping import check_mapping, mapping_entry, mapping_of, read_mapping
from bus_agent.bus.pysoem_bus import PysoemBus

RX_ENTRIES = [mapping_entry(0x6040, 0, 16), mapping_entry(0x607A, 0, 32)]
TX_ENTRIES = [mapping_entry(0x6041, 0, 16), mapping_entry(0x6064, 0, 32), mapping_entry(0x606C, 0, 32)]
OBJECTS = {0x1C12: [1, 0x1600], 0x1600: [len(RX_ENTRIES), *RX_ENTRIES],
           0x1C13: [1, 0x1A00], 0x1A00: [len(TX_ENTRIES), *TX_ENTRIES]}
WANT = mapping_of([(0x1600, RX_ENTRIES)], [(0x1A00, TX_ENTRIES)])


class LateSlave:
    """Uploads of OBJECTS through a mailbox. Each (index, subindex, delay) in ``late`` (one per
    occurrence) makes that upload fail: its answer arrives only after ``delay`` more requests
    were sent (after their first read of the mailbox)."""

    name = "Late"

    def __init__(self, late: list[tuple[int, int, int]]) -> None:
        self.late = list(late)
        self.mailbox: collections.deque[tuple[int, bytes]] = collections.deque()
        self.in_flight: list[list] = []  # [requests to go, index, value]

    @staticmethod
    def _value(index: int, sub: int) -> bytes:
        if index == 0x6502:
            return struct.pack("<I", 0x2D)
        v = OBJECTS[index][sub]
        return bytes([v]) if sub == 0 else struct.pack("<I" if index in (0x1600, 0x1A00) else "<H", v)

    def sdo_read(self, index: int, sub: int, size: int, release_gil: bool = False) -> bytes:
        if self.mailbox:
            self.mailbox.popleft()  # SOEM empties the mailbox (one message) first
        for f in self.in_flight:
            f[0] -= 1
        self.mailbox.extend((f[1], f[2]) for f in self.in_flight if f[0] <= 0)  # late answers arrive
        self.in_flight = [f for f in self.in_flight if f[0] > 0]
        value = self._value(index, sub)
        delay = next((d for i, s, d in self.late if (i, s) == (index, sub)), None)
        if delay is not None:
            self.late.remove((index, sub, delay))
            self.in_flight.append([delay, index, value])
            raise pysoem.WkcError()
        self.mailbox.append((index, value))
        got_index, got = self.mailbox.popleft()
        if got_index != index:
            raise pysoem.WkcError()  # SOEM: an answer for another object, the upload fails
        return got


def _configure(slave: LateSlave) -> object:
    bus = PysoemBus("none")
    bus._startup.slaves = [slave]
    return bus._startup.configure_slave(0)


def test_the_stand_in_gives_a_plain_read_a_wrong_mapping():
    """0x1A00:02's answer comes two requests late: a plain read with retries maps 0x6064 twice
    and loses 0x606C (0x1A00:03 takes it); check_mapping refuses that mapping."""
    slave = LateSlave([(0x1A00, 2, 2)])

    def read(index: int, sub: int, size: int) -> bytes:
        for _ in range(3):
            try:
                return slave.sdo_read(index, sub, size)
            except pysoem.WkcError:
                continue
        raise AssertionError("no answer")

    m = read_mapping(read)
    assert [e.index for e in m.tx] == [0x6041, 0x6064, 0x6064]
    assert check_mapping(m) == ["0x6064:00 is mapped twice in the inputs (TxPDO)"]


@pytest.mark.parametrize("late", [
    [(0x1A00, 2, 2)],                    # 0x1A00:03 would take 0x1A00:02's entry
    [(0x1A00, 0, 2)],                    # 0x1A00:01 would take a 1-byte answer (sub 0) for its u32
    [(0x1600, 1, 1), (0x1600, 1, 3), (0x1A00, 1, 2)],
    [(0x1C13, 1, 1)],
    [],
])
def test_the_backend_reads_until_it_has_the_slaves_own_mapping(late):
    assert _configure(LateSlave(late)) == WANT


def test_answers_that_never_agree_are_an_error_naming_the_slave():
    class Flaky(LateSlave):
        def sdo_read(self, index, sub, size, release_gil=False):
            if (index, sub) == (0x1A00, 3):
                self.late.append((0x1A00, 3, 1))  # late every time
            return super().sdo_read(index, sub, size, release_gil)

    with pytest.raises(BusError, match=r"slave 0 \('Late'\): .*SDO upload 0x1A00:03 failed: WkcError"):
        _configure(Flaky([]))
