"""One simulated EtherCAT slave controller (ESC) hosting a CiA 402 drive model.

Register map, SII EEPROM interface, SyncManagers, FMMUs and the AL state machine (ETG.1000.4 /
ETG.1000.6, ESC datasheet section II register descriptions). Its parts: the mailbox SMs
(:mod:`.esc_mailbox`), the process data (:mod:`.esc_pd`), the DC clock and sync error counter
(:mod:`.dc`); the SII image is built by :mod:`.sii`.
The ESC is driven by :class:`bus_agent.sim.ecat.segment.Segment`, which addresses it with
datagrams; process data (LRD/LWR/LRW) goes through the segment's precomputed FMMU plans.
"""

from __future__ import annotations

import logging
import struct
import time
from typing import Callable, Mapping

from bus_agent.bus.base import AL_ERROR_FLAG, ALState
from bus_agent.sim.drive_model import PROFILES, DriveModel, DriveProfile, ObjectEntry
from bus_agent.sim.ecat.coe import Mailbox, SdoServer
from bus_agent.sim.ecat.dc import (DC_END, DC_FIRST, REG_ACTIVATION, REG_SYS_TIME, SYNC_ERROR_LIMIT, SYNC_MODE_SM, DcClock,
                                   SyncErrorCounter)
from bus_agent.sim.ecat.esc_mailbox import MailboxSms
from bus_agent.sim.ecat.esc_pd import ProcessData
from bus_agent.sim.ecat.profiles import EcatProfile, PdoCatalog, as_ecat
from bus_agent.sim.ecat.sii import MBX_PROTO_COE, MBX_PROTO_FOE, PDI_CONTROL, build_sii, type_code, without_mailbox

log = logging.getLogger(__name__)

MEM_SIZE = 0x2000  # 4 KiB registers + 4 KiB process RAM (more when an ESI places SMs higher)
MAX_IMAGE = 0x400  # room for a process image behind its SM start
REG_END = 0x1000


class Reg:
    """ESC register addresses used here (ETG.1000.4 Table 31 ff.)."""

    TYPE = 0x0000
    FMMU_COUNT = 0x0004
    SM_COUNT = 0x0005
    RAM_SIZE = 0x0006
    PORT_DESC = 0x0007
    FEATURES = 0x0008
    STATION_ADDR = 0x0010
    ALIAS = 0x0012
    DL_CONTROL = 0x0100
    DL_STATUS = 0x0110
    AL_CONTROL = 0x0120
    AL_STATUS = 0x0130
    AL_STATUS_CODE = 0x0134
    PDI_CONTROL = 0x0140
    WD_DIVIDER = 0x0400
    WD_TIME_PDI = 0x0410
    WD_TIME_PD = 0x0420
    WD_STATUS_PD = 0x0440
    WD_COUNTER_PD = 0x0442
    EEP_CONFIG = 0x0500
    EEP_PDI_STATE = 0x0501
    EEP_CONTROL = 0x0502
    EEP_ADDRESS = 0x0504
    EEP_DATA = 0x0508
    FMMU0 = 0x0600
    SM0 = 0x0800


class AlStatusCode:
    """AL status codes this ESC raises (register 0x0134, ETG.1000.6 Table 11)."""

    NONE = 0x0000
    INVALID_STATE_CHANGE = 0x0011
    UNKNOWN_STATE = 0x0012
    BOOTSTRAP_NOT_SUPPORTED = 0x0013
    INVALID_MAILBOX_CONFIG = 0x0016
    SM_WATCHDOG = 0x001B
    INVALID_OUTPUT_CONFIG = 0x001D
    INVALID_INPUT_CONFIG = 0x001E
    SYNC_ERROR = 0x001A
    INVALID_DC_SYNC = 0x0030


EEP_STATUS_R64 = 0x0040  # 8-byte reads supported
EEP_CMD_READ, EEP_CMD_WRITE, EEP_CMD_RELOAD = 0x01, 0x02, 0x04
SM_WD_ENABLE = 0x40  # SM control bit 6: watchdog trigger

