"""The mailbox SyncManagers of a simulated ESC (a part :class:`bus_agent.sim.ecat.esc.Esc` owns):
SM0 (master -> slave) and SM1 (slave -> master), their full flags and status registers, SM1's
repeat toggle, and the CoE mailbox behind them (ETG.1000.4 §6.7.2, ETG.1000.6 §5.6).
"""

from __future__ import annotations

import logging
from typing import Callable

from bus_agent.sim.ecat.coe import Mailbox

log = logging.getLogger("bus_agent.sim.ecat.esc")

SM0 = 0x0800
SM_STATUS_MBX_FULL = 0x08


class MailboxSms:
    """SM0 and SM1 over the ESC's memory ``mem`` (``set8`` writes a read-only register).

    ``out``: SM0 at (start, size), the master's requests; ``in_``: SM1, the replies."""

    def __init__(self, position: int, mem: bytearray, set8: Callable[[int, int], None], mailbox: Mailbox,
                 out: tuple[int, int], in_: tuple[int, int]) -> None:
        self.position = position
        self._mem = mem
        self._mv = memoryview(mem)
        self._set8 = set8
        self.mailbox = mailbox
        self.out_start, self.out_size = out
        self.in_start, self.in_size = in_
        #: Where each SM ends: the ESC checks a datagram against these itself (its hot path)
        self.out_end, self.in_end = self.out_start + self.out_size, self.in_start + self.in_size
        self.reset()

    def reset(self) -> None:
        """Power-on: both SMs off and empty, no repeat requested."""
        self.enabled = [False, False]
        self.repeat = 0
        self.out_full = False
        self.in_full = False

    def empty(self) -> None:
        """Both SMs empty (the slave back in INIT)."""
        self.in_full = self.out_full = False
        self.render_status()

    def enable(self, k: int, enabled: bool) -> None:
        """SM ``k`` (0 or 1) switched on or off by the master: it empties; an enabled SM1 takes a reply."""
        self.enabled[k] = enabled
        if k == 0:
            self.out_full = False
        else:
            self.in_full = False
            if enabled:
                self.offer()

    def repeat_written(self, repeat: int) -> None:
        """SM1's repeat request (0x080E bit 1) as the master wrote it."""
        if repeat != self.repeat:
            self.repeat = repeat
            # The master lost the last reply (read with WKC 0): offer it again if SM1 is empty.
            if not self.in_full and self.mailbox.last_sent is not None and self.enabled[1]:
                self._put(self.mailbox.last_sent)

    def read(self, ado: int, end: int, dst: memoryview) -> bool:
        """A read of [ado, end) that touches SM1, enabled: False (no WKC, data untouched) while
        SM1 is empty; True once copied (its last byte read empties SM1)."""
        if not self.in_full:
            return False
        dst[:] = self._mv[ado:end]
        if end >= self.in_end:  # last byte read: SM1 empties
            self.in_full = False
            self.render_status()
            self.offer()
        return True

    def write(self, ado: int, end: int, src: memoryview, init: bool) -> bool:
        """A write of [ado, end) that touches SM0, enabled: False (no WKC) while SM0 is full or
        the slave is in INIT (``init``); True once taken (its last byte hands the request to the
        mailbox)."""
        if self.out_full or init:
            return False
        self._mv[ado:end] = src[: end - ado]
        if end >= self.out_end:
            self._written()
        return True

    def _written(self) -> None:
        self.out_full = True
        self.render_status()
        try:
            self.mailbox.request(self._mv[self.out_start:self.out_start + self.out_size])
        except Exception:  # a broken request must never stop the segment
            log.exception("slave %d: mailbox request failed", self.position)
        self.out_full = False  # the application consumed it at once
        self.render_status()
        self.offer()

    def offer(self) -> None:
        """Move the next queued reply into SM1 if it is enabled and empty."""
        if self.in_full or not self.enabled[1] or not self.mailbox.queue:
            return
        self._put(self.mailbox.queue.popleft())

    def _put(self, frame: bytes) -> None:
        self.mailbox.last_sent = frame
        self._mem[self.in_start:self.in_start + self.in_size] = frame.ljust(self.in_size, b"\0")
        self.in_full = True
        self.render_status()

    def render_status(self) -> None:
        """SM0/SM1 status registers: mailbox full; SM1's repeat acknowledge follows its request."""
        self._set8(SM0 + 5, SM_STATUS_MBX_FULL if self.out_full else 0)
        self._set8(SM0 + 8 + 5, SM_STATUS_MBX_FULL if self.in_full else 0)
        self._set8(SM0 + 8 + 7, self.repeat)
