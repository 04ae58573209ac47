"""The pysoem backend: a NIC (or the master end of a veth pair facing ``ecat-sim``).

Start-up (not cycle-safe, seconds): ``open`` and ``start`` by its part
:class:`~bus_agent.bus.pysoem_startup.PysoemStartup`; distributed clocks by its part
:class:`~bus_agent.bus.pysoem_dc.PysoemDc`. Cycle-safe: ``exchange`` (LRW: send_processdata + receive_processdata), ``inputs`` /
``set_outputs`` (preallocated records, one struct pack/unpack per slave).

Management (``read_al_status``, ``request_al_state``, ``recover``, SDO) is meant for the cycle's
management thread, concurrently with ``exchange`` in the cycle thread: SOEM gives every
datagram its own frame index and serialises the NIC with mutexes, so the two threads' frames
do not mix. Each management call is a few single datagrams with a short timeout
(:data:`MGMT_TIMEOUT_US`), never one long blocking SOEM call.

GIL: pysoem holds the GIL in its calls unless asked; process-data calls, config_init and SDO
transfers here release it (``release_gil=True``). The datagram primitives (``_fprd`` /
``_fpwr``), ``recover_slave`` and ``write_state`` cannot release it, so each is bounded by its
timeout (at most :data:`MGMT_TIMEOUT_US` per datagram): the cycle thread waits for the GIL at
most about that long. SOEM's ``reconfig_slave`` / ``statecheck`` / ``readstate`` are *not*
used after start-up: they hold the GIL for up to 2 s per AL state (EC_TIMEOUTSTATE) with a
slave that answers but does not change state; recovery re-does their steps one datagram at a
time instead (SM and FMMU registers as read back from the slave in OP at start-up).
"""

from __future__ import annotations

import logging
import struct
import time
from typing import Any, Callable, Mapping, Sequence

from bus_agent.bus.base import ALState, BusError, SlaveALStatus, SlaveInfo, al_status_text
from bus_agent.bus.codec import DriveCodec
from bus_agent.bus.emergency import EmergencyLog
from bus_agent.bus.pdo import DriveInputs, DriveOutputs
from bus_agent.bus.pysoem_dc import MGMT_TIMEOUT_US, PysoemDc
from bus_agent.bus.pysoem_init_cmds import apply_safeop_sdos
from bus_agent.bus.pysoem_startup import (CONFIG_INIT_DEADLINE_S, REG_EEP_CONFIG, REG_FMMU0, REG_SM0, SOEM_CALL_S,
                                          STATE_ACK, PysoemStartup, al_state)
from bus_agent.startup_guard import StartupSteps

log = logging.getLogger(__name__)

#: Kept for callers of the previous name.
RECOVER_TIMEOUT_US = MGMT_TIMEOUT_US
#: A slave whose AL status reads get no frame back (lost/late frames: the link, not the slave)
#: keeps its last known status for this long before it reads NONE. A frame that comes back
#: without the slave's working counter (the slave is silent) reads NONE at once.
NO_FRAME_GRACE_S = 0.05
# ESC registers (ETG.1000.4 Table 31 ff.)
_AL_CONTROL_REG = 0x0120
_AL_STATUS_REG = 0x0130      # 0x0130 AL status, 0x0134 AL status code


