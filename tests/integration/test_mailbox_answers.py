"""Definite mailbox answers are reported at once with their meaning; only a lost answer is asked
again (issue 23, item 10), over pysoem against ``ecat-sim``.

- a slave without a mailbox (``generic:no-mailbox``: SII mailbox sizes 0) is named as such before
  any transfer, not reported as "no answer from the slave's mailbox" after three tries;
- a mailbox without CoE (``generic:no-coe``) likewise; and its answer to a CoE request (the
  mailbox error "mailbox protocol not supported") is a definite answer: not asked again;
- an SDO abort is reported at once with its code and meaning.
"""

from __future__ import annotations

import logging

import pytest

from bus_agent.bus.base import BusError, NoAnswer
from bus_agent.bus.mailbox import transfer_failure
from bus_agent.bus.pysoem_bus import PysoemBus

pytestmark = [pytest.mark.root, pytest.mark.timeout(120)]


@pytest.fixture
def opened(ecat_segment):
    buses: list[PysoemBus] = []

    def make(profile: str, n: int = 2) -> PysoemBus:
        ifname, _control = ecat_segment(n, profile)
        bus = PysoemBus(ifname)
        buses.append(bus)
        bus.open()
        return bus

    yield make
    for bus in buses:
        bus.close()


def _retries(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "trying again" in r.getMessage()]


def test_a_slave_without_a_mailbox_is_named_at_once(opened, caplog):
    caplog.set_level(logging.INFO)
    bus = opened("generic,generic:no-mailbox")
    with pytest.raises(BusError) as err:
        bus.start()
    text = str(err.value)
    assert "slave 1 ('SimDrive402') has no mailbox (its SII gives mailbox sizes 0/0 bytes): no CoE" in text
    assert "no answer" not in text and "slave 0" not in text
    assert not _retries(caplog)
    with pytest.raises(BusError, match="SDO upload 0x1018:1: slave 1 has no mailbox") as err:
        bus.sdo_read(1, 0x1018, 1, 4)
    assert not isinstance(err.value, NoAnswer)
    assert len(bus.sdo_read(0, 0x1018, 1, 4)) == 4  # the other slave answers


def test_a_mailbox_without_coe_is_named_at_once_and_its_error_answer_is_not_asked_again(opened, caplog):
    caplog.set_level(logging.INFO)
    bus = opened("generic,generic:no-coe")
    with pytest.raises(BusError, match=r"slave 1 \('SimDrive402'\) its mailbox does not offer CoE "
                                       r"\(SII mailbox protocols: FoE\): no SDO"):
        bus.start()
    assert not _retries(caplog)
    # Its answer to a CoE request, should one be sent anyway: the mailbox error, a definite answer.
    slave = bus._slaves[1]
    sent = []

    def upload() -> bytes:
        sent.append(1)
        return slave.sdo_read(0x1018, 1, 4, release_gil=True)

    with pytest.raises(BusError) as err:
        bus._startup.sdo(0, upload, "slave 1: SDO upload 0x1018:1", attempts=3)
    assert sent == [1] and not _retries(caplog)
    assert str(err.value) == "slave 1: SDO upload 0x1018:1 failed: mailbox error 0x0002: mailbox protocol not supported"
    assert not isinstance(err.value, NoAnswer)
    try:
        slave.sdo_read(0x1018, 1, 4)
    except Exception as e:  # pysoem's own exception, as it comes from the wire
        assert transfer_failure(e) == ("mailbox error 0x0002: mailbox protocol not supported", False)
    else:
        raise AssertionError("a mailbox without CoE answered a CoE request")


def test_an_sdo_abort_is_reported_at_once_with_its_meaning(opened, caplog):
    caplog.set_level(logging.INFO)
    bus = opened("generic", 1)
    bus.start()
    with pytest.raises(BusError) as err:
        bus.sdo_read(0, 0x7777, 0, 2)
    assert "SDO upload 0x7777:0 aborted 0x06020000" in str(err.value) and not isinstance(err.value, NoAnswer)
    assert not _retries(caplog)
