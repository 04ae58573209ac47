"""The cycle's management thread: what may wait on a slave, off the cycle thread.

AL status reads, AL control writes (NMT) and step-wise recovery of lost slaves run here while
the cycle thread keeps exchanging process data, so a slave that does not answer never stalls the
others (their SM watchdogs would trip). SOEM makes the two threads' datagrams safe: each has its
own frame index. Used only by :class:`bus_agent.cycle.cycle.Cycle`.
"""

from __future__ import annotations

import collections
import logging
import struct
import threading
from dataclasses import dataclass
from typing import Callable

from bus_agent.bus.base import ALState, Bus, NoAnswer, SlaveALStatus
from bus_agent.cycle.realtime import name_thread, set_thread_fifo

log = logging.getLogger(__name__)

#: While something is wrong (working counter, a lost slave, an NMT command), read every slave's
#: AL status this often (cycles). While the working counter is right, nothing is read: an LRW
#: counts 3 per slave only from slaves in OP (ETG.1000.4: +1 read in SAFE-OP/OP, +2 write in OP),
#: so the counter already proves every slave in OP, and a management datagram would hold the GIL
#: (pysoem's primitives do not release it) in the cycle thread's way.
AL_POLL_MIN_CYCLES = 10
#: Call bus.recover() for a lost slave every this many cycles (each call is a few round trips).
RECOVER_EVERY_CYCLES = 10
#: While a mode written by SDO (0x6060) waits for its echo, read 0x6061 by SDO this often.
MODE_POLL_NS = 5_000_000
#: Reads of an SDO job tried this often before its error is reported.
SDO_ATTEMPTS = 5
#: A bus with mailboxes (``poll_mailbox``, EtherCAT CoE): one slave's mailbox is read this often,
#: in turn, for emergencies that no SDO transfer picked up (a drive's warning). A drive that
#: enters Fault has its mailbox read at once (an SdoJob of kind "mailbox").
MAILBOX_POLL_NS = 100_000_000


@dataclass
class SdoJob:
    """An object served by SDO because the drive does not map it (never on the cycle thread).

    ``kind`` "mailbox": read the slave's mailbox once (its emergency); "mode": write 0x6060 = ``value`` (unless ``written``: it is in the PDOs), then read 0x6061 every :data:`MODE_POLL_NS` until
    it echoes or ``deadline_ns``; "error_code": read 0x603F once; "write": download ``writes``
    ((index, subindex, data), in order, stopping at the first refusal; homing parameters).
    Reports ``("sdo", slave, what, value, error, definite)`` with what = "mode_write" (error
    only), "mode_display", "error_code" or "written" (error: '' or the refused object and abort;
    definite: the error is the slave's own answer, an abort or a mailbox error, not a transfer
    without answer). Only a transfer without answer (:class:`NoAnswer`) is made again."""

    slave: int
    kind: str
    value: int = 0
    deadline_ns: int = 0
    next_ns: int = 0
    written: bool = False
    attempts: int = 0
    writes: tuple[tuple[int, int, bytes], ...] = ()


