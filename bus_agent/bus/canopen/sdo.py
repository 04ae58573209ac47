"""SDO client adapter (CiA 301 §7.2.4) over python-canopen's ``SdoClient``: an abort becomes
:class:`SdoError` (a BusError) naming the node, the object and the abort code with its text; no
valid answer :class:`SdoNoAnswer` (a :class:`NoAnswer`, abort code 0): :data:`SDO_FAILURES`.
Blocking (one request/response per expedited transfer): management thread and start-up only.
"""

from __future__ import annotations

import struct
from typing import Callable

from canopen.sdo import SdoAbortedError, SdoClient, SdoCommunicationError

from bus_agent.bus.base import BusError, NoAnswer

SdoRead = Callable[[int, int], bytes]          # (index, subindex) -> bytes
SdoWrite = Callable[[int, int, bytes], None]   # (index, subindex, data)


def _text(node_id: int, what: str, index: int, subindex: int, abort_code: int, detail: str) -> str:
    code = f"aborted with 0x{abort_code:08X} " if abort_code else ""
    return f"node {node_id}: SDO {what} 0x{index:04X}:{subindex} {code}({detail})"


class SdoError(BusError):
    """An SDO transfer the node refused (``abort_code``): its definite answer."""

    def __init__(self, node_id: int, what: str, index: int, subindex: int, abort_code: int, detail: str) -> None:
        self.node_id = node_id
        self.index = index
        self.subindex = subindex
        self.abort_code = abort_code
        super().__init__(_text(node_id, what, index, subindex, abort_code, detail))


class SdoNoAnswer(NoAnswer):
    """An SDO transfer without a valid answer in time: it may be made again (the only retry
    rule, :class:`NoAnswer`). ``abort_code`` 0, so a caller of either failure
    (:data:`SDO_FAILURES`) tells them apart by the code, as CiA 301 has no code for it."""

    abort_code = 0

    def __init__(self, node_id: int, what: str, index: int, subindex: int, detail: str) -> None:
        self.node_id = node_id
        self.index = index
        self.subindex = subindex
        super().__init__(_text(node_id, what, index, subindex, 0, detail))


#: Either failure of an SDO transfer: refused (:class:`SdoError`) or unanswered (:class:`SdoNoAnswer`).
SDO_FAILURES = (SdoError, SdoNoAnswer)


def _abort_text(e: SdoAbortedError) -> str:
    return SdoAbortedError.CODES.get(e.code, "unknown abort code")


def read(client: SdoClient, node_id: int, index: int, subindex: int) -> bytes:
    """Upload one object. Raises SdoError or SdoNoAnswer."""
    try:
        return bytes(client.upload(index, subindex))
    except SdoAbortedError as e:
        raise SdoError(node_id, "read", index, subindex, e.code, _abort_text(e)) from None
    except SdoCommunicationError as e:
        raise SdoNoAnswer(node_id, "read", index, subindex, f"no valid answer: {e}") from None


def write(client: SdoClient, node_id: int, index: int, subindex: int, data: bytes) -> None:
    """Download one object. Raises SdoError (the node changed nothing) or SdoNoAnswer."""
    try:
        client.download(index, subindex, bytes(data))
    except SdoAbortedError as e:
        raise SdoError(node_id, "write", index, subindex, e.code, _abort_text(e)) from None
    except SdoCommunicationError as e:
        raise SdoNoAnswer(node_id, "write", index, subindex, f"no valid answer: {e}") from None


_FORMATS = {8: "<B", 16: "<H", 32: "<I"}


def read_uint(sdo_read: SdoRead, index: int, subindex: int) -> int:
    """An unsigned object of 1, 2 or 4 bytes."""
    raw = sdo_read(index, subindex)
    return int.from_bytes(raw[:4], "little")


#: Aborts saying an object or subindex does not exist.
ABSENT = frozenset({0x06020000, 0x06090011})


def read_identity(sdo_read: SdoRead) -> tuple[int, int, int, int]:
    """0x1018 (vendor id, product code, revision, serial). Only the vendor id is mandatory (CiA
    301): an absent product code, revision or serial reads 0. Raises SdoError or SdoNoAnswer."""
    values = []
    for sub in (1, 2, 3, 4):
        try:
            values.append(read_uint(sdo_read, 0x1018, sub))
        except SdoError as e:
            if sub == 1 or e.abort_code not in ABSENT:
                raise
            values.append(0)
    return values[0], values[1], values[2], values[3]


def write_uint(sdo_write: SdoWrite, index: int, subindex: int, value: int, bits: int) -> None:
    sdo_write(index, subindex, struct.pack(_FORMATS[bits], value))
