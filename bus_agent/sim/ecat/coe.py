"""CoE over the EtherCAT mailbox: SDO server, emergencies, PDO communication objects.

Device side of ETG.1000.6 §5.6 (mailbox) and CiA 301 SDO semantics as CoE carries them:
expedited, normal and segmented upload/download, aborts, emergencies (service 1), the
SyncManager communication objects (:mod:`bus_agent.sim.ecat.pdo_config`), complete access and
SDO information (:mod:`bus_agent.sim.ecat.sdo_info`) where the device's CoE flags offer them.
Everything else is delegated to the drive model's object dictionary.
"""

from __future__ import annotations

import logging
import struct
from collections import deque
from enum import IntEnum
from typing import Callable, Mapping

from bus_agent.bus.base import ALState
from bus_agent.sim.drive_model import Emcy, ObjectEntry, SdoAbort
from bus_agent.sim.ecat import sdo_info
from bus_agent.sim.ecat.pdo_config import PdoConfig, SdoAbortCode
from bus_agent.sim.ecat.profiles import FLEXIBLE, PdoCatalog
from bus_agent.sim.ecat.sii import COE_COMPLETE_ACCESS, COE_SDO_INFO, MBX_IN_SIZE, MBX_OUT_SIZE

log = logging.getLogger(__name__)

MBX_HEADER = struct.Struct("<HHBB")  # length, address, channel/priority, type | counter << 4
SDO_HEADER = struct.Struct("<HBHB")  # CoE header, command, index, subindex
MAX_PENDING = 16  # responses/emergencies queued behind SM1
SCRATCH_INDEX = 0x2FFF  # emulator object: octet string to exercise segmented transfers
SCRATCH_MAX = 512
SYNC_PARAMETER_INDEXES = (0x1C32, 0x1C33)


class MbxType(IntEnum):
    """Mailbox type, header byte 5 low nibble (ETG.1000.4 Table 29)."""

    ERR = 0
    AOE = 1
    EOE = 2
    COE = 3
    FOE = 4
    SOE = 5
    VOE = 15


class MbxError(IntEnum):
    """Mailbox error reply details (ETG.1000.4 Table 30)."""

    SYNTAX = 1
    UNSUPPORTED_PROTOCOL = 2
    INVALID_CHANNEL = 3
    SERVICE_NOT_SUPPORTED = 4
    INVALID_HEADER = 5
    SIZE_TOO_SHORT = 6
    NO_MORE_MEMORY = 7
    INVALID_SIZE = 8


class CoeService(IntEnum):
    """CoE header bits 12-15 (ETG.1000.6 Table 29)."""

    EMERGENCY = 1
    SDO_REQUEST = 2
    SDO_RESPONSE = 3
    TXPDO = 4
    RXPDO = 5
    SDO_INFO = 8