# Registers the master cannot overwrite: (start, end) byte ranges restored after a write.
RO_RANGES: tuple[tuple[int, int], ...] = (
    (0x0000, 0x0010), (0x0012, 0x0014), (0x0110, 0x0112), (0x0130, 0x0136), (0x0140, 0x0142),
    (0x0440, 0x0444), (0x0501, 0x0502),
    *((Reg.SM0 + 8 * k + 5, Reg.SM0 + 8 * k + 6) for k in range(16)),
    *((Reg.SM0 + 8 * k + 7, Reg.SM0 + 8 * k + 8) for k in range(16)),
)
# transitions allowed upward (ETG.1000.6 Table 10); every downward one is allowed
_UP = {(ALState.INIT, ALState.PREOP), (ALState.PREOP, ALState.SAFEOP), (ALState.SAFEOP, ALState.OP)}
_STATES = {int(s) for s in ALState if s != ALState.NONE}
U16 = struct.Struct("<H")
FMMU = struct.Struct("<IHBBHBBB3x")
SM = struct.Struct("<HHBBBB")


def sii_pdos(catalog: PdoCatalog, objects: Mapping[tuple[int, int], ObjectEntry]
             ) -> list[tuple[int, int, list[tuple[int, int, int, int]]]]:
    """(PDO index, SM, entries) of every PDO, for the SII categories: the power-on assigned
    ones on SM2/SM3, the others (alternatives) on 0xFF; empty alternatives left out."""
    out = []
    for assign, sm in ((0x1C13, 3), (0x1C12, 2)):
        lo, hi = (0x1600, 0x17FF) if assign == 0x1C12 else (0x1A00, 0x1BFF)
        for pdo in sorted(catalog.maps, key=lambda p: (p not in catalog.assign[assign], p)):
            if not lo <= pdo <= hi or not (catalog.maps[pdo] or pdo in catalog.assign[assign]):
                continue
            entries = []
            for e in catalog.maps[pdo]:
                i, s, b = e >> 16, (e >> 8) & 0xFF, e & 0xFF
                entries.append((i, s, b, type_code(objects.get((i, s)))))
            out.append((pdo, sm if pdo in catalog.assign[assign] else 0xFF, entries))
    return out


