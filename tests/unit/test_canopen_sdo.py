"""The CANopen SDO adapter's failures: an abort is the node's definite answer (SdoError), no
valid answer a NoAnswer (the only retry rule); both caught as SDO_FAILURES, told apart by the code."""

from __future__ import annotations

import pytest
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from bus_agent.bus.base import BusError, NoAnswer
from bus_agent.bus.canopen import sdo


class Client:
    def __init__(self, error: Exception) -> None:
        self.error = error

    def upload(self, index: int, subindex: int) -> bytes:
        raise self.error

    def download(self, index: int, subindex: int, data: bytes) -> None:
        raise self.error


def test_an_abort_is_an_sdo_error_with_its_code_and_not_retried():
    with pytest.raises(sdo.SDO_FAILURES) as err:
        sdo.read(Client(SdoAbortedError(0x06020000)), 3, 0x6061, 0)  # type: ignore[arg-type]
    e = err.value
    assert isinstance(e, sdo.SdoError) and isinstance(e, BusError) and not isinstance(e, NoAnswer)
    assert e.abort_code == 0x06020000
    assert str(e) == "node 3: SDO read 0x6061:0 aborted with 0x06020000 (Object does not exist)"


def test_no_answer_is_a_no_answer_with_code_0():
    with pytest.raises(sdo.SDO_FAILURES) as err:
        sdo.write(Client(SdoCommunicationError("timeout")), 5, 0x6060, 0, b"\x08")  # type: ignore[arg-type]
    e = err.value
    assert isinstance(e, NoAnswer) and isinstance(e, BusError) and not isinstance(e, sdo.SdoError)
    assert e.abort_code == 0
    assert str(e) == "node 5: SDO write 0x6060:0 (no valid answer: timeout)"


def test_the_identity_is_not_taken_without_an_answer():
    def read(index: int, sub: int) -> bytes:
        if sub == 1:
            return b"\x01\x00\x00\x00"
        raise sdo.SdoNoAnswer(2, "read", index, sub, "no valid answer: timeout")

    with pytest.raises(sdo.SdoNoAnswer):
        sdo.read_identity(read)
