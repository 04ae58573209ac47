"""The pysoem backend: a NIC (or the master end of a veth pair facing ``ecat-sim``).

Start-up (not cycle-safe, seconds): ``open`` = Master.open + config_init (retried until a
deadline) + identity; ``start`` = PDO mapping override by SDO in PRE-OP through pysoem's
``config_func`` hook, config_map, SAFE-OP, then OP with process data flowing, each with a
deadline; errors name the slave and decode the AL status code (register 0x0134, ETG.1000.6
Table 11). Cycle-safe: ``exchange`` (LRW: send_processdata + receive_processdata), ``inputs`` /
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

from bus_agent.bus.base import (ALState, BusError, SlaveALStatus, SlaveIdentity, SlaveInfo,
                                al_status_text)
from bus_agent.bus.codec import DriveCodec, segment_decoder
from bus_agent.bus.mapping import (MappingError, SlaveMapping, SlaveSetup, abort_hint, check_mapping, describe,
                                   plan_writes, read_mapping)
from bus_agent.bus.pdo import DriveInputs, DriveOutputs
from bus_agent.bus.pysoem_dc import MGMT_TIMEOUT_US, SYNC0_START_S, PysoemDc

log = logging.getLogger(__name__)

STATE_ACK = 0x10
#: How long open() keeps retrying config_init when no slave answers.
CONFIG_INIT_DEADLINE_S = 10.0
#: Deadlines of the AL transitions in start().
SAFEOP_DEADLINE_S = 5.0
OP_DEADLINE_S = 5.0
#: While waiting for an AL state, request it again this often (s).
STATE_REWRITE_S = 0.25
#: Short state_check polls (us) so the GIL is given up between them.
STATE_POLL_US = 5000
#: Kept for callers of the previous name.
RECOVER_TIMEOUT_US = MGMT_TIMEOUT_US
#: A slave whose AL status reads get no frame back (lost/late frames: the link, not the slave)
#: keeps its last known status for this long before it reads NONE. A frame that comes back
#: without the slave's working counter (the slave is silent) reads NONE at once.
NO_FRAME_GRACE_S = 0.05
#: SOEM's config_map sizes each slave's process data from the PDO objects it uploads by SDO
#: itself, and counts an entry whose upload got no answer as 0 bits, without an error. A size
#: that disagrees with the mapping read here is such a lost answer (a stalled slave or link):
#: start() goes back to INIT and config_init and tries again, this many times in all, before it
#: reports the mismatch.
START_ATTEMPTS = 3
#: Uploads of the PDO mapping in PRE-OP: a transfer without an answer (not an abort) is tried
#: again, this many times in all. Reads only: they change nothing on the slave.
MAPPING_READ_ATTEMPTS = 3
# ESC registers (ETG.1000.4 Table 31 ff.)
_REG_FMMU_COUNT = 0x0004     # 0x0004 FMMUs supported, 0x0005 SMs supported
_REG_EEP_CONFIG = 0x0500     # EEPROM access: bit 0 = PDI
_REG_FMMU0 = 0x0600          # 16 bytes per FMMU
_REG_SM0 = 0x0800            # 8 bytes per SyncManager
_AL_CONTROL_REG = 0x0120
_AL_STATUS_REG = 0x0130      # 0x0130 AL status, 0x0134 AL status code


class ProcessDataSizeError(BusError):
    """The process data SOEM sized for a slave disagrees with the slave's PDO mapping."""


def _al_state(value: int) -> ALState:
    try:
        return ALState(value & 0x0F)
    except ValueError:
        return ALState.NONE