class SdoServer:
    """SDO request handling of one drive: one transfer at a time, as CoE allows.

    ``al_state`` returns the current AL state (PDO configuration writes depend on it).
    """

    def __init__(self, model, al_state: Callable[[], ALState], catalog: PdoCatalog = FLEXIBLE, *,
                 mailbox_size: int = MBX_IN_SIZE, coe_details: int = 0, builtin: bool = True):
        self.model = model
        self.pdo = PdoConfig(model.objects, catalog)
        self._al_state = al_state
        data_max = mailbox_size - MBX_HEADER.size
        self.normal_upload_max = data_max - 10  # CoE 2 + SDO 4 + size 4
        self.segment_max = data_max - 3  # CoE 2 + command 1
        self.complete_access = bool(coe_details & COE_COMPLETE_ACCESS)
        self.sdo_info = bool(coe_details & COE_SDO_INFO)
        self.info_room = data_max - 2 - 4  # CoE header, SDO info header
        self.builtin = builtin  # the built-in dictionary: also the scratch object 0x2FFF
        self._scratch = b""
        #: (sync mode, SYNC0 cycle ns) for 0x1C32/0x1C33, set by the ESC
        self.sync_info: Callable[[], tuple[int, int]] | None = None
        self._sub0 = self._implicit_sub0(model.objects)
        self._upload: tuple[int, int, bytes, int, int] | None = None  # index, sub, data, offset, toggle
        self._download: tuple[int, int, int, bytearray, int] | None = None  # index, sub, size, buf, toggle

    @staticmethod
    def _implicit_sub0(objects: Mapping[tuple[int, int], ObjectEntry]) -> dict[int, int]:
        """Records listed without subindex 0 (e.g. 0x1018:1..4) get sub0 = highest subindex."""
        highest: dict[int, int] = {}
        for index, sub in objects:
            if sub > 0:
                highest[index] = max(highest.get(index, 0), sub)
        return {i: n for i, n in highest.items() if (i, 0) not in objects}

    def reset(self) -> None:
        self._upload = None
        self._download = None

    def _sync_parameter(self, index: int, sub: int) -> bytes:
        """0x1C32/0x1C33 (SM output/input sync parameter, ETG.1020): sub 1 sync mode (0 free run,
        1 SM event, 2 DC SYNC0), sub 2 cycle time (ns)."""
        mode, cycle_ns = self.sync_info() if self.sync_info is not None else (1, 0)
        if sub == 0:
            return bytes([2])
        if sub == 1:
            return struct.pack("<H", mode)
        if sub == 2:
            return struct.pack("<I", cycle_ns)
        raise SdoAbort(SdoAbortCode.NO_SUBINDEX)

    # -- object access --------------------------------------------------------------------
    def read_object(self, index: int, sub: int) -> bytes:
        if self.pdo.handles(index):
            return self.pdo.read(index, sub)
        if index in SYNC_PARAMETER_INDEXES:
            return self._sync_parameter(index, sub)
        if index == SCRATCH_INDEX and self.builtin:
            if sub != 0:
                raise SdoAbort(SdoAbortCode.NO_SUBINDEX)
            return self._scratch
        if sub == 0 and index in self._sub0:
            return bytes([self._sub0[index]])
        return bytes(self.model.read_bytes(index, sub))

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        if self.pdo.handles(index):
            self.pdo.write(index, sub, data, self._al_state())
            return
        if index in SYNC_PARAMETER_INDEXES:
            self._sync_parameter(index, sub)  # abort for a missing subindex first
            if sub != 1 or len(data) != 2:
                raise SdoAbort(SdoAbortCode.READ_ONLY if sub != 1 else SdoAbortCode.LENGTH_MISMATCH)
            return  # the sync mode follows the DC activation (0x0981); a written one is accepted
        if index == SCRATCH_INDEX and self.builtin:
            if sub != 0:
                raise SdoAbort(SdoAbortCode.NO_SUBINDEX)
            if len(data) > SCRATCH_MAX:
                raise SdoAbort(SdoAbortCode.LENGTH_TOO_HIGH)
            self._scratch = bytes(data)
            return
        if sub == 0 and index in self._sub0:
            raise SdoAbort(SdoAbortCode.READ_ONLY)
        self.model.write_bytes(index, sub, bytes(data))

    # -- protocol -------------------------------------------------------------------------
    def handle(self, req: memoryview) -> bytes | None:
        """One SDO request (starting at the CoE header). Returns the reply after the CoE
        header position, or None when no reply is due (abort from the master)."""
        if len(req) < 4:
            return _abort(0, 0, SdoAbortCode.INVALID_COMMAND)
        cmd = req[2]
        index = req[3] | (req[4] << 8) if len(req) >= 5 else 0
        sub = req[5] if len(req) >= 6 else 0
        ccs = cmd >> 5
        try:
            if ccs == 1:
                return self._download_initiate(req, cmd, index, sub)
            if ccs == 0:
                return self._download_segment(req, cmd)
            if ccs == 2:
                return self._upload_initiate(cmd, index, sub)
            if ccs == 3:
                return self._upload_segment(cmd)
            if ccs == 4:
                self.reset()
                return None
            raise SdoAbort(SdoAbortCode.INVALID_COMMAND)
        except SdoAbort as exc:
            code = int(exc.code)
            if ccs in (0, 3):  # segments carry no index: report the transfer's object
                index, sub = self._segment_object()
            self.reset()
            log.debug("SDO abort 0x%04X:%d code 0x%08X %s", index, sub, code, exc)
            return _abort(index, sub, code)

    def _store(self, index: int, sub: int, data: bytes) -> None:
        """A finished download; ``sub`` bit 8 marks complete access."""
        if sub & 0x100:
            self._write_complete(index, sub & 0xFF, data)
        else:
            self.write_object(index, sub, data)

    def _segment_object(self) -> tuple[int, int]:
        if self._upload is not None:
            return self._upload[0], self._upload[1]
        if self._download is not None:
            return self._download[0], self._download[1]
        return 0, 0

    # -- complete access (ETG.1000.6 5.6.2.1.2: subindex 0 travels as 16 bits) ------------------
    def _entry_size(self, index: int, sub: int) -> int:
        if self.pdo.handles(index):
            return 1 if sub == 0 or index == 0x1C00 else (2 if index in self.pdo.assign else 4)
        entry = self.model.objects.get((index, sub))
        if entry is None:
            raise SdoAbort(SdoAbortCode.NO_SUBINDEX)
        return entry.size

    def _read_complete(self, index: int, sub: int) -> bytes:
        if sub > 1:
            raise SdoAbort(SdoAbortCode.UNSUPPORTED_ACCESS, "complete access starts at subindex 0 or 1")
        count = self.read_object(index, 0)[0]
        out = bytearray(bytes([count, 0]) if sub == 0 else b"")
        for k in range(1, count + 1):
            try:
                out += self.read_object(index, k)
            except SdoAbort as exc:
                if exc.code != SdoAbortCode.NO_SUBINDEX:
                    raise
        return bytes(out)

    def _write_complete(self, index: int, sub: int, data: bytes) -> None:
        if sub > 1:
            raise SdoAbort(SdoAbortCode.UNSUPPORTED_ACCESS, "complete access starts at subindex 0 or 1")
        count = data[0] if sub == 0 else self.read_object(index, 0)[0]
        pos = 2 if sub == 0 else 0
        values = []
        for k in range(1, count + 1):
            size = self._entry_size(index, k)
            if pos + size > len(data):
                raise SdoAbort(SdoAbortCode.LENGTH_MISMATCH)
            values.append(data[pos:pos + size])
            pos += size
        if sub == 0:
            self.write_object(index, 0, b"\0")
        for k, value in enumerate(values, 1):
            self.write_object(index, k, value)
        if sub == 0:
            self.write_object(index, 0, bytes([count]))

    def _upload_initiate(self, cmd: int, index: int, sub: int) -> bytes:
        self.reset()
        if cmd & 0x10 and not self.complete_access:
            raise SdoAbort(SdoAbortCode.UNSUPPORTED_ACCESS, "complete access not supported")
        data = self._read_complete(index, sub) if cmd & 0x10 else self.read_object(index, sub)
        n = len(data)
        ca = cmd & 0x10
        if 0 < n <= 4:
            return SDO_HEADER.pack(CoeService.SDO_RESPONSE << 12, 0x43 | ca | ((4 - n) << 2), index, sub) \
                + data + b"\0" * (4 - n)
        first = data[:self.normal_upload_max]
        if n > self.normal_upload_max:
            self._upload = (index, sub, data, len(first), 0)
        return SDO_HEADER.pack(CoeService.SDO_RESPONSE << 12, 0x41 | ca, index, sub) + struct.pack("<I", n) + first

    def _upload_segment(self, cmd: int) -> bytes:
        if self._upload is None:
            raise SdoAbort(SdoAbortCode.INVALID_COMMAND, "no upload in progress")
        index, sub, data, offset, toggle = self._upload
        if (cmd & 0x10) != toggle:
            raise SdoAbort(SdoAbortCode.TOGGLE)
        chunk = data[offset: offset + self.segment_max]
        offset += len(chunk)
        last = offset >= len(data)
        scmd = toggle | (1 if last else 0)
        if len(chunk) < 7:
            scmd |= (7 - len(chunk)) << 1
            chunk = chunk + b"\0" * (7 - len(chunk))
        self._upload = None if last else (index, sub, data, offset, toggle ^ 0x10)
        return struct.pack("<HB", CoeService.SDO_RESPONSE << 12, scmd) + chunk

    def _download_initiate(self, req: memoryview, cmd: int, index: int, sub: int) -> bytes:
        self.reset()
        if cmd & 0x10 and not self.complete_access:
            raise SdoAbort(SdoAbortCode.UNSUPPORTED_ACCESS, "complete access not supported")
        if len(req) < 10:
            raise SdoAbort(SdoAbortCode.INVALID_COMMAND)
        if cmd & 0x02:  # expedited
            n = 4 - ((cmd >> 2) & 0x03) if cmd & 0x01 else 4
            self._store(index, sub | (0x100 if cmd & 0x10 else 0), bytes(req[6:6 + n]))
        else:
            size = struct.unpack_from("<I", req, 6)[0]
            if size > SCRATCH_MAX:
                raise SdoAbort(SdoAbortCode.LENGTH_TOO_HIGH)
            chunk = bytes(req[10:])
            sub_ca = sub | (0x100 if cmd & 0x10 else 0)
            if len(chunk) >= size:
                self._store(index, sub_ca, chunk[:size])
            else:
                self._download = (index, sub_ca, size, bytearray(chunk), 0)
        return SDO_HEADER.pack(CoeService.SDO_RESPONSE << 12, 0x60, index, sub) + b"\0\0\0\0"

    def _download_segment(self, req: memoryview, cmd: int) -> bytes:
        if self._download is None:
            raise SdoAbort(SdoAbortCode.INVALID_COMMAND, "no download in progress")
        index, sub, size, buf, toggle = self._download
        if (cmd & 0x10) != toggle:
            raise SdoAbort(SdoAbortCode.TOGGLE)
        data = req[3:]
        if len(data) == 7:
            data = data[: 7 - ((cmd >> 1) & 0x07)]
        buf += data
        if len(buf) > size:
            raise SdoAbort(SdoAbortCode.LENGTH_TOO_HIGH)
        if cmd & 0x01:
            if len(buf) != size:
                raise SdoAbort(SdoAbortCode.LENGTH_MISMATCH)
            self._download = None
            self._store(index, sub, bytes(buf))
        else:
            self._download = (index, sub, size, buf, toggle ^ 0x10)
        return struct.pack("<HB", CoeService.SDO_RESPONSE << 12, 0x20 | toggle) + b"\0" * 7