class Esc:
    """One slave: memory image, SII, AL state machine, mailbox and drive model.

    ``position`` is 0-based on the segment; ``last`` tells the DL status that port 1 is
    closed. ``on_change(kind)`` tells the segment to drop cached plans ("fmmu", "address",
    "al") — called from the datagram path, so it must be cheap.
    """

    def __init__(self, position: int, profile: DriveProfile | EcatProfile = PROFILES["generic"], *,
                 last: bool = True, on_change: Callable[[str], None] = lambda kind: None):
        self.position = position
        self.ecat_profile = as_ecat(profile)
        self.profile = profile = self.ecat_profile.drive
        ep = self.ecat_profile
        self.model = DriveModel(profile, serial=position + 1, dictionary=ep.dictionary, hidden=ep.hidden)
        catalog = ep.pdos
        self.sms = ep.sms
        self.sdo = SdoServer(self.model, lambda: self.al_state, catalog, mailbox_size=self.sms[1].length,
                             coe_details=ep.coe_details, builtin=ep.dictionary is None)
        self.mailbox = Mailbox(self.sdo, self.sms[0].length, coe=bool(ep.mailbox_protocols & MBX_PROTO_COE))
        self.last = last
        self.on_change = on_change
        # process RAM up to the end of the highest SM (an ESI's layout; process images up to MAX_IMAGE)
        self.mem_size = max(MEM_SIZE, max(d.start + max(d.length, MAX_IMAGE) for d in self.sms))
        self.mem = bytearray(self.mem_size)
        self.mv = memoryview(self.mem)
        self.dc = DcClock(self.mem) if self.ecat_profile.dc else None
        self._sync_errors = SyncErrorCounter()
        self._mbx = MailboxSms(position, self.mem, self._set8, self.mailbox, (self.sms[0].start, self.sms[0].length),
                               (self.sms[1].start, self.sms[1].length))
        self._pd = ProcessData(position, self.mem, self.model, self.sdo.pdo, self.sms[2].start, self.sms[3].start)
        # the segment calls these for every slave at every step: no call in between
        self.apply_outputs = self._pd.apply_outputs
        self.update_inputs = self._pd.update_inputs
        self.offer_mailbox = self._mbx.offer
        self.sdo.sync_info = self._sync_info
        self.ro = bytearray(REG_END)
        self.present = True
        self.wkc_fault = False
        self.sii = bytearray(build_sii(
            vendor_id=profile.vendor_id, product_code=profile.product_code, revision=profile.revision,
            serial=position + 1, name=profile.device_name, order=ep.sii_order or profile.device_name,
            pdos=sii_pdos(catalog, self.model.objects), sms=self.sms, coe_details=ep.coe_details,
            mailbox_protocols=ep.mailbox_protocols))
        self.has_mailbox = self.ecat_profile.mailbox != "none"
        if not self.has_mailbox:
            self.sii[:] = without_mailbox(self.sii)
        elif self.ecat_profile.mailbox == "no-coe":
            U16.pack_into(self.sii, 0x1C * 2, MBX_PROTO_FOE)
            self.mailbox.coe = False
        self.power_on()

    # -- reset ----------------------------------------------------------------------------
    def power_on(self) -> None:
        """Registers to power-on values (INIT, station address 0, SMs/FMMUs off)."""
        self.mem[:] = bytes(self.mem_size)
        self.ro[:] = bytes(REG_END)
        self._set8(Reg.TYPE, 0x11)
        self._set8(Reg.FMMU_COUNT, 3)
        self._set8(Reg.SM_COUNT, 4)
        self._set8(Reg.RAM_SIZE, 4)
        self._set8(Reg.PORT_DESC, 0x0F)  # ports 0 and 1: MII
        # bit 2 DC available, bit 3 64-bit DC; 0: SOEM skips DC configuration
        self._set16(Reg.FEATURES, 0x000C if self.dc is not None else 0x0000)
        if self.dc is not None:
            self.dc.power_on()
        self._set16(Reg.ALIAS, U16.unpack_from(self.sii, 0x04 * 2)[0])
        # DL status: PDI operational, link port 0, port 0 open and communicating, ports 2/3 closed;
        # port 1 open with communication unless this is the last slave (loop closed).
        dl = 0x0003 | 0x0010 | 0x0200 | 0x5000 | (0x0400 if self.last else 0x0020 | 0x0800)
        self._set16(Reg.DL_STATUS, dl)
        self._set16(Reg.PDI_CONTROL, PDI_CONTROL)
        self._set8(Reg.WD_STATUS_PD, 1)
        U16.pack_into(self.mem, Reg.WD_DIVIDER, 2498)  # (2498 + 2) * 40 ns = 100 us
        U16.pack_into(self.mem, Reg.WD_TIME_PDI, 1000)
        U16.pack_into(self.mem, Reg.WD_TIME_PD, 1000)  # 1000 * 100 us = 100 ms
        self._set16(Reg.EEP_CONTROL, EEP_STATUS_R64)
        self.al_state = ALState.INIT
        self.al_error = False
        self.al_code = 0
        self._render_al()
        self.mailbox.reset()
        self.sdo.pdo.reset()
        self._mbx.reset()
        self.fmmus: list[tuple[int, int, int, int]] = []  # (logical start, length, physical, type)
        self.out_time = 0.0
        self.out_count = 0  # process-data writes of outputs (the segment counts them)
        self._sync_errors.reset()
        self.last_step = 0.0  # when the segment last stepped this slave's drive model
        self.outputs_fresh = False
        self._pd.reset()
        self.wd_timeout_s = 0.1
        self.on_change("all")

    def _set8(self, addr: int, value: int) -> None:
        self.mem[addr] = self.ro[addr] = value

    def _set16(self, addr: int, value: int) -> None:
        U16.pack_into(self.mem, addr, value)
        U16.pack_into(self.ro, addr, value)

    def _render_al(self) -> None:
        self._set16(Reg.AL_STATUS, int(self.al_state) | (AL_ERROR_FLAG if self.al_error else 0))
        self._set16(Reg.AL_STATUS_CODE, self.al_code)

    @property
    def sync_error_counter(self) -> int:
        """The sync error counter of a dc-required drive in OP (0x001A above its limit)."""
        return self._sync_errors.counter

    @property
    def station_address(self) -> int:
        return U16.unpack_from(self.mem, Reg.STATION_ADDR)[0]

    # -- datagram access ------------------------------------------------------------------
    def read(self, ado: int, dst: memoryview) -> bool:
        """Copy [ado, ado+len) into ``dst``. False (no WKC, data untouched) for an empty
        read mailbox."""
        n = len(dst)
        end = ado + n
        if self.dc is not None and ado < REG_SYS_TIME + 8 and end > REG_SYS_TIME:
            self.dc.render()
        if end > self.mem_size:
            if ado >= self.mem_size:
                return True
            dst[: self.mem_size - ado] = self.mv[ado:self.mem_size]
            return True
        mbx = self._mbx
        if end > mbx.in_start and ado < mbx.in_end and mbx.enabled[1]:
            return mbx.read(ado, end, dst)
        dst[:] = self.mv[ado:end]
        return True

    def write(self, ado: int, src: memoryview) -> bool:
        """Apply a write of ``src`` at ``ado``. False (no WKC) for a refused mailbox write."""
        if ado == REG_SYS_TIME and len(src) == 8 and self.dc is not None:
            self.dc.time_control(src)  # every frame's FRMW: the hot path
            return True
        end = min(ado + len(src), self.mem_size)
        if ado >= self.mem_size:
            return True
        if ado >= REG_END:
            mbx = self._mbx
            if end > mbx.out_start and ado < mbx.out_end and mbx.enabled[0]:
                return mbx.write(ado, end, src, self.al_state == ALState.INIT)
            self.mv[ado:end] = src[: end - ado]
            return True
        reg_end = min(end, REG_END)
        old_act = bytes(self.mem[Reg.SM0 + 6: Reg.SM0 + 32: 8]) if ado < 0x0820 and reg_end > 0x0800 else b""
        dc_before = bytes(self.mem[DC_FIRST:DC_END]) if self.dc is not None and ado < DC_END and reg_end > DC_FIRST else None
        self.mv[ado:reg_end] = src[: reg_end - ado]
        for s, e in RO_RANGES:
            if s < reg_end and ado < e:
                a, b = max(s, ado), min(e, reg_end)
                self.mem[a:b] = self.ro[a:b]
        if dc_before is not None and self.dc is not None:
            self.dc.written(ado, reg_end, dc_before)
            if ado <= REG_ACTIVATION < reg_end:
                self.on_change("sync")  # SYNC0 on or off: SM-synchronous or not (the segment's plans)
        if ado < 0x0012 and reg_end > 0x0010:
            self.on_change("address")
        if ado <= Reg.AL_CONTROL < reg_end:
            self._al_control(self.mem[Reg.AL_CONTROL])
        if ado <= Reg.EEP_CONTROL + 1 < reg_end:
            self._eeprom_command()
        if ado < 0x0700 and reg_end > 0x0600:
            self._read_fmmus()
        if ado < 0x0880 and reg_end > 0x0800:
            self._sm_written(old_act)
        if ado < 0x0422 and reg_end > 0x0400:
            self._update_watchdog()
        if end > REG_END:
            self.mv[REG_END:end] = src[REG_END - ado: end - ado]
        return True

    # -- EEPROM interface -----------------------------------------------------------------
    def _eeprom_command(self) -> None:
        ctrl = U16.unpack_from(self.mem, Reg.EEP_CONTROL)[0]
        cmd = (ctrl >> 8) & 0x07
        word = struct.unpack_from("<I", self.mem, Reg.EEP_ADDRESS)[0]
        if cmd == EEP_CMD_READ:
            a = word * 2
            chunk = bytes(self.sii[a:a + 8]).ljust(8, b"\xff")
            self.mem[Reg.EEP_DATA:Reg.EEP_DATA + 8] = chunk
        elif cmd == EEP_CMD_WRITE and ctrl & 0x0001:
            a = word * 2
            if a + 2 <= len(self.sii):
                self.sii[a:a + 2] = self.mem[Reg.EEP_DATA:Reg.EEP_DATA + 2]
        self._set16(Reg.EEP_CONTROL, EEP_STATUS_R64)  # done at once: never busy, no error

    # -- SyncManagers and FMMUs -----------------------------------------------------------
    def sm(self, k: int) -> tuple[int, int, int, int, int, int]:
        """(start, length, control, status, activate, pdi control) of SM k."""
        return SM.unpack_from(self.mem, Reg.SM0 + 8 * k)

    def _sm_written(self, old_act: bytes) -> None:
        mbx = self._mbx
        for k in (0, 1):  # SM2/SM3 being enabled is checked on the way to SAFE-OP
            enabled = bool(self.mem[Reg.SM0 + 8 * k + 6] & 0x01)
            if enabled != mbx.enabled[k]:
                mbx.enable(k, enabled)
        mbx.repeat_written(self.mem[Reg.SM0 + 8 + 6] & 0x02)
        mbx.render_status()
        self._update_watchdog()
        self.on_change("fmmu")

    def _read_fmmus(self) -> None:
        fmmus = []
        for k in range(3):
            log_start, log_len, _sb, _eb, phys, _pb, ftype, active = FMMU.unpack_from(self.mem, Reg.FMMU0 + 16 * k)
            if active & 0x01 and log_len and ftype in (1, 2):
                fmmus.append((log_start, log_len, phys, ftype))
        self.fmmus = fmmus
        self.on_change("fmmu")

    def _update_watchdog(self) -> None:
        divider = U16.unpack_from(self.mem, Reg.WD_DIVIDER)[0]
        time_pd = U16.unpack_from(self.mem, Reg.WD_TIME_PD)[0]
        control = self.mem[Reg.SM0 + 16 + 4]
        if time_pd == 0 or not control & SM_WD_ENABLE:
            self.wd_timeout_s = 0.0
        else:
            self.wd_timeout_s = (divider + 2) * 40e-9 * time_pd

    # -- mailbox --------------------------------------------------------------------------
    def push_emergencies(self) -> None:
        """Move the model's EMCY records into the mailbox (dropped below PRE-OP)."""
        emcys = self.model.take_emcy()
        if not emcys or self.al_state == ALState.INIT:
            return
        for emcy in emcys:
            self.mailbox.emergency(emcy)
        self.offer_mailbox()

    # -- AL state machine -----------------------------------------------------------------
    def _al_control(self, value: int) -> None:
        """AL control write (ETG.1000.6 §6.4.1): request = bits 0-3, acknowledge = bit 4."""
        requested, ack = value & 0x0F, bool(value & AL_ERROR_FLAG)
        if self.al_error and not ack and requested != ALState.INIT:
            return  # an error indication stays until acknowledged
        if ack or requested == ALState.INIT:
            self.al_error = False
            self.al_code = 0
        if requested not in _STATES:
            self._fail(self.al_state, AlStatusCode.UNKNOWN_STATE)
            return
        target = ALState(requested)
        if target == self.al_state:
            self._render_al()
            return
        if target == ALState.BOOT:
            self._fail(self.al_state, AlStatusCode.BOOTSTRAP_NOT_SUPPORTED)
            return
        if target > self.al_state and (self.al_state, target) not in _UP:
            self._fail(self.al_state, AlStatusCode.INVALID_STATE_CHANGE)
            return
        if target == ALState.PREOP and self.al_state == ALState.INIT:
            if not self._mailbox_sms_valid():
                self._fail(ALState.INIT, AlStatusCode.INVALID_MAILBOX_CONFIG)
                return
            self.mailbox.reset()
        if target == ALState.OP and self._needs_sync0():
            self._fail(self.al_state, AlStatusCode.INVALID_DC_SYNC)
            return
        if target == ALState.SAFEOP and self.al_state == ALState.PREOP:
            code = self._pd_sms_check()
            if code:
                self._fail(ALState.PREOP, code)
                return
            self._pd.build_codecs()
            self.update_inputs()
        self._enter(target)

    def _enter(self, target: ALState) -> None:
        previous = self.al_state
        self.al_state = target
        if previous == ALState.OP and target != ALState.OP:
            self.model.communication_lost()
        if target == ALState.OP:
            self.out_time = time.monotonic()
            self._sync_errors.reset()
            self._set8(Reg.WD_STATUS_PD, 1)
        if target == ALState.INIT:
            self.mailbox.reset()
            self._mbx.empty()
        self._render_al()
        log.debug("slave %d: AL %s -> %s", self.position, previous.name, target.name)
        self.on_change("al")

    def _fail(self, state: ALState, code: int) -> None:
        log.info("slave %d: AL error 0x%04X, state %s", self.position, code, state.name)
        self.al_error = True
        self.al_code = code
        if state != self.al_state:
            self._enter(state)
        self._render_al()

    # -- distributed clocks ---------------------------------------------------------------
    def _sync_info(self) -> tuple[int, int]:
        """(0x1C32:01 sync mode, SYNC0 cycle ns)."""
        if self.dc is None:
            return SYNC_MODE_SM, 0
        return self.dc.sync_mode(), self.dc.sync0[1] if self.dc.sync0 else 0

    def _needs_sync0(self) -> bool:
        """dc-required: cyclic synchronous modes (8/9/10) need SYNC0 running."""
        if self.dc is None or not self.ecat_profile.dc_required:
            return False
        return (self.ecat_profile.sync0_always or self._mode_display() in (8, 9, 10)) and not self.dc.sync0_running()

    def _mode_display(self) -> int:
        return int(self.model.value(0x6061, 0))  # also when the dictionary lacks 0x6061

    def check_sync(self, now: float) -> None:
        """In OP: a dc-required drive in mode 8/9/10 without SYNC0 -> SAFE-OP + 0x0030; the sync
        error counter over the SYNC0 periods since the last call above :data:`SYNC_ERROR_LIMIT`
        -> SAFE-OP + 0x001A. Called often (the segment's loop)."""
        dc = self.dc
        if dc is None or not self.ecat_profile.dc_required or self.al_state != ALState.OP:
            return
        events = dc.sync0_events()  # 0 while SYNC0 does not run
        if not events and (self.ecat_profile.sync0_always or self._mode_display() in (8, 9, 10)):  # as _needs_sync0
            self._fail(ALState.SAFEOP, AlStatusCode.INVALID_DC_SYNC)
            return
        if self._sync_errors.count(events, self.out_count):
            log.warning("slave %d: sync error: outputs not in step with SYNC0 (counter %d > %d)", self.position,
                        self._sync_errors.counter, SYNC_ERROR_LIMIT)
            self._fail(ALState.SAFEOP, AlStatusCode.SYNC_ERROR)

    def watchdog_expired(self) -> None:
        """SM watchdog in OP: outputs missing too long -> SAFE-OP + 0x001B."""
        self.mem[Reg.WD_COUNTER_PD] = self.ro[Reg.WD_COUNTER_PD] = (self.ro[Reg.WD_COUNTER_PD] + 1) & 0xFF
        self._set8(Reg.WD_STATUS_PD, 0)
        self._fail(ALState.SAFEOP, AlStatusCode.SM_WATCHDOG)

    def _mailbox_sms_valid(self) -> bool:
        if not self.has_mailbox:
            return True  # nothing to check: SM0/SM1 are unused
        for k in (0, 1):
            start, length, control, _st, act, _pdi = self.sm(k)
            d = self.sms[k]
            if not (act & 0x01) or start != d.start or length != d.length or control & 0x0F != d.control & 0x0F:
                return False
        return True

    def _pd_sms_check(self) -> int:
        out_size, in_size = self._pd.size()
        for k, size, code in ((2, out_size, AlStatusCode.INVALID_OUTPUT_CONFIG),
                              (3, in_size, AlStatusCode.INVALID_INPUT_CONFIG)):
            start, length, control, _st, act, _pdi = self.sm(k)
            d = self.sms[k]
            if size == 0:
                if act & 0x01 and length:
                    return code
                continue
            if not (act & 0x01) or start != d.start or length != size or control & 0x0F != d.control & 0x0F:
                return code
        return 0
