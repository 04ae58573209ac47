"""The management thread's SDO jobs for a mode the drive does not map (0x6060 by SDO): a
download that gets no answer (a mailbox timeout) is written again; a refusal (abort) is final."""

from __future__ import annotations

import struct

from bus_agent.bus.base import BusError, NoAnswer
from bus_agent.cycle.management import Management, SdoJob


class MailboxBus:
    """0x6060/0x6061 by SDO; the first ``timeouts`` downloads get no answer, or every one is refused."""

    def __init__(self, timeouts: int = 0, refuse: bool = False) -> None:
        self.timeouts, self.refuse, self.mode, self.writes = timeouts, refuse, 0, 0

    def sdo_write(self, slave: int, index: int, subindex: int, data: bytes) -> None:
        self.writes += 1
        if self.refuse:
            raise BusError(f"slave {slave}: SDO download 0x{index:04X}:{subindex} aborted 0x06090030 (value range)")
        if self.timeouts:
            self.timeouts -= 1
            raise NoAnswer(f"slave {slave}: SDO download 0x{index:04X}:{subindex} failed: no answer")
        self.mode = struct.unpack("<b", data)[0]

    def sdo_read(self, slave: int, index: int, subindex: int, size: int) -> bytes:
        return struct.pack("<b", self.mode)


def _run(bus: MailboxBus) -> list:
    m = Management(bus, lambda: 0, 1_000_000, "h1")  # type: ignore[arg-type]
    job = SdoJob(0, "mode", 8, deadline_ns=10**9)
    steps = 0
    while m._sdo_step(job, 0) and steps < 20:
        steps += 1
    return list(m.reports)


def test_a_mode_download_without_answer_is_written_again_until_echoed():
    bus = MailboxBus(timeouts=2)
    reports = _run(bus)
    assert bus.writes == 3 and bus.mode == 8
    assert reports[-1] == ("sdo", 0, "mode_display", 8, "", False)
    assert not any(r[2] == "mode_write" for r in reports)


def test_a_refused_mode_download_is_reported_once_and_not_retried():
    bus = MailboxBus(refuse=True)
    reports = _run(bus)
    assert bus.writes == 1
    assert [r[2] for r in reports] == ["mode_write"] and "aborted 0x06090030" in reports[0][4]
    assert reports[0][5] is True  # definite


class AbortingBus:
    """0x603F and 0x6061 uploads: each is refused (abort 0x06020000), or gets no answer."""

    def __init__(self, lost: bool = False) -> None:
        self.lost, self.reads = lost, 0

    def sdo_read(self, slave: int, index: int, subindex: int, size: int) -> bytes:
        self.reads += 1
        if self.lost:
            raise NoAnswer(f"slave {slave}: SDO upload 0x{index:04X}:{subindex} failed: no answer")
        raise BusError(f"slave {slave}: SDO upload 0x{index:04X}:{subindex} aborted 0x06020000 (object does not exist)")


def _run_job(bus, job: SdoJob) -> list:
    m = Management(bus, lambda: 0, 1_000_000, "h1")  # type: ignore[arg-type]
    steps = 0
    while m._sdo_step(job, 0) and steps < 20:
        steps += 1
    return list(m.reports)


def test_an_aborted_upload_is_reported_at_once_and_one_without_answer_is_read_again():
    """A definite answer (an abort: the object does not exist) is the same when asked again."""
    for kind in ("error_code", "mode_display"):
        bus = AbortingBus()
        job = SdoJob(0, kind, 8, deadline_ns=10**9)
        job.written = True
        reports = _run_job(bus, job)
        assert bus.reads == 1, kind
        assert len(reports) == 1 and "aborted 0x06020000" in reports[0][4]
        assert reports[0][5] is True  # the drive's definite answer: the cycle turns to its EMCY
    bus = AbortingBus(lost=True)
    reports = _run_job(bus, SdoJob(0, "error_code", deadline_ns=10**9))
    assert bus.reads > 1 and "no answer" in reports[-1][4] and reports[-1][5] is False


class PolledBus:
    """A bus with mailboxes: records each poll_mailbox call; the second one fails."""

    def __init__(self) -> None:
        self.polls: list[int | None] = []

    def poll_mailbox(self, position: int | None) -> None:
        self.polls.append(position)
        if len(self.polls) == 2:
            raise BusError("slave 1: mailbox read failed: WkcError")

    def read_al_status(self):
        return ()


def test_mailboxes_are_read_in_turn_every_poll_period_and_at_once_for_a_job():
    """One mailbox (the bus's next in turn) per MAILBOX_POLL_NS, a failed read logged and the
    schedule kept; a "mailbox" job (a drive entered Fault) reads that slave's at once."""
    from bus_agent.cycle.management import MAILBOX_POLL_NS

    bus = PolledBus()
    m = Management(bus, lambda: 0, 1_000_000, "h1")  # type: ignore[arg-type]
    for now in (0, 1, MAILBOX_POLL_NS - 1, MAILBOX_POLL_NS, MAILBOX_POLL_NS + 5, 2 * MAILBOX_POLL_NS):
        m.run_once(now)
    assert bus.polls == [None, None, None]
    m.sdo(SdoJob(3, "mailbox"))
    m.run_once(2 * MAILBOX_POLL_NS + 1)
    assert bus.polls == [None, None, None, 3] and not m._sdo_jobs
    assert not [r for r in m.reports if r[0] == "sdo"]  # a mailbox read reports nothing itself


def test_a_bus_without_mailboxes_is_never_polled():
    m = Management(MailboxBus(), lambda: 0, 1_000_000, "h1")  # type: ignore[arg-type]
    m.sdo(SdoJob(0, "mailbox"))
    m.run_once(0)
    assert not m._sdo_jobs and m._poll_mailbox is None
