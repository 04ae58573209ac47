"""Emergencies (CiA 301 EMCY) of a bus's drives, for the cycle.

The same content over either bus: an error code, the error register (0x1001) and 5
manufacturer bytes, in a CAN frame on 0x080 + node id (:mod:`bus_agent.bus.canopen.emcy`) or as a
CoE emergency in an EtherCAT slave's mailbox (:class:`bus_agent.bus.pysoem_bus.PysoemBus`). A
backend records each one here; the cycle takes the new ones (``take_emergencies``: an ``emcy``
event per drive of the slave) and reads ``error_texts`` for the drive status's ``error_text``.
One thread records (the one that reads the bus), the cycle thread takes: deque and dict
operations that need no lock.
"""

from __future__ import annotations

import collections

from schemas.error_codes import ERROR_CLASSES, describe

#: New emergencies kept until the cycle takes them (the oldest go first beyond this).
MAX_PENDING = 256


def error_text(code: int) -> str:
    """The meaning of an EMCY / 0x603F error code (:func:`schemas.error_codes.describe`: the
    code, else its sub-class or class, with the code); "error reset or no error" for 0x00xx."""
    return describe(code) if code & 0xFF00 else ERROR_CLASSES[0]


class EmergencyLog:
    """The emergencies a backend received: new ones for the cycle, the last text per position."""

    def __init__(self) -> None:
        #: position -> (error code, text) of its last emergency that is not a reset
        self.error_texts: dict[int, tuple[int, str]] = {}
        self._new: collections.deque[tuple[int, int, int, str]] = collections.deque(maxlen=MAX_PENDING)

    def record(self, position: int, error_code: int, error_register: int) -> str:
        """One emergency of the drive at ``position``; returns its text."""
        text = error_text(error_code)
        if error_code & 0xFF00:
            self.error_texts[position] = (error_code, text)
        self._new.append((position, error_code, error_register, text))
        return text

    def take(self) -> list[tuple[int, int, int, str]]:
        """The emergencies since the last call as (position, error code, register, text)."""
        out = []
        q = self._new
        while q:
            out.append(q.popleft())
        return out
