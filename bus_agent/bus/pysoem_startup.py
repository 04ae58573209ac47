"""Start-up of the pysoem backend (:class:`PysoemStartup`, a part
:class:`bus_agent.bus.pysoem_bus.PysoemBus` owns): ``open`` = Master.open + config_init (retried
until a deadline); ``start`` = PDO mapping read (and per policy written) by SDO in PRE-OP through
pysoem's ``config_func`` hook, config_map, SAFE-OP, then OP with process data flowing, each with a
deadline. Errors name the slave and decode the AL status code (register 0x0134, ETG.1000.6
Table 11) or the SDO abort code.
"""

from __future__ import annotations

import functools
import logging
import struct
import threading
import time
from typing import Any, Callable, Mapping

from bus_agent.bus.base import ALState, BusError, NoAnswer, SlaveInfo, SlaveIdentity, al_status_text
from bus_agent.bus.mailbox import SII_MAILBOX_WORD, SII_PROTOCOLS_WORD, SiiMailbox, transfer_failure
from bus_agent.bus.codec import DriveCodec, segment_decoder
from bus_agent.bus.mapping import (MappingError, SlaveMapping, SlaveSetup, abort_hint, check_mapping, describe,
                                   plan_writes, read_mapping)
from bus_agent.bus.pdo import DriveInputs, DriveOutputs
from bus_agent.bus.pysoem_dc import PysoemDc
from bus_agent.bus.pysoem_init_cmds import apply_safeop_sdos
from bus_agent.startup_guard import StartupAbandoned, StartupSteps

log = logging.getLogger("bus_agent.bus.pysoem_bus")

STATE_ACK = 0x10
#: How long open() keeps retrying config_init when no slave answers.
CONFIG_INIT_DEADLINE_S = 10.0
#: Deadline of each SOEM call start-up cannot interrupt (one config_init, config_dc, and in
#: config_map: SOEM's own reading of one slave's PDO sizes (CoE, else its SII), our reading and
#: writing of one slave's mapping): SOEM's own CoE reads of one slave are about 20 uploads of up
#: to 700 ms each when its mailbox stalls. ``[startup] soem_call_s`` in the agent's configuration.
SOEM_CALL_S = 30.0
#: Deadline of opening the NIC and of reading back one slave's registers.
OPEN_S = 5.0
#: Deadlines of the AL transitions in start().
SAFEOP_DEADLINE_S = 5.0
OP_DEADLINE_S = 5.0
#: While waiting for an AL state, request it again this often (s).
STATE_REWRITE_S = 0.25
#: Short state_check polls (us) so the GIL is given up between them.
STATE_POLL_US = 5000
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
REG_FMMU_COUNT = 0x0004     # 0x0004 FMMUs supported, 0x0005 SMs supported
REG_EEP_CONFIG = 0x0500     # EEPROM access: bit 0 = PDI
REG_FMMU0 = 0x0600          # 16 bytes per FMMU
REG_SM0 = 0x0800            # 8 bytes per SyncManager


class ProcessDataSizeError(BusError):
    """The process data SOEM sized for a slave disagrees with the slave's PDO mapping."""


def al_state(value: int) -> ALState:
    """The AL state in bits 0-3 of an AL status word (NONE for a value outside the states)."""
    try:
        return ALState(value & 0x0F)
    except ValueError:
        return ALState.NONE