class PysoemBus:
    """The Bus protocol over pysoem (backend "pysoem"). It owns two parts and calls them: start-up
    (:class:`PysoemStartup`: open, start, SDO transfers, a recovered slave's configuration) and
    distributed clocks (:class:`PysoemDc`); the cycle and management paths are its own."""

    backend = "pysoem"
    express_exchange = True

    def __init__(self, ifname: str, receive_timeout_us: int = 1000, release_gil: bool = True,
                 config_init_deadline_s: float = CONFIG_INIT_DEADLINE_S, soem_call_s: float = SOEM_CALL_S) -> None:
        import pysoem  # imported here so the sim backend needs no pysoem

        self.ifname = ifname
        self.receive_timeout_us = receive_timeout_us
        self.release_gil = release_gil
        self._dc = PysoemDc(ifname)
        # start-up exchanges through the bus's exchange as it is when called (benchmarks and tests wrap it)
        self._startup = PysoemStartup(pysoem, ifname, self._dc, config_init_deadline_s=config_init_deadline_s,
                                      soem_call_s=soem_call_s, on_emergency=self._on_emergency,
                                      exchange=lambda: self.exchange(), on_segment=self._on_segment)
        # The segment as start-up set it up (:meth:`_on_segment`), read by the cycle path directly
        self._master: Any = None
        self._slaves: list[Any] = []
        self._inputs: list[DriveInputs] = []
        self._codecs: list[DriveCodec] = []
        self._decode_all: Callable[[], list[int] | None] = lambda: None
        self._changed: list[int] | None = None
        self._closed = False
        #: Per slave: the recovery step under way ("to_init", "to_preop", "to_safeop", "to_op").
        self._recover_step: dict[int, str] = {}
        self._al_last: dict[int, SlaveALStatus] = {}
        self._no_frame_since: float | None = None
        self._frames_back = 0
        self._frames_back_at = 0
        self._poll_first = -1
        self._emcy = EmergencyLog()
        self._mailbox_turn = -1
        #: position -> (error code, text) of its last CoE emergency (read by the cycle for error_text)
        self.error_texts = self._emcy.error_texts

    def _on_segment(self, master: Any, slaves: list[Any], inputs: list[DriveInputs], codecs: list[DriveCodec],
                    decode_all: Callable[[], list[int] | None]) -> None:
        """Start-up's segment, whenever it changes (opened, mapped, released)."""
        self._master, self._slaves, self._inputs, self._codecs, self._decode_all = (
            master, slaves, inputs, codecs, decode_all)

    # ---- start-up (the PysoemStartup part) ---------------------------------------------------------

    @property
    def startup_steps(self) -> StartupSteps:
        """The steps of start-up with their deadlines (the agent sets its own, guarded, before open)."""
        return self._startup.steps

    @startup_steps.setter
    def startup_steps(self, steps: StartupSteps) -> None:
        self._startup.steps = steps

    def open(self) -> list[SlaveInfo]:
        """Open the NIC and find the slaves (INIT -> PRE-OP). Raises BusError."""
        return self._startup.open()

    def start(self, mapping_override: Mapping[int, object] | None = None) -> int:
        """Each slave's PDO mapping and start-up SDOs in PRE-OP, its codec, then SAFE-OP and OP
        (:meth:`PysoemStartup.start`). Returns the expected working counter. Raises BusError."""
        return self._startup.start(mapping_override)

    @property
    def expected_wkc(self) -> int:
        return self._startup.expected_wkc

    def codec(self, position: int) -> DriveCodec:
        """The process-data codec of the slave at ``position`` (after start())."""
        return self._codecs[position]

    def preop_sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        """An object read in PRE-OP at start-up (0x6502), else an SDO upload now."""
        v = self._startup.preop_values.get((position, index)) if subindex == 0 else None
        if v is None:
            return self.sdo_read(position, index, subindex, size)
        if isinstance(v, BusError):
            raise v
        return v

    # ---- distributed clocks (the PysoemDc part) ------------------------------------------------

    def dc_capable(self, position: int) -> bool:
        """True when the slave's ESC has distributed clocks (0x0008 bit 2), read at open()."""
        return self._dc.capable[position]

    def dc_states(self) -> list[str]:
        """Per slave: "sync0" (SYNC0 started), "off" (DC capable, unused) or "none"."""
        return self._dc.states()

    @property
    def dc_active(self) -> bool:
        return bool(self._dc.sync0)

    def dc_time_ns(self) -> int:
        """System time of the reference clock from the last frame's FRMW (0x0910). Cycle-safe."""
        return self._master.dc_time

    # ---- cycle ------------------------------------------------------------------------------------

    def exchange(self) -> int:
        """One LRW: send outputs, receive inputs. Returns the working counter. Cycle-safe."""
        m = self._master
        rg = self.release_gil
        m.send_processdata(release_gil=rg)
        wkc = m.receive_processdata(self.receive_timeout_us, release_gil=rg)
        if wkc >= 0:
            self._frames_back += 1  # the link carries frames (read by the management thread)
        # every slave's inputs in one pass, decoding only those whose bytes changed (codec.segment_decoder)
        self._changed = self._decode_all()
        return wkc

    def inputs_changed(self) -> list[int] | None:
        """Positions of the slaves whose inputs changed at the last :meth:`exchange` (the others'
        records hold the same values as before). Optional hook of the Bus protocol. Cycle-safe."""
        return self._changed

    def inputs(self, position: int) -> DriveInputs:
        """The TxPDO of the slave as the last :meth:`exchange` received it, decoded by its codec
        into a preallocated record (valid until the next exchange). Cycle-safe: no work."""
        return self._inputs[position]

    def set_outputs(self, position: int, outputs: DriveOutputs) -> None:
        """RxPDO for the next exchange (copied into the IO map) through the slave's codec. Cycle-safe."""
        self._slaves[position].output = self._codecs[position].encode(outputs)

    # ---- management (management thread; bounded datagrams) -----------------------------------

    def _fprd(self, position: int, register: int, size: int) -> tuple[bytes | None, bool]:
        """One FPRD of at most MGMT_TIMEOUT_US: (data, False); (None, False) when the frame came
        back without this slave's working counter; (None, True) when no frame came back (SOEM
        waits for it at least one scheduler tick: its 1 us SO_RCVTIMEO rounds up to a jiffy)."""
        t0 = time.perf_counter_ns()
        try:
            return bytes(self._slaves[position]._fprd(register, size, MGMT_TIMEOUT_US)), False
        except Exception as e:
            dt = time.perf_counter_ns() - t0
            log.debug("slave %d: FPRD 0x%04X failed after %d us: %r", position, register, dt // 1000, e)
            return None, dt >= MGMT_TIMEOUT_US * 1000

    def _write_al_control(self, position: int, value: int) -> bool:
        """FPWR 0x0120 (AL control), one datagram; False when the slave did not take it."""
        try:
            self._slaves[position]._fpwr(_AL_CONTROL_REG, struct.pack("<H", value), MGMT_TIMEOUT_US)
            return True
        except Exception:
            return False

    def read_al_status(self) -> Sequence[SlaveALStatus]:
        """AL status (0x0130) and status code (0x0134) of every slave, one FPRD each (management
        thread). A silent slave (its FPRD comes back without working counter) reads NONE. When a
        frame does not come back at all, the rest of this read is skipped (each such wait holds
        the GIL for a scheduler tick) and the slaves not read keep their last status until no
        frame (management or process data) has come back for :data:`NO_FRAME_GRACE_S`, then
        read NONE: lost frames are the
        link's, not a slave's. The first slave read rotates, so each gets its turn."""
        none = SlaveALStatus(ALState.NONE, False, 0)
        n = len(self._slaves)
        now = time.monotonic()
        first = self._poll_first = (self._poll_first + 1) % n if n else 0
        out: list[SlaveALStatus | None] = [None] * n
        link_lost = False
        for k in range(n):
            pos = (first + k) % n
            if link_lost:
                continue
            raw, no_frame = self._fprd(pos, _AL_STATUS_REG, 6)
            if raw is None and no_frame:
                link_lost = True
                if self._no_frame_since is None or self._frames_back != self._frames_back_at:
                    # no frame since now (process-data frames came back before this one)
                    self._no_frame_since, self._frames_back_at = now, self._frames_back
                continue
            self._no_frame_since = None
            if raw is None:
                out[pos] = none
            else:
                w, _r, code = struct.unpack("<HHH", raw)
                out[pos] = SlaveALStatus(al_state(w), bool(w & STATE_ACK), code)
        if link_lost:
            stale = self._no_frame_since is not None and now - self._no_frame_since >= NO_FRAME_GRACE_S
            out = [st if st is not None else (none if stale else self._al_last.get(pos, none))
                   for pos, st in enumerate(out)]
        for pos, st in enumerate(out):
            self._al_last[pos] = st  # type: ignore[assignment]
        return out  # type: ignore[return-value]

    def request_al_state(self, position: int | None, state: ALState) -> None:
        """Write AL control (0x0120) for one slave (FPWR, bounded) or all (broadcast), with the
        error acknowledge. No wait."""
        if position is None:
            self._startup.request_all(state)
        elif not self._write_al_control(position, int(state) | STATE_ACK):
            log.debug("slave %d: AL control %s not taken", position, state.wire_name)

    def recover(self, position: int) -> bool:
        """One step towards OP for a lost or fallen slave; call again (every few ms) until True.

        Each step is a few datagrams of at most :data:`MGMT_TIMEOUT_US` (plus, once, the SDOs of
        a PDO mapping override, GIL released). Steps, from the AL status (0x0130) read first:
        no answer -> SOEM ``recover_slave`` (re-address a slave that came back reset);
        error flag -> acknowledge; INIT -> SMs (as read back at start-up), EEPROM to PDI, request
        PRE-OP; PRE-OP reached from there -> PDO mapping override, FMMUs, request SAFE-OP; any
        other PRE-OP/BOOT -> request INIT first; SAFE-OP -> request OP. True once it reports OP
        without error. Nothing here waits for a state: the next call looks again."""
        s = self._slaves[position]
        step = self._recover_step.get(position)
        raw, no_frame = self._fprd(position, _AL_STATUS_REG, 6)
        if raw is None and no_frame:
            return False  # the frame was lost (the link, not the slave): look again next call
        st = None
        if raw is not None:
            w, _r, code = struct.unpack("<HHH", raw)
            st = SlaveALStatus(al_state(w), bool(w & STATE_ACK), code)
        if st is None:
            self._recover_step.pop(position, None)
            try:  # not answering at its address: if it came back reset, give it its address again
                if s.recover(MGMT_TIMEOUT_US) > 0:
                    log.info("slave %d: answers again at its station address", position)
            except Exception as e:
                log.debug("slave %d recover_slave: %s", position, e)
            return False
        state = st.state
        if state == ALState.OP and not st.error:
            self._recover_step.pop(position, None)
            s.is_lost = False
            return True
        if st.error:
            log.info("slave %d in %s with error 0x%04X %s: acknowledging", position, state.wire_name,
                     st.status_code, al_status_text(st.status_code))
            self._write_al_control(position, int(state) | STATE_ACK)
            if state != ALState.SAFEOP:
                self._recover_step.pop(position, None)  # start again from INIT
            return False
        if state == ALState.SAFEOP:
            if position in self._dc.sync0 and step == "to_safeop" and not self._startup.setups[position].sync0_before_safeop:
                # a power cycle reset the slave's DC unit: SYNC0 again, OP after its first pulse
                try:
                    self._dc.start_sync0(self._slaves, [position])
                except BusError as e:
                    log.warning("%s", e)
                    return False
                self._recover_step[position] = "sync0"
                return False
            if step == "sync0" and self._dc.sync0_pending(position):
                return False
            if step in ("to_safeop", "sync0") and not self._safeop_sdos_again(position):
                return False
            self._write_al_control(position, int(ALState.OP))
            self._recover_step[position] = "to_op"
            return False
        if state == ALState.INIT:
            cfg = self._startup.esc_config.get(position)
            if cfg is None:
                raise BusError(f"slave {position}: no SM/FMMU configuration to restore (start() not done)")
            sm, _fmmu = cfg
            if step != "to_preop":
                log.info("slave %d in init: reconfiguring", position)
            try:
                if sm:
                    s._fpwr(REG_SM0, sm, MGMT_TIMEOUT_US)
                s._fpwr(REG_EEP_CONFIG, b"\x01\x00", MGMT_TIMEOUT_US)
            except Exception as e:
                log.debug("slave %d: SM configuration not taken: %s", position, e)
                return False
            self._write_al_control(position, int(ALState.PREOP))
            self._recover_step[position] = "to_preop"
            return False
        if state == ALState.PREOP and step in ("to_preop", "sync0_preop", "to_safeop"):
            if step == "to_preop":
                _sm, fmmu = self._startup.esc_config[position]
                try:
                    self._startup.configure_slave(position)  # a power cycle forgot mapping and SDOs
                    if fmmu:
                        s._fpwr(REG_FMMU0, fmmu, MGMT_TIMEOUT_US)
                    if position in self._dc.sync0:  # ... and its DC time: set again before SYNC0
                        self._dc.restore_time(self._slaves, position, self._fprd)
                        if self._startup.setups[position].sync0_before_safeop:
                            self._dc.start_sync0(self._slaves, [position])
                            self._recover_step[position] = "sync0_preop"
                            return False
                except BusError as e:
                    log.warning("%s", e)
                    self._recover_step.pop(position, None)
                    return False
                except Exception as e:
                    log.debug("slave %d: FMMU configuration not taken: %s", position, e)
                    return False
            if step == "sync0_preop" and self._dc.sync0_pending(position):
                return False
            self._write_al_control(position, int(ALState.SAFEOP))
            self._recover_step[position] = "to_safeop"
            return False
        # PRE-OP/BOOT not reached through this sequence (NMT, a reset): from INIT, fully.
        self._write_al_control(position, int(ALState.INIT))
        self._recover_step[position] = "to_init"
        return False

    def _safeop_sdos_again(self, position: int) -> bool:
        """After a reconfiguration: the slave's SAFE-OP start-up SDOs (ESI ``SO`` InitCmds), as at
        start-up. False (try again at the next call) when one is refused."""
        setup = self._startup.setups.get(position)
        if setup is None or not setup.safeop_sdos:
            return True
        try:
            apply_safeop_sdos(self._slaves, {position: setup}, self._startup.sdo, lambda: None)
        except BusError as e:
            log.warning("%s", e)
            return False
        return True

    # ---- emergencies (CoE EMCY) -------------------------------------------------------------------

    def _on_emergency(self, position: int, e: Any) -> None:
        """pysoem's emergency callback (a ``pysoem.Emergency``), on the thread that read the
        mailbox: start-up or the management thread."""
        text = self._emcy.record(position, e.error_code, e.error_reg)
        log.warning("%s: slave %d: EMCY 0x%04X (%s), error register 0x%02X, data %02X %04X %04X", self.ifname,
                    position, e.error_code, text, e.error_reg, e.b1, e.w1, e.w2)

    def take_emergencies(self) -> list[tuple[int, int, int, str]]:
        """CoE emergencies since the last call as (position, error code, register, text). Cycle-safe."""
        return self._emcy.take()

    def poll_mailbox(self, position: int | None) -> None:
        """Read the slave's mailbox if it holds something (one datagram when empty, holding the
        GIL for it): an emergency goes to the log. ``None``: the next slave in turn. Skipped
        while an SDO transfer runs (on any thread). Raises BusError."""
        if position is None:
            if not self._slaves:
                return
            position = self._mailbox_turn = (self._mailbox_turn + 1) % len(self._slaves)
        lock = self._startup.mailbox_lock
        if not lock.acquire(blocking=False):
            return  # an SDO transfer is reading the mailboxes: it hands any emergency over itself
        try:
            self._slaves[position].mbx_receive()
        except Exception as e:
            raise BusError(f"slave {position}: mailbox read failed: {type(e).__name__} {e}") from None
        finally:
            lock.release()

    def sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        """CoE SDO upload. Raises BusError with the abort code or mailbox error (NoAnswer: none came).
        Not cycle-safe (mailbox round trips)."""
        s = self._slaves[position]
        return bytes(self._startup.sdo(position, lambda: s.sdo_read(index, subindex, size, release_gil=True),
                               f"slave {position}: SDO upload 0x{index:04X}:{subindex}"))

    def sdo_write(self, position: int, index: int, subindex: int, data: bytes) -> None:
        """CoE SDO download. Raises BusError with the abort code."""
        s = self._slaves[position]
        self._startup.sdo(position, lambda: s.sdo_write(index, subindex, bytes(data), release_gil=True),
                  f"slave {position}: SDO download 0x{index:04X}:{subindex}")

    def close(self) -> None:
        """All slaves to INIT (briefly checked), then release the NIC. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._master is not None:
            self._startup.release("on close")