class PysoemBus(PysoemDc):
    """The Bus protocol over pysoem (backend "pysoem"); distributed clocks in :class:`PysoemDc`."""

    backend = "pysoem"
    express_exchange = True

    def __init__(self, ifname: str, receive_timeout_us: int = 1000, release_gil: bool = True,
                 config_init_deadline_s: float = CONFIG_INIT_DEADLINE_S) -> None:
        import pysoem  # imported here so the sim backend needs no pysoem

        self._pysoem = pysoem
        self.ifname = ifname
        self.receive_timeout_us = receive_timeout_us
        self.release_gil = release_gil
        self.config_init_deadline_s = config_init_deadline_s
        self._master: Any = None
        self._slaves: list[Any] = []
        self._inputs: list[DriveInputs] = []
        self._expected_wkc = 0
        self._setups: dict[int, SlaveSetup] = {}
        self._dc_capable: list[bool] = []
        self._sync0: dict[int, tuple[int, int]] = {}
        self._sync0_armed_at: dict[int, float] = {}
        #: Per SYNC0 slave: its propagation delay (0x0928) as config_dc set it, for recovery.
        self._dc_delay: dict[int, int] = {}
        self._preop_values: dict[tuple[int, int], bytes | BusError] = {}
        self._mappings: dict[int, SlaveMapping] = {}
        self._codecs: list[DriveCodec] = []
        self._decode_all: Callable[[], list[int] | None] = lambda: None
        self._changed: list[int] | None = None
        self._opened = False
        self._closed = False
        #: Per slave: the recovery step under way ("to_init", "to_preop", "to_safeop", "to_op").
        self._recover_step: dict[int, str] = {}
        #: Per slave: SM and FMMU register blocks read back in OP at start-up (for reconfiguration).
        self._esc_config: dict[int, tuple[bytes, bytes]] = {}
        self._al_last: dict[int, SlaveALStatus] = {}
        self._no_frame_since: float | None = None
        self._frames_back = 0
        self._frames_back_at = 0
        self._poll_first = -1

    # ---- start-up ------------------------------------------------------------------------------

    def open(self) -> list[SlaveInfo]:
        """Open the NIC and find the slaves (INIT -> PRE-OP). Raises BusError."""
        pysoem = self._pysoem
        m = pysoem.Master()
        try:
            m.open(self.ifname)
        except Exception as e:
            raise BusError(f"{self.ifname}: cannot open the interface: {e}") from None
        self._master = m
        deadline = time.monotonic() + self.config_init_deadline_s
        n = 0
        while True:
            try:
                n = m.config_init(release_gil=True)
            except Exception as e:
                self._abort_open()
                raise BusError(f"{self.ifname}: config_init failed: {e}") from None
            if n > 0 or time.monotonic() >= deadline:
                break
            time.sleep(0.2)
        if n <= 0:
            self._abort_open()
            raise BusError(f"{self.ifname}: no slave answered within {self.config_init_deadline_s:g} s")
        self._slaves = list(m.slaves)
        self._inputs = [DriveInputs() for _ in self._slaves]
        self._dc_capable = [self._read_dc_capable(s) for s in self._slaves]
        self._opened = True
        infos = []
        for pos, s in enumerate(self._slaves):
            infos.append(SlaveInfo(pos, s.name, SlaveIdentity(s.man, s.id, s.rev, 0)))
            log.info("%s: slave %d %r vendor 0x%08X product 0x%08X revision 0x%08X",
                     self.ifname, pos, s.name, s.man, s.id, s.rev)
        return infos

    def _abort_open(self) -> None:
        try:
            self._master.close()
        except Exception:
            pass
        self._master = None

    def _config_func(self, position: int) -> None:
        """pysoem PO2SO hook, in PRE-OP (inside config_map): the slave's mapping and start-up SDOs."""
        self._configure_slave(position)

    def _configure_slave(self, position: int) -> SlaveMapping:
        """In PRE-OP: read the drive's PDO mapping, write what its policy wants (only what
        differs), read it back, check it, then apply the start-up SDOs. SDOs release the GIL.
        Raises BusError naming the slave, the object, the abort code and what to do."""
        setup = self._setups.get(position, SlaveSetup())
        s = self._slaves[position]
        who = f"slave {position} ({s.name!r})"

        def read(index: int, sub: int, size: int) -> bytes:
            return bytes(self._sdo(lambda: s.sdo_read(index, sub, size, release_gil=True),
                                   f"{who}: reading its PDO mapping: SDO upload 0x{index:04X}:{sub:02X}",
                                   attempts=MAPPING_READ_ATTEMPTS))

        current = read_mapping(read)
        policy = setup.policy
        steps = plan_writes(policy, current)
        for step in steps:
            self._sdo(lambda: s.sdo_write(step.index, step.subindex, step.data, release_gil=True),
                      f"{who}: mapping policy {policy.policy!r}: SDO write {step} = 0x{step.value:X}", hint=True)
        if steps:
            current = read_mapping(read)
            log.info("%s: mapping policy %s written (%d SDO downloads): %s", who, policy.policy, len(steps),
                     describe(current))
        problems = check_mapping(current)
        if problems:
            hint = ("use mapping policy 'default' (write the project's layout) or 'predefined'/'explicit'"
                    if policy.policy == "drive" else "choose other PDOs or entries")
            raise BusError(f"{who}: its PDO mapping cannot run the cycle: {'; '.join(problems)} "
                           f"(mapping policy {policy.policy!r}: {describe(current)}); {hint}")
        for sdo in setup.sdos:
            self._sdo(lambda: s.sdo_write(sdo.index, sdo.subindex, sdo.data, release_gil=True), f"{who}: start-up SDO {sdo}")
        if setup.sdos:
            log.info("%s: %d start-up SDO(s) applied", who, len(setup.sdos))
        if position < len(self._codecs) and self._codecs[position].mapping != current:
            raise BusError(f"{who}: its PDO mapping is not the one of start-up ({describe(current)}, was "
                           f"{describe(self._codecs[position].mapping)}): not brought back")
        self._mappings[position] = current
        try:  # for preop_sdo_read: the cycle reads it after start() without a mailbox round trip
            self._preop_values[(position, 0x6502)] = read(0x6502, 0, 4)
        except BusError as e:
            self._preop_values[(position, 0x6502)] = e
        return current

    def _sdo(self, transfer: Callable[[], Any], what: str, hint: bool = False, attempts: int = 1) -> Any:
        """One SDO transfer; its failure as a BusError naming ``what``, the abort code and its
        meaning (with ``hint``: what to do instead). A transfer that got no answer (not an
        abort, which is the slave's definite no) is made again up to ``attempts`` times in all:
        only for transfers that may be repeated (uploads)."""
        for attempt in range(1, attempts + 1):
            try:
                return transfer()
            except self._pysoem.SdoError as e:
                code = e.abort_code & 0xFFFFFFFF
                raise BusError(f"{what} aborted 0x{code:08X} ({e.desc})"
                               + (f": {abort_hint(code)}" if hint else "")) from None
            except Exception as e:
                # pysoem's WkcError says nothing by itself: the mailbox exchange got no answer
                why = str(e) or (f"{type(e).__name__}: no answer from the slave's mailbox"
                                 if type(e).__name__ == "WkcError" else type(e).__name__)
                if attempt < attempts:
                    log.warning("%s: %s (attempt %d of %d); trying again", what, why, attempt, attempts)
                    continue
                raise BusError(f"{what} failed: {why}" + (f" ({attempts} attempts)" if attempts > 1 else "")) from None
        raise AssertionError("unreachable")

    def preop_sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        """An object read in PRE-OP at start-up (0x6502), else an SDO upload now."""
        v = self._preop_values.get((position, index)) if subindex == 0 else None
        if v is None:
            return self.sdo_read(position, index, subindex, size)
        if isinstance(v, BusError):
            raise v
        return v

    def codec(self, position: int) -> DriveCodec:
        """The process-data codec of the slave at ``position`` (after start())."""
        return self._codecs[position]

    def start(self, mapping_override: Mapping[int, object] | None = None) -> int:
        """Read (and per policy write) each slave's PDO mapping and apply its start-up SDOs in
        PRE-OP, build its codec, then SAFE-OP and OP, each with a deadline. ``mapping_override``
        maps slave positions to a :class:`SlaveSetup` (default: policy ``drive``, no SDOs).
        Returns the expected working counter. Raises BusError naming the slave (and the object,
        abort code or AL status code).

        A process-data size that disagrees with the mapping (see :data:`START_ATTEMPTS`) sends
        the segment back to INIT and config_init for another try; the slaves found then must be
        the ones found by open()."""
        if not self._opened:
            raise BusError(f"{self.ifname}: start() before open()")
        for attempt in range(1, START_ATTEMPTS + 1):
            try:
                return self._start_once(mapping_override)
            except ProcessDataSizeError as e:
                if attempt == START_ATTEMPTS:
                    raise BusError(f"{e} ({START_ATTEMPTS} attempts from INIT)") from None
                log.warning("%s: %s; SOEM's own reading of the PDO mapping lost an answer: from INIT "
                            "again (attempt %d of %d)", self.ifname, e, attempt + 1, START_ATTEMPTS)
                self._reopen()
        raise AssertionError("unreachable")

    def _reopen(self) -> None:
        """Every slave to INIT, the master closed, then open() again; the same slaves (name and
        identity per position) must answer."""
        before = [(s.name, s.man, s.id, s.rev) for s in self._slaves]
        m = self._master
        try:
            self.request_al_state(None, ALState.INIT)
            m.state_check(int(ALState.INIT), 50_000)
        except Exception as e:
            log.warning("%s: INIT request before another start failed: %s", self.ifname, e)
        finally:
            try:
                m.close()
            except Exception:
                pass
            self._master = None
            self._opened = False
        self.open()
        after = [(s.name, s.man, s.id, s.rev) for s in self._slaves]
        if after != before:
            raise BusError(f"{self.ifname}: the segment changed during start-up: {len(before)} slave(s) "
                           f"{before} before, {len(after)} {after} now")

    def _start_once(self, mapping_override: Mapping[int, object] | None) -> int:
        """One try of :meth:`start`; raises ProcessDataSizeError on a size mismatch."""
        self._codecs = []
        self._mappings = {}
        self._preop_values = {}
        pysoem = self._pysoem
        m = self._master
        setups: dict[int, SlaveSetup] = {}
        for pos, setup in (mapping_override or {}).items():
            if not 0 <= pos < len(self._slaves):
                raise BusError(f"{self.ifname}: a mapping policy is configured for slave {pos}, which is not on the segment")
            if not isinstance(setup, SlaveSetup):
                raise BusError(f"slave {pos}: mapping setup must be a SlaveSetup, got {type(setup).__name__}")
            setups[pos] = setup
        self._setups = setups
        self._sync0 = {pos: st.sync0 for pos, st in setups.items() if st.sync0 is not None}
        before_safeop = any(st.sync0_before_safeop for st in setups.values() if st.sync0 is not None)
        if self._sync0:
            # PRE-OP: find the DC slaves, latch and set offsets and delays; from here on every
            # process-data frame carries the FRMW of the reference clock (master.dc_time)
            found = m.config_dc()
            if not found:
                raise BusError(f"{self.ifname}: config_dc found no DC slave, although slave(s) "
                               f"{sorted(self._sync0)} report DC in 0x0008")
        m.manual_state_change = before_safeop  # config_map requests SAFE-OP by itself otherwise
        for pos, s in enumerate(self._slaves):
            s.config_func = self._config_func
        try:
            m.config_map()
        except BusError:
            raise
        except pysoem.ConfigMapError as e:
            details = "; ".join(str(x) for x in e.error_list)
            raise BusError(f"{self.ifname}: config_map: {details}") from None
        except Exception as e:
            raise BusError(f"{self.ifname}: config_map failed: {e}") from None
        self._codecs = []
        for pos, s in enumerate(self._slaves):
            mp = self._mappings[pos]
            try:
                codec = DriveCodec(mp)
            except MappingError as e:
                raise BusError(f"slave {pos} ({s.name!r}): {e}") from None
            if len(s.output) != codec.out_size or len(s.input) != codec.in_size:
                raise ProcessDataSizeError(f"slave {pos} ({s.name!r}): process data is {len(s.output)} bytes out / "
                               f"{len(s.input)} in, its PDO mapping says {codec.out_size}/{codec.in_size} "
                               f"({describe(mp)})")
            self._codecs.append(codec)
            log.info("%s: slave %d: %s; absent actual values: %s; other objects: %s", self.ifname, pos,
                     describe(mp), ", ".join(codec.absent_inputs) or "none", ", ".join(codec.extra_names) or "none")
        self._decode_all = segment_decoder(self._codecs, self._inputs, self._slaves, changes=True)
        if before_safeop:
            self._start_sync0(sorted(self._sync0))
            self._wait_sync0_start()
            m.state = pysoem.SAFEOP_STATE
            m.write_state()
        self._wait_state(ALState.SAFEOP, SAFEOP_DEADLINE_S, exchange=False)
        if self._sync0 and not before_safeop:
            self._start_sync0(sorted(self._sync0))
        self._expected_wkc = m.expected_wkc
        # Outputs must flow while OP is requested, or the SM watchdog trips on the way.
        for pos in range(len(self._slaves)):
            self.set_outputs(pos, DriveOutputs())
        self.exchange()
        self._wait_sync0_start(exchange=True)
        m.state = pysoem.OP_STATE
        m.write_state()
        self._wait_state(ALState.OP, OP_DEADLINE_S, exchange=True)
        self._read_esc_config()
        self._read_dc_delays()
        log.info("%s: %d slave(s) in OP, expected working counter %d", self.ifname, len(self._slaves),
                 self._expected_wkc)
        return self._expected_wkc

    def _read_esc_config(self) -> None:
        """Read back each slave's SM (0x0800) and FMMU (0x0600) registers as SOEM programmed
        them, so recover() can program a reset slave again without SOEM's reconfig_slave."""
        for pos, s in enumerate(self._slaves):
            try:
                n_fmmu, n_sm = struct.unpack("<BB", s._fprd(_REG_FMMU_COUNT, 2, 2000))
                sm = bytes(s._fprd(_REG_SM0, 8 * n_sm, 2000)) if n_sm else b""
                fmmu = bytes(s._fprd(_REG_FMMU0, 16 * n_fmmu, 2000)) if n_fmmu else b""
            except Exception as e:
                raise BusError(f"slave {pos} ({s.name!r}): reading back its SM/FMMU registers failed: {e}") from None
            self._esc_config[pos] = (sm, fmmu)

    def _wait_state(self, state: ALState, deadline_s: float, exchange: bool) -> None:
        m = self._master
        deadline = time.monotonic() + deadline_s
        rewrite_at = time.monotonic() + STATE_REWRITE_S
        while True:
            if exchange:
                self.exchange()
            if m.state_check(int(state), STATE_POLL_US) == int(state):
                return
            now = time.monotonic()
            if now >= deadline:
                break
            if now >= rewrite_at:
                # An AL control write lost on the wire (SOEM gives up after its retries) must not
                # fail start-up: writing the same request again is idempotent (ETG.1000.6 0x0120).
                rewrite_at = now + STATE_REWRITE_S
                m.state = int(state)
                m.write_state()
        m.read_state()
        bad = []
        for pos, s in enumerate(self._slaves):
            st = s.state
            if _al_state(st) != state or st & STATE_ACK:
                code = s.al_status
                bad.append(f"slave {pos} ({s.name!r}) in {_al_state(st).wire_name}"
                           + (f" with error: AL status code 0x{code:04X} {al_status_text(code)}" if st & STATE_ACK else ""))
        raise BusError(f"{self.ifname}: {state.wire_name} not reached within {deadline_s:g} s: "
                       + ("; ".join(bad) or "no slave reports an error"))

    @property
    def expected_wkc(self) -> int:
        return self._expected_wkc

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
                out[pos] = SlaveALStatus(_al_state(w), bool(w & STATE_ACK), code)
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
        value = int(state) | STATE_ACK
        if position is None:
            self._master.state = value  # slave 0 of SOEM's list = broadcast (BWR 0x0120)
            self._master.write_state()
        elif not self._write_al_control(position, value):
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
            st = SlaveALStatus(_al_state(w), bool(w & STATE_ACK), code)
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
            if position in self._sync0 and step == "to_safeop" and not self._setups[position].sync0_before_safeop:
                # a power cycle reset the slave's DC unit: SYNC0 again, OP after its first pulse
                try:
                    self._start_sync0([position])
                except BusError as e:
                    log.warning("%s", e)
                    return False
                self._recover_step[position] = "sync0"
                return False
            if step == "sync0" and time.monotonic() - self._sync0_armed_at.get(position, 0.0) < SYNC0_START_S:
                return False
            self._write_al_control(position, int(ALState.OP))
            self._recover_step[position] = "to_op"
            return False
        if state == ALState.INIT:
            cfg = self._esc_config.get(position)
            if cfg is None:
                raise BusError(f"slave {position}: no SM/FMMU configuration to restore (start() not done)")
            sm, _fmmu = cfg
            if step != "to_preop":
                log.info("slave %d in init: reconfiguring", position)
            try:
                if sm:
                    s._fpwr(_REG_SM0, sm, MGMT_TIMEOUT_US)
                s._fpwr(_REG_EEP_CONFIG, b"\x01\x00", MGMT_TIMEOUT_US)
            except Exception as e:
                log.debug("slave %d: SM configuration not taken: %s", position, e)
                return False
            self._write_al_control(position, int(ALState.PREOP))
            self._recover_step[position] = "to_preop"
            return False
        if state == ALState.PREOP and step in ("to_preop", "sync0_preop", "to_safeop"):
            if step == "to_preop":
                _sm, fmmu = self._esc_config[position]
                try:
                    self._configure_slave(position)  # a power cycle forgot mapping and SDOs
                    if fmmu:
                        s._fpwr(_REG_FMMU0, fmmu, MGMT_TIMEOUT_US)
                    if position in self._sync0:  # ... and its DC time: set again before SYNC0
                        self._restore_dc_time(position)
                        if self._setups[position].sync0_before_safeop:
                            self._start_sync0([position])
                            self._recover_step[position] = "sync0_preop"
                            return False
                except BusError as e:
                    log.warning("%s", e)
                    self._recover_step.pop(position, None)
                    return False
                except Exception as e:
                    log.debug("slave %d: FMMU configuration not taken: %s", position, e)
                    return False
            if step == "sync0_preop" and time.monotonic() - self._sync0_armed_at.get(position, 0.0) < SYNC0_START_S:
                return False
            self._write_al_control(position, int(ALState.SAFEOP))
            self._recover_step[position] = "to_safeop"
            return False
        # PRE-OP/BOOT not reached through this sequence (NMT, a reset): from INIT, fully.
        self._write_al_control(position, int(ALState.INIT))
        self._recover_step[position] = "to_init"
        return False

    def sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        """CoE SDO upload. Raises BusError with the abort code. Not cycle-safe (mailbox round trips)."""
        s = self._slaves[position]
        return bytes(self._sdo(lambda: s.sdo_read(index, subindex, size, release_gil=True),
                               f"slave {position}: SDO upload 0x{index:04X}:{subindex}"))

    def sdo_write(self, position: int, index: int, subindex: int, data: bytes) -> None:
        """CoE SDO download. Raises BusError with the abort code."""
        s = self._slaves[position]
        self._sdo(lambda: s.sdo_write(index, subindex, bytes(data), release_gil=True),
                  f"slave {position}: SDO download 0x{index:04X}:{subindex}")

    def close(self) -> None:
        """All slaves to INIT (briefly checked), then release the NIC. Idempotent."""
        if self._closed:
            return
        self._closed = True
        m = self._master
        if m is None:
            return
        try:
            if self._opened:
                self.request_al_state(None, ALState.INIT)
                m.state_check(int(ALState.INIT), 50_000)
        except Exception as e:
            log.warning("%s: INIT request on close failed: %s", self.ifname, e)
        finally:
            try:
                m.close()
            except Exception:
                pass
            self._master = None