class PysoemStartup:
    """Start-up of a pysoem master: open() and start(), the SDO transfers of start-up and of the
    management thread (one mailbox lock), and a recovered slave's configuration again. It owns
    the master and the slaves it finds, their mappings, codecs and start-up setups, and tells
    its owner the segment it set up (``on_segment``) whenever that changes."""

    def __init__(self, pysoem: Any, ifname: str, dc: PysoemDc, *, config_init_deadline_s: float, soem_call_s: float,
                 on_emergency: Callable[[int, Any], None], exchange: Callable[[], int],
                 on_segment: Callable[[Any, list[Any], list[DriveInputs], list[DriveCodec],
                                       Callable[[], list[int] | None]], None]) -> None:
        self._pysoem = pysoem
        self.ifname = ifname
        self._dc = dc
        self.config_init_deadline_s = config_init_deadline_s
        self.soem_call_s = soem_call_s
        self._on_emergency = on_emergency
        self._exchange = exchange
        self._on_segment = on_segment
        #: The steps of start-up with their deadlines: deadlines only, until the agent sets its own
        #: (stop signal, guard process) before open
        self.steps = StartupSteps()
        self._map_phase = False
        self.master: Any = None
        self.slaves: list[Any] = []
        self.inputs: list[DriveInputs] = []
        self.codecs: list[DriveCodec] = []
        self.decode_all: Callable[[], list[int] | None] = lambda: None
        self.expected_wkc = 0
        self.opened = False
        self.setups: dict[int, SlaveSetup] = {}
        self._mappings: dict[int, SlaveMapping] = {}
        #: Objects read in PRE-OP at start-up (0x6502), or the error reading them
        self.preop_values: dict[tuple[int, int], bytes | BusError] = {}
        #: Per slave: SM and FMMU register blocks read back in OP at start-up (for reconfiguration).
        self.esc_config: dict[int, tuple[bytes, bytes]] = {}
        #: Per slave: its mailbox as its SII describes it (read at open)
        self._mailboxes: list[SiiMailbox] = []
        #: Held for every mailbox exchange (SDO transfer, mailbox read): a mailbox read on one thread
        #: would take the answer an SDO transfer on another waits for.
        self.mailbox_lock = threading.Lock()
        #: Transfers made again (no answer in time, or an answer of the wrong size) since open.
        self.sdo_retries = 0

    def _publish(self) -> None:
        self._on_segment(self.master, self.slaves, self.inputs, self.codecs, self.decode_all)

    def open(self) -> list[SlaveInfo]:
        """Open the NIC and find the slaves (INIT -> PRE-OP). Raises BusError."""
        pysoem = self._pysoem
        steps = self.steps
        m = pysoem.Master()
        try:
            with steps.step(f"{self.ifname}: open the interface", OPEN_S):
                m.open(self.ifname)
        except StartupAbandoned:
            raise
        except Exception as e:
            raise BusError(f"{self.ifname}: cannot open the interface: {e}") from None
        self.master = m
        self._publish()  # closed by the bus's close() if start-up ends here
        deadline = time.monotonic() + self.config_init_deadline_s
        n = 0
        try:
            while True:
                try:
                    with steps.step(f"{self.ifname}: config_init (SOEM finds the slaves, reads their SII, "
                                    "brings them to PRE-OP)", self.soem_call_s):
                        n = m.config_init(release_gil=True)
                except StartupAbandoned:
                    raise
                except Exception as e:
                    raise BusError(f"{self.ifname}: config_init failed: {e}") from None
                if n > 0 or time.monotonic() >= deadline:
                    break
                steps.sleep(0.2)
        except BaseException:
            self._abort_open()
            raise
        if n <= 0:
            self._abort_open()
            raise BusError(f"{self.ifname}: no slave answered within {self.config_init_deadline_s:g} s")
        self.slaves = list(m.slaves)
        for pos, s in enumerate(self.slaves):
            # CoE emergencies reach the bus's log whenever SOEM reads the mailbox (every SDO
            # transfer, poll_mailbox); without a callback pysoem would fail that SDO transfer
            s.add_emergency_callback(functools.partial(self._on_emergency, pos))
        self.inputs = [DriveInputs() for _ in self.slaves]
        self._dc.read_capable(self.slaves)
        self._mailboxes = [self._read_sii_mailbox(pos, s) for pos, s in enumerate(self.slaves)]
        self.opened = True
        self._publish()
        infos = []
        for pos, s in enumerate(self.slaves):
            infos.append(SlaveInfo(pos, s.name, SlaveIdentity(s.man, s.id, s.rev, 0)))
            log.info("%s: slave %d %r vendor 0x%08X product 0x%08X revision 0x%08X",
                     self.ifname, pos, s.name, s.man, s.id, s.rev)
        return infos

    def _read_sii_mailbox(self, position: int, s: Any) -> SiiMailbox:
        """The slave's mailbox sizes and protocols from its SII (EEPROM words 0x19, 0x1B, 0x1C)."""
        try:
            with self.steps.step(f"slave {position}: reading its SII mailbox words", OPEN_S):
                w18 = bytes(s.eeprom_read(SII_MAILBOX_WORD, 20000))
                w1a = bytes(s.eeprom_read(SII_MAILBOX_WORD + 2, 20000))
                w1c = bytes(s.eeprom_read(SII_PROTOCOLS_WORD, 20000))
                s._fpwr(REG_EEP_CONFIG, b"\x01\x00", 2000)  # the EEPROM back to the PDI, as config_init left it
        except StartupAbandoned:
            self._abort_open()
            raise
        except Exception as e:
            self._abort_open()
            raise BusError(f"slave {position} ({s.name!r}): its SII (mailbox words 0x18-0x1C) not readable: {e}") from None
        return SiiMailbox(receive_size=struct.unpack_from("<H", w18, 2)[0], send_size=struct.unpack_from("<H", w1a, 2)[0],
                          protocols=struct.unpack_from("<H", w1c, 0)[0])

    def _coe_check(self, position: int, what: str) -> None:
        """A transfer with a slave that has no mailbox or no CoE fails at once, saying so."""
        problem = self._mailboxes[position].coe_problem() if position < len(self._mailboxes) else None
        if problem:
            raise BusError(f"{what}: slave {position} {problem}")

    def _abort_open(self) -> None:
        try:
            self.master.close()
        except Exception:
            pass
        self.master = None
        self._publish()

    def _config_func(self, position: int) -> None:
        """pysoem PO2SO hook, in PRE-OP (inside config_map): the slave's mapping and start-up SDOs.
        SOEM calls it for each slave, then reads that slave's PDO sizes itself: each is a step."""
        name = f"slave {position} ({self.slaves[position].name!r})"
        self._config_map_phase(f"config_map: {name}: reading (and per policy writing) its PDO mapping by SDO")
        self.configure_slave(position)
        self._config_map_phase(f"config_map: SOEM reading the PDO sizes of {name} (CoE, else its SII) and the "
                               "slaves after it")

    def _config_map_phase(self, name: str | None) -> None:
        """End config_map's current step and begin ``name`` (None: none), each with soem_call_s."""
        if self._map_phase:
            self._map_phase = False
            self.steps.end()
        if name is not None:
            self.steps.begin(name, self.soem_call_s)
            self._map_phase = True

    def configure_slave(self, position: int) -> SlaveMapping:
        """In PRE-OP: read the drive's PDO mapping, write what its policy wants (only what
        differs), read it back, check it, then apply the start-up SDOs. SDOs release the GIL.
        Raises BusError naming the slave, the object, the abort code and what to do."""
        setup = self.setups.get(position, SlaveSetup())
        s = self.slaves[position]
        who = f"slave {position} ({s.name!r})"

        def read(index: int, sub: int, size: int) -> bytes:
            what = f"{who}: reading its PDO mapping: SDO upload 0x{index:04X}:{sub:02X}"
            for _ in range(MAPPING_READ_ATTEMPTS):
                data = bytes(self.sdo(position, lambda: s.sdo_read(index, sub, size, release_gil=True), what,
                                       attempts=MAPPING_READ_ATTEMPTS))
                if len(data) == size:
                    return data
                # the late answer to an earlier upload of this object (another subindex)
                self.sdo_retries += 1
                log.warning("%s: %d byte(s) where the object has %d: the answer to another upload; again",
                            what, len(data), size)
            raise BusError(f"{what}: answered {len(data)} byte(s) where the object has {size}, "
                           f"{MAPPING_READ_ATTEMPTS} times")

        current = self._read_mapping_twice(read, who)
        policy = setup.policy
        steps = plan_writes(policy, current)
        for step in steps:
            self.sdo(position, lambda: s.sdo_write(step.index, step.subindex, step.data, release_gil=True),
                      f"{who}: mapping policy {policy.policy!r}: SDO write {step} = 0x{step.value:X}", hint=True)
        if steps:
            current = self._read_mapping_twice(read, who)
            log.info("%s: mapping policy %s written (%d SDO downloads): %s", who, policy.policy, len(steps),
                     describe(current))
        problems = check_mapping(current)
        if problems:
            hint = ("use mapping policy 'default' (write the project's layout) or 'predefined'/'explicit'"
                    if policy.policy == "drive" else "choose other PDOs or entries")
            raise BusError(f"{who}: its PDO mapping cannot run the cycle: {'; '.join(problems)} "
                           f"(mapping policy {policy.policy!r}: {describe(current)}); {hint}")
        for sdo in setup.sdos:
            self.sdo(position, lambda: s.sdo_write(sdo.index, sdo.subindex, sdo.data, release_gil=True),
                      f"{who}: start-up SDO {sdo}")
        if setup.sdos:
            log.info("%s: %d start-up SDO(s) applied", who, len(setup.sdos))
        if position < len(self.codecs) and self.codecs[position].mapping != current:
            raise BusError(f"{who}: its PDO mapping is not the one of start-up ({describe(current)}, was "
                           f"{describe(self.codecs[position].mapping)}): not brought back")
        self._mappings[position] = current
        try:  # for preop_sdo_read: the cycle reads it after start() without a mailbox round trip
            self.preop_values[(position, 0x6502)] = bytes(self.sdo(
                position, lambda: s.sdo_read(0x6502, 0, 4, release_gil=True), f"{who}: SDO upload 0x6502:00",
                attempts=MAPPING_READ_ATTEMPTS))
        except BusError as e:
            self.preop_values[(position, 0x6502)] = e
        return current

    def _read_mapping_twice(self, read: Callable[[int, int, int], bytes], who: str) -> SlaveMapping:
        """The slave's mapping (:func:`read_mapping`). After an upload that got no answer in
        time, its answer may still come and be taken for the next upload of the same object:
        SOEM matches an answer's index, not its subindex. So a read during which any upload was
        made again is followed by another, until one goes without and agrees with the one before."""
        retries = self.sdo_retries
        current = read_mapping(read)
        for _ in range(MAPPING_READ_ATTEMPTS):
            if self.sdo_retries == retries:
                return current
            log.warning("%s: reading its PDO mapping needed another try: reading it again (%s)", who,
                        describe(current))
            retries = self.sdo_retries
            again = read_mapping(read)
            if again == current and self.sdo_retries == retries:
                return current
            current = again
        raise BusError(f"{who}: its PDO mapping could not be read twice alike without lost answers "
                       f"({MAPPING_READ_ATTEMPTS + 1} reads; the last: {describe(current)}); check the link")

    def sdo(self, position: int, transfer: Callable[[], Any], what: str, hint: bool = False,
             attempts: int = 1) -> Any:
        """One SDO transfer with the slave at ``position``; its failure as a BusError naming
        ``what`` and what the slave answered: an SDO abort code and its meaning (with ``hint``:
        what to do instead), a mailbox error and its meaning, or no answer (:class:`NoAnswer`).
        Only a transfer that got no answer, whose answer may have been lost, is made again, up to
        ``attempts`` times in all (for transfers that may be repeated: uploads); a definite
        answer is the same every time: reported at once. A slave without a mailbox or without
        CoE is named as such, without a transfer."""
        self._coe_check(position, what)
        for attempt in range(1, attempts + 1):
            self.steps.check()  # a transfer is up to 700 ms: a stop or deadline between them
            try:
                with self.mailbox_lock:
                    return transfer()
            except self._pysoem.SdoError as e:
                code = e.abort_code & 0xFFFFFFFF
                raise BusError(f"{what} aborted 0x{code:08X} ({e.desc})"
                               + (f": {abort_hint(code)}" if hint else "")) from None
            except Exception as e:
                why, lost = transfer_failure(e)
                if not lost:
                    raise BusError(f"{what} failed: {why}") from None
                if attempt < attempts:
                    self.sdo_retries += 1
                    log.warning("%s: %s (attempt %d of %d); trying again", what, why, attempt, attempts)
                    continue
                raise NoAnswer(f"{what} failed: {why}" + (f" ({attempts} attempts)" if attempts > 1 else "")) from None
        raise AssertionError("unreachable")

    def start(self, mapping_override: Mapping[int, object] | None = None) -> int:
        """Read (and per policy write) each slave's PDO mapping and apply its start-up SDOs in
        PRE-OP, build its codec, then SAFE-OP and OP, each with a deadline. ``mapping_override``
        maps slave positions to a :class:`SlaveSetup` (default: policy ``drive``, no SDOs).
        Returns the expected working counter. Raises BusError naming the slave (and the object,
        abort code or AL status code).

        A process-data size that disagrees with the mapping (see :data:`START_ATTEMPTS`) sends
        the segment back to INIT and config_init for another try; the slaves found then must be
        the ones found by open()."""
        if not self.opened:
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
        before = [(s.name, s.man, s.id, s.rev) for s in self.slaves]
        self.release("before another start")
        self.opened = False
        self.open()
        after = [(s.name, s.man, s.id, s.rev) for s in self.slaves]
        if after != before:
            raise BusError(f"{self.ifname}: the segment changed during start-up: {len(before)} slave(s) "
                           f"{before} before, {len(after)} {after} now")

    def release(self, when: str) -> None:
        """Every slave to INIT (briefly checked) if the segment was opened, then the NIC released."""
        m = self.master
        try:
            if self.opened:
                self.request_all(ALState.INIT)
                m.state_check(int(ALState.INIT), 50_000)
        except Exception as e:
            log.warning("%s: INIT request %s failed: %s", self.ifname, when, e)
        finally:
            try:
                m.close()
            except Exception:
                pass
            self.master = None
            self._publish()

    def request_all(self, state: ALState) -> None:
        """AL control (0x0120) of every slave at once (a broadcast), with the error acknowledge."""
        self.master.state = int(state) | STATE_ACK  # slave 0 of SOEM's list = broadcast (BWR 0x0120)
        self.master.write_state()

    def _start_once(self, mapping_override: Mapping[int, object] | None) -> int:
        """One try of :meth:`start`; raises ProcessDataSizeError on a size mismatch."""
        self.codecs = []
        self._mappings = {}
        self.preop_values = {}
        pysoem = self._pysoem
        m = self.master
        setups: dict[int, SlaveSetup] = {}
        for pos, setup in (mapping_override or {}).items():
            if not 0 <= pos < len(self.slaves):
                raise BusError(f"{self.ifname}: a mapping policy is configured for slave {pos}, which is not on the segment")
            if not isinstance(setup, SlaveSetup):
                raise BusError(f"slave {pos}: mapping setup must be a SlaveSetup, got {type(setup).__name__}")
            setups[pos] = setup
        self.setups = setups
        self._dc.use({pos: st.sync0 for pos, st in setups.items() if st.sync0 is not None})
        before_safeop = any(st.sync0_before_safeop for st in setups.values() if st.sync0 is not None)
        if self._dc.sync0:
            # PRE-OP: find the DC slaves, latch and set offsets and delays; from here on every
            # process-data frame carries the FRMW of the reference clock (master.dc_time)
            with self.steps.step(f"{self.ifname}: config_dc (SOEM measures the DC delays)", self.soem_call_s):
                found = m.config_dc()
            if not found:
                raise BusError(f"{self.ifname}: config_dc found no DC slave, although slave(s) "
                               f"{sorted(self._dc.sync0)} report DC in 0x0008")
        no_coe = [f"slave {pos} ({s.name!r}) {problem}" for pos, s in enumerate(self.slaves)
                  if (problem := self._mailboxes[pos].coe_problem())]
        if no_coe:  # its PDO mapping cannot be read: named now, before any transfer is tried
            raise BusError(f"{self.ifname}: " + "; ".join(no_coe))
        m.manual_state_change = before_safeop  # config_map requests SAFE-OP by itself otherwise
        for pos, s in enumerate(self.slaves):
            s.config_func = self._config_func
        try:
            self._config_map_phase(f"{self.ifname}: config_map (SOEM maps the process data)")
            try:
                m.config_map()
            finally:
                self._config_map_phase(None)
        except (BusError, StartupAbandoned):
            raise
        except pysoem.ConfigMapError as e:
            details = "; ".join(str(x) for x in e.error_list)
            raise BusError(f"{self.ifname}: config_map: {details}") from None
        except Exception as e:
            raise BusError(f"{self.ifname}: config_map failed: {e}") from None
        self.codecs = []
        for pos, s in enumerate(self.slaves):
            mp = self._mappings[pos]
            try:
                codec = DriveCodec(mp, dict(self.setups.get(pos, SlaveSetup()).objects))
            except MappingError as e:
                raise BusError(f"slave {pos} ({s.name!r}): {e}") from None
            if len(s.output) != codec.out_size or len(s.input) != codec.in_size:
                raise ProcessDataSizeError(f"slave {pos} ({s.name!r}): process data is {len(s.output)} bytes out / "
                               f"{len(s.input)} in, its PDO mapping says {codec.out_size}/{codec.in_size} "
                               f"({describe(mp)})")
            self.codecs.append(codec)
            log.info("%s: slave %d: %s; absent actual values: %s; other objects: %s", self.ifname, pos,
                     describe(mp), ", ".join(codec.absent_inputs) or "none", ", ".join(codec.extra_names) or "none")
        self.decode_all = segment_decoder(self.codecs, self.inputs, self.slaves, changes=True)
        self._publish()
        if before_safeop:
            self._dc.start_sync0(self.slaves, sorted(self._dc.sync0))
            self._dc.wait_sync0_start()
            m.state = pysoem.SAFEOP_STATE
            m.write_state()
        with self.steps.step(f"{self.ifname}: to SAFE-OP", SAFEOP_DEADLINE_S + 1.0):
            self._wait_state(ALState.SAFEOP, SAFEOP_DEADLINE_S, exchange=False)
        if self._dc.sync0 and not before_safeop:
            self._dc.start_sync0(self.slaves, sorted(self._dc.sync0))
        self.expected_wkc = m.expected_wkc
        # Outputs must flow while OP is requested, or the SM watchdog trips on the way.
        for s, codec in zip(self.slaves, self.codecs):
            s.output = codec.encode(DriveOutputs())
        self._exchange()
        self._dc.wait_sync0_start(self._exchange)
        apply_safeop_sdos(self.slaves, self.setups, self.sdo, self._exchange)
        m.state = pysoem.OP_STATE
        m.write_state()
        with self.steps.step(f"{self.ifname}: to OP", OP_DEADLINE_S + 1.0):
            self._wait_state(ALState.OP, OP_DEADLINE_S, exchange=True)
        with self.steps.step(f"{self.ifname}: reading back SM, FMMU and DC registers", OPEN_S):
            self._read_esc_config()
            self._dc.read_delays(self.slaves)
        log.info("%s: %d slave(s) in OP, expected working counter %d", self.ifname, len(self.slaves),
                 self.expected_wkc)
        return self.expected_wkc

    def _read_esc_config(self) -> None:
        """Read back each slave's SM (0x0800) and FMMU (0x0600) registers as SOEM programmed
        them, so recover() can program a reset slave again without SOEM's reconfig_slave."""
        for pos, s in enumerate(self.slaves):
            try:
                n_fmmu, n_sm = struct.unpack("<BB", s._fprd(REG_FMMU_COUNT, 2, 2000))
                sm = bytes(s._fprd(REG_SM0, 8 * n_sm, 2000)) if n_sm else b""
                fmmu = bytes(s._fprd(REG_FMMU0, 16 * n_fmmu, 2000)) if n_fmmu else b""
            except Exception as e:
                raise BusError(f"slave {pos} ({s.name!r}): reading back its SM/FMMU registers failed: {e}") from None
            self.esc_config[pos] = (sm, fmmu)

    def _wait_state(self, state: ALState, deadline_s: float, exchange: bool) -> None:
        """Until every slave is in ``state`` (requested already), at most ``deadline_s``: the
        request is written again every STATE_REWRITE_S. A slave that refuses sets its error
        indication (AL status bit 4) and stays below until the master acknowledges it, which
        start-up does not: the same refusal seen at two rewrites in a row ends the wait at once.
        Raises BusError naming every slave not there, with its AL status code."""
        m = self.master
        start = time.monotonic()
        deadline = start + deadline_s
        rewrite_at = start + STATE_REWRITE_S
        refused: tuple[int, ...] = ()
        steps = self.steps
        while True:
            steps.check()  # the loop's own deadline is checked below; a stop signal here
            if exchange:
                self._exchange()
            if m.state_check(int(state), STATE_POLL_US) == int(state):
                return
            now = time.monotonic()
            if now >= deadline:
                break
            if now >= rewrite_at:
                m.read_state()
                seen = tuple(pos for pos, s in enumerate(self.slaves)
                             if s.state & STATE_ACK and al_state(s.state) != state)
                if seen and seen == refused:
                    break
                refused = seen
                # An AL control write lost on the wire (SOEM gives up after its retries) must not
                # fail start-up: writing the same request again is idempotent (ETG.1000.6 0x0120).
                rewrite_at = now + STATE_REWRITE_S
                m.state = int(state)
                m.write_state()
        m.read_state()
        bad = []
        for pos, s in enumerate(self.slaves):
            st = s.state
            if al_state(st) != state or st & STATE_ACK:
                code = s.al_status
                bad.append(f"slave {pos} ({s.name!r}) in {al_state(st).wire_name}"
                           + (f" with error: AL status code 0x{code:04X} {al_status_text(code)}" if st & STATE_ACK else ""))
        waited = time.monotonic() - start
        when = f"refused after {waited:.1f} s" if time.monotonic() < deadline else f"not reached within {deadline_s:g} s"
        raise BusError(f"{self.ifname}: {state.wire_name} {when}: " + ("; ".join(bad) or "no slave reports an error"))