class Management:
    """AL status reads, AL state requests and lost-slave recovery, off the cycle thread.

    Runs in its own thread while the cycle thread runs (:meth:`start`), or inline from
    :meth:`Cycle.tick` (:meth:`run_once`, tests and tools). The cycle posts requests (plain
    attributes and a deque; :meth:`kick` wakes the thread) and drains :attr:`reports` in order:
    ``("al", statuses, ticket)`` -- the AL status of every slave, read after the AL requests up
    to ``ticket`` were written -- and ``("returned", slave, epoch)`` -- a slave of the recover
    set is back in OP. Nothing here touches drives, controllers or snapshots.
    """

    def __init__(self, bus: Bus, clock_ns: Callable[[], int], period_ns: int, host: str) -> None:
        self.bus = bus
        self.rt_priority = 0  # SCHED_FIFO of this thread: set by the cycle (one below its own)
        self.clock_ns = clock_ns
        self.host = host
        self.fast_ns = AL_POLL_MIN_CYCLES * period_ns
        self.recover_ns = RECOVER_EVERY_CYCLES * period_ns
        # cycle -> management (written by the cycle thread only)
        self.fast = False
        self.recover_set: frozenset[tuple[int, int]] = frozenset()  # (slave, epoch)
        self.requests: collections.deque[tuple[int, int | None, ALState, str]] = collections.deque()
        self.sdo_requests: collections.deque[SdoJob] = collections.deque()
        self._sdo_jobs: list[SdoJob] = []
        self.tickets = 0
        self._poll_asap = True
        # management -> cycle
        self.reports: collections.deque[tuple] = collections.deque()
        self._done_ticket = 0
        self._last_poll_ns: int | None = None
        self._next_recover: dict[int, int] = {}
        self._reported: set[tuple[int, int]] = set()
        self._poll_mailbox: Callable[[int | None], None] | None = getattr(bus, "poll_mailbox", None)
        self._next_mailbox_ns = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # cycle side
    def kick(self) -> None:
        """Read the AL status as soon as possible."""
        self._poll_asap = True
        self._wake.set()

    def wake(self) -> None:
        self._wake.set()

    def request_state(self, slave: int | None, state: ALState, nmt: str = "") -> int:
        """Queue an AL control write (one slave or all); returns its ticket. ``nmt``: the agent's
        NMT command it serves, for a bus that has its own (``bus.request_nmt``, CANopen)."""
        self.tickets += 1
        self.requests.append((self.tickets, slave, state, nmt))
        self.kick()
        return self.tickets

    def sdo(self, job: SdoJob) -> None:
        """Queue an SDO job (a newer mode job of the same slave replaces the older one)."""
        self.sdo_requests.append(job)
        self._wake.set()

    # management side
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"cycle-mgmt-{self.host}", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the thread (idempotent); the bus is the cycle's again afterwards."""
        self._stop.set()
        self._wake.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout_s)
            if t.is_alive():
                log.error("host %s: management thread did not stop", self.host)

    @property
    def threaded(self) -> bool:
        return self._thread is not None

    def _run(self) -> None:
        set_thread_fifo(self.rt_priority, f"the management thread of {self.host}")
        name_thread(f"mgmt-{self.host}")
        while not self._stop.is_set():
            self._wake.clear()
            try:
                self.run_once(self.clock_ns())
            except Exception:  # keep managing: one failed step must not end recovery for good
                log.exception("host %s: management step failed", self.host)
            now = self.clock_ns()
            # Steady state (working counter right): no poll due; a kick or wake starts one.
            due = (self._last_poll_ns or now) + self.fast_ns if self.fast else now + 100_000_000
            for _slave, _epoch in self.recover_set:
                due = min(due, self._next_recover.get(_slave, now))
            for job in self._sdo_jobs:
                due = min(due, job.next_ns)
            if self._poll_mailbox is not None:
                due = min(due, self._next_mailbox_ns)
            self._wake.wait(min(max(due - now, 200_000), 100_000_000) / 1e9)

    def run_once(self, now_ns: int) -> None:
        """Due work: queued AL requests, then an AL status read, then recover steps."""
        bus = self.bus
        while self.requests:
            ticket, slave, state, nmt = self.requests.popleft()
            request_nmt = getattr(bus, "request_nmt", None) if nmt else None
            try:
                if request_nmt is not None:
                    request_nmt(slave, nmt)
                else:
                    bus.request_al_state(slave, state)
            except Exception as e:
                log.warning("host %s: AL %s request for %s failed: %s", self.host, state.wire_name,
                            "all slaves" if slave is None else f"slave {slave}", e)
            self._done_ticket = ticket
        if (self._poll_asap or self._last_poll_ns is None
                or (self.fast and now_ns - self._last_poll_ns >= self.fast_ns)):
            self._poll_asap = False
            self._last_poll_ns = now_ns
            ticket = self._done_ticket
            try:
                statuses: tuple[SlaveALStatus, ...] | None = tuple(bus.read_al_status())
            except Exception as e:
                log.warning("host %s: AL status read failed: %s", self.host, e)
                statuses = None
            self.reports.append(("al", statuses, ticket))
        self._run_sdo_jobs(now_ns)
        if self._poll_mailbox is not None and now_ns >= self._next_mailbox_ns:
            self._next_mailbox_ns = now_ns + MAILBOX_POLL_NS
            self._read_mailbox(None)  # the next slave in turn
        keys = self.recover_set
        self._reported &= keys
        for key in sorted(keys):
            if key in self._reported or self._stop.is_set():
                continue
            slave = key[0]
            if now_ns < self._next_recover.get(slave, 0):
                continue
            self._next_recover[slave] = now_ns + self.recover_ns
            try:
                back = bus.recover(slave)
            except Exception as e:
                log.debug("host %s: slave %d recover: %s", self.host, slave, e)
                back = False
            if back:
                self._reported.add(key)
                self.reports.append(("returned", slave, key[1]))

    def _run_sdo_jobs(self, now_ns: int) -> None:
        while self.sdo_requests:
            job = self.sdo_requests.popleft()
            if job.kind == "mode":
                self._sdo_jobs = [j for j in self._sdo_jobs if not (j.slave == job.slave and j.kind == "mode")]
            self._sdo_jobs.append(job)
        if not self._sdo_jobs:
            return
        keep = []
        for job in self._sdo_jobs:
            if now_ns < job.next_ns:
                keep.append(job)
            elif self._sdo_step(job, now_ns):
                job.next_ns = now_ns + MODE_POLL_NS
                keep.append(job)
        self._sdo_jobs = keep

    def _read_mailbox(self, slave: int | None) -> None:
        assert self._poll_mailbox is not None
        try:
            self._poll_mailbox(slave)
        except Exception as e:  # a slave being recovered or gone: its AL status says so
            log.debug("host %s: %s", self.host, e)

    def _sdo_step(self, job: SdoJob, now_ns: int) -> bool:
        """One step of a job; True while it is not finished."""
        bus = self.bus
        if job.kind == "mailbox":
            if self._poll_mailbox is not None:
                self._read_mailbox(job.slave)
            return False
        if job.kind == "write":
            error = ""
            for index, subindex, data in job.writes:
                try:
                    bus.sdo_write(job.slave, index, subindex, data)
                except Exception as e:  # the abort code names why; later objects are not written
                    error = f"0x{index:04X}:{subindex}: {e}"
                    break
            self.reports.append(("sdo", job.slave, "written", None, error, bool(error)))
            return False
        try:
            if job.kind == "error_code":
                raw = bus.sdo_read(job.slave, 0x603F, 0, 2)
                self.reports.append(("sdo", job.slave, "error_code", struct.unpack("<H", bytes(raw)[:2])[0], "", False))
                return False
            if not job.written:
                job.written = True
                bus.sdo_write(job.slave, 0x6060, 0, struct.pack("<b", job.value))
            raw = bus.sdo_read(job.slave, 0x6061, 0, 1)
        except Exception as e:  # BusError with the abort code: the cycle answers the command with it
            what = job.kind if job.kind == "error_code" else ("mode_write" if "0x6060" in str(e) else "mode_display")
            job.attempts += 1
            # Only a transfer without an answer (a mailbox timeout under load) is made again; an
            # abort or a mailbox error is the drive's definite answer: reported at once
            lost = isinstance(e, NoAnswer)
            if what == "mode_write" and lost:
                job.written = False  # write again
            if lost and (what != "mode_write" or not job.written) and job.attempts < SDO_ATTEMPTS \
                    and now_ns < job.deadline_ns:
                return True
            self.reports.append(("sdo", job.slave, what, None, str(e), not lost))
            return False
        value = struct.unpack("<b", bytes(raw)[:1])[0]
        self.reports.append(("sdo", job.slave, "mode_display", value, "", False))
        return value != job.value and now_ns < job.deadline_ns