def _abort(index: int, sub: int, code: int) -> bytes:
    sub &= 0xFF  # a complete-access download carries a flag above the subindex
    # SOEM recognises an abort by service 2 (request) and command 0x80.
    return SDO_HEADER.pack(CoeService.SDO_REQUEST << 12, 0x80, index, sub) + struct.pack("<I", code)


class Mailbox:
    """Mailbox protocol layer of one ESC: requests from SM0, replies queued for SM1.

    Counter dedupe (header byte 5 bits 4-6): a request repeating the previous non-zero
    counter is a resend and is ignored. The last reply handed to SM1 is kept for the
    repeat request (SM1 activate bit 1 toggle).
    """

    def __init__(self, sdo: SdoServer, out_size: int = MBX_OUT_SIZE, coe: bool = True):
        self.sdo = sdo
        self.out_size = out_size
        #: False: a device without CoE (its ESI has none, or the profile modifier ``no-coe``):
        #: every request is answered with the mailbox error "unsupported protocol".
        self.coe = coe
        self.queue: deque[bytes] = deque()
        self.last_counter = 0
        self._out_counter = 0
        self.last_sent: bytes | None = None
        #: Fault injection (control action ``mute_sdo``): [index, subindex, skip, count]. Of
        #: the uploads of that object, the next ``skip`` are answered and the ``count`` after
        #: them get no answer at all, as from a mailbox answer lost for good. Kept over reset.
        self.mute: list[int] | None = None
        #: Fault injection (control action ``refuse_sdo``): (index, subindex) -> abort code that
        #: answers every upload and download of that object, as from a drive without it (0x06020000).
        self.refuse: dict[tuple[int, int], int] = {}

    def _muted(self, body: memoryview) -> bool:
        """True for an SDO upload request that the ``mute`` fault swallows (counts it down)."""
        mute = self.mute
        if mute is None or len(body) < 6 or body[2] >> 5 != 2 or (body[3] | body[4] << 8, body[5]) != tuple(mute[:2]):
            return False
        if mute[2]:
            mute[2] -= 1
            return False
        mute[3] -= 1
        if mute[3] <= 0:
            self.mute = None
        log.info("SDO upload 0x%04X:%02X: no answer (mute_sdo fault)", mute[0], mute[1])
        return True

    def reset(self) -> None:
        self.queue.clear()
        self.last_counter = 0
        self.last_sent = None
        self.sdo.reset()

    def _frame(self, mtype: MbxType, payload: bytes) -> bytes:
        self._out_counter = self._out_counter % 7 + 1
        return MBX_HEADER.pack(len(payload), 0, 0, mtype | (self._out_counter << 4)) + payload

    def _push(self, frame: bytes, emergency: bool = False) -> None:
        if len(self.queue) >= MAX_PENDING:
            if emergency:
                log.warning("mailbox queue full: emergency dropped")
                return
            self.queue.popleft()
        self.queue.append(frame)

    def request(self, buf: memoryview) -> None:
        """A complete mailbox written by the master into SM0."""
        length, _address, _channel, mtype = MBX_HEADER.unpack_from(buf, 0)
        counter = (mtype >> 4) & 0x07
        mtype &= 0x0F
        if counter and counter == self.last_counter:
            log.debug("mailbox counter %d repeated: resend ignored", counter)
            return
        self.last_counter = counter
        if length < 2 or length > self.out_size - MBX_HEADER.size:
            self._push(self._frame(MbxType.ERR, struct.pack("<HH", 1, MbxError.INVALID_SIZE)))
            return
        if mtype != MbxType.COE or not self.coe:
            self._push(self._frame(MbxType.ERR, struct.pack("<HH", 1, MbxError.UNSUPPORTED_PROTOCOL)))
            return
        body = buf[MBX_HEADER.size: MBX_HEADER.size + length]
        service = (body[1] >> 4) & 0x0F
        if service == CoeService.SDO_INFO and self.sdo.sdo_info:
            model = self.sdo.model
            for reply in sdo_info.handle(bytes(body[2:]), model.objects, model.value, self.sdo.info_room):
                self._push(self._frame(MbxType.COE, struct.pack("<H", CoeService.SDO_INFO << 12) + reply))
            return
        if service != CoeService.SDO_REQUEST:
            self._push(self._frame(MbxType.ERR, struct.pack("<HH", 1, MbxError.SERVICE_NOT_SUPPORTED)))
            return
        if self._muted(body):
            return
        if self.refuse and len(body) >= 6:
            key = (body[3] | body[4] << 8, body[5])
            code = self.refuse.get(key)
            if code is not None and body[2] >> 5 in (1, 2):  # initiate download / upload
                log.info("SDO 0x%04X:%02X: aborted 0x%08X (refuse_sdo fault)", key[0], key[1], code)
                self._push(self._frame(MbxType.COE, _abort(key[0], key[1], code)))
                return
        answer = self.sdo.handle(body)
        if answer is not None:
            self._push(self._frame(MbxType.COE, answer))

    def emergency(self, emcy: Emcy) -> None:
        """Queue a CoE emergency (service 1): error code, error register, 5 bytes."""
        data = bytes(emcy.data)[:5].ljust(5, b"\0")
        payload = struct.pack("<HHB", CoeService.EMERGENCY << 12, emcy.error_code, emcy.error_register) + data
        self._push(self._frame(MbxType.COE, payload), emergency=True)
