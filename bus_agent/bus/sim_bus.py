"""An in-process simulated EtherCAT segment: N drive models behind the Bus protocol (no root, no NIC).

Each slave is a :class:`bus_agent.sim.drive_model.DriveModel` plus an emulated AL state machine
(ETG.1000.6: INIT 1, PRE-OP 2, SAFE-OP 4, OP 8, error flag 0x10, status code 0x0134), so a
master sees the same behaviour as with ``ecat-sim``:

- working counter per exchange: 3 per slave in OP (LRW read + write), 1 in SAFE-OP (inputs
  only), 0 in PRE-OP/INIT, when unplugged, or with a WKC fault injected;
- outputs are applied only in OP; a slave in OP whose outputs stop arriving longer than the SM
  watchdog (default 100 ms) falls to SAFE-OP + error 0x001B and its drive loses communication;
- leaving OP on request also calls ``communication_lost()`` on drives in Operation enabled;
- an unplugged slave answers nothing; when plugged back it is power-cycled and sits in INIT
  until :meth:`SimBus.recover` reconfigures it.

Time: the models advance by the clock time between exchanges (clock injected, default
``time.monotonic``). Thread-safety: a lock serialises the cycle thread and fault injection
coming from :mod:`bus_agent.sim.control` handlers.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

from bus_agent.bus.base import (
    ALState,
    BusError,
    NoAnswer,
    SlaveALStatus,
    SlaveIdentity,
    SlaveInfo,
    al_status_text,
)
from bus_agent.cia402.states import State
from bus_agent.bus.pdo import DriveInputs, DriveOutputs
from bus_agent.sim.drive_model import PROFILES, DriveModel, DriveProfile, SdoAbort

log = logging.getLogger(__name__)

AL_INVALID_STATE_CHANGE = 0x0011
AL_UNKNOWN_STATE = 0x0012
AL_BOOTSTRAP_NOT_SUPPORTED = 0x0013
AL_SM_WATCHDOG = 0x001B
AL_INVALID_OUTPUT_CONFIG = 0x001D

WKC_PER_SLAVE_OP = 3        # LRW: +1 read, +2 write (ETG.1000.4)
WKC_PER_SLAVE_SAFEOP = 1    # outputs SM disabled in SAFE-OP: only the read counts
DEFAULT_SM_WATCHDOG_S = 0.1  # 0x0400/0x0420: 100 us * 1000

# (current, requested) AL transitions a slave accepts (ETG.1000.6 Table 9 without BOOT).
_AL_ALLOWED = {
    (ALState.INIT, ALState.INIT), (ALState.INIT, ALState.PREOP),
    (ALState.PREOP, ALState.INIT), (ALState.PREOP, ALState.PREOP), (ALState.PREOP, ALState.SAFEOP),
    (ALState.SAFEOP, ALState.INIT), (ALState.SAFEOP, ALState.PREOP), (ALState.SAFEOP, ALState.SAFEOP),
    (ALState.SAFEOP, ALState.OP),
    (ALState.OP, ALState.INIT), (ALState.OP, ALState.PREOP), (ALState.OP, ALState.SAFEOP), (ALState.OP, ALState.OP),
}


class SimSdoError(BusError):
    """An SDO abort from a simulated slave; carries the CoE abort code."""

    def __init__(self, position: int, index: int, subindex: int, abort_code: int, detail: str) -> None:
        self.position = position
        self.index = index
        self.subindex = subindex
        self.abort_code = abort_code
        super().__init__(f"slave {position}: SDO 0x{index:04X}:{subindex} aborted with 0x{abort_code:08X} ({detail})")


@dataclass
class _Slave:
    model: DriveModel
    al_state: ALState = ALState.INIT
    al_error: bool = False
    al_code: int = 0
    configured: bool = False      # SM/FMMU/PDO set up since the last power-on
    plugged: bool = True
    wkc_fault: bool = False
    watchdog_armed: bool = False  # outputs received in OP at least once
    since_outputs_s: float = 0.0
    outputs: DriveOutputs = field(default_factory=DriveOutputs)
    inputs: DriveInputs = field(default_factory=DriveInputs)
    inputs_al: ALState | None = None  # the AL state in which ``inputs`` were last taken (None: not since)
    outputs_set: bool = False     # set_outputs since the outputs were last applied


def _resolve_profiles(profile: str | DriveProfile | Sequence[str | DriveProfile], n: int) -> list[DriveProfile]:
    items = [profile] * n if isinstance(profile, (str, DriveProfile)) else list(profile)
    if len(items) != n:
        raise ValueError(f"{len(items)} profiles given for {n} drives")
    out = []
    for p in items:
        if isinstance(p, str):
            if p not in PROFILES:
                raise ValueError(f"unknown drive profile {p!r}; known: {', '.join(sorted(PROFILES))}")
            p = PROFILES[p]
        out.append(p)
    return out


class SimBus:
    """The Bus protocol over N in-process drive models (backend "sim")."""

    backend = "sim"
    express_exchange = True
    #: Skip the step of a steady drive model (see exchange); False: step every model (tests compare).
    skip_steady = True

    def __init__(self, n_drives: int, profile: str | DriveProfile | Sequence[str | DriveProfile] = "generic",
                 segment_name: str = "sim", clock: Callable[[], float] = time.monotonic,
                 sm_watchdog_s: float | None = DEFAULT_SM_WATCHDOG_S) -> None:
        if not isinstance(n_drives, int) or n_drives < 1:
            raise ValueError(f"n_drives must be a positive integer, got {n_drives!r}")
        self.segment_name = segment_name
        self.profiles = _resolve_profiles(profile, n_drives)
        self._clock = clock
        self._sm_watchdog_s = sm_watchdog_s
        self._lock = threading.Lock()
        self._slaves = [_Slave(DriveModel(p, serial=i + 1)) for i, p in enumerate(self.profiles)]
        self._opened = False
        self._started = False
        self._last_t: float | None = None
        self._changed: list[int] = []

    # ------------------------------------------------------------------ helpers

    @property
    def n_drives(self) -> int:
        return len(self._slaves)

    def _slave(self, position: int) -> _Slave:
        if not isinstance(position, int) or not 0 <= position < len(self._slaves):
            raise BusError(f"segment {self.segment_name}: no slave at position {position!r} "
                           f"(0..{len(self._slaves) - 1})")
        return self._slaves[position]

    def model(self, position: int) -> DriveModel:
        """The drive model at ``position`` (tests and simulators; not for the cycle)."""
        return self._slave(position).model

    def _set_al(self, position: int, sl: _Slave, state: ALState) -> None:
        if sl.al_state is ALState.OP and state is not ALState.OP:
            if sl.model.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
                log.warning("segment %s slave %d: left OP while the drive is %s: communication lost",
                            self.segment_name, position, sl.model.state.value)
            sl.model.communication_lost()
        if state is not ALState.OP:
            sl.watchdog_armed = False
        sl.al_state = state
        # PDO assignment/mapping writable only in PRE-OP (and INIT)
        sl.model.set_pdo_config_locked(state in (ALState.SAFEOP, ALState.OP))

    def _al_error(self, position: int, sl: _Slave, state: ALState, code: int) -> None:
        log.warning("segment %s slave %d: AL error 0x%04X (%s) in %s", self.segment_name, position,
                    code, al_status_text(code), state.wire_name)
        self._set_al(position, sl, state)
        sl.al_error = True
        sl.al_code = code

    def _request(self, position: int, sl: _Slave, state: ALState) -> None:
        """AL control write (0x0120) for one slave; the ack is implied (clears the error flag)."""
        if not sl.plugged:
            return  # nobody there to receive it
        current = sl.al_state
        if state not in (ALState.INIT, ALState.PREOP, ALState.SAFEOP, ALState.OP, ALState.BOOT):
            self._al_error(position, sl, current, AL_UNKNOWN_STATE)
            return
        if state is ALState.BOOT:
            self._al_error(position, sl, current, AL_BOOTSTRAP_NOT_SUPPORTED)
            return
        if (current, state) not in _AL_ALLOWED:
            self._al_error(position, sl, current, AL_INVALID_STATE_CHANGE)
            return
        if state in (ALState.SAFEOP, ALState.OP) and not sl.configured:
            self._al_error(position, sl, current, AL_INVALID_OUTPUT_CONFIG)
            return
        sl.al_error = False
        sl.al_code = 0
        self._set_al(position, sl, state)

    # ------------------------------------------------------------------ Bus protocol

    def open(self) -> list[SlaveInfo]:
        """Identify the slaves (0x1018 from each profile) and bring them INIT -> PRE-OP."""
        with self._lock:
            infos = []
            for pos, sl in enumerate(self._slaves):
                if not sl.plugged:
                    raise BusError(f"segment {self.segment_name}: slave {pos} does not answer (unplugged)")
                p = sl.model.profile
                infos.append(SlaveInfo(pos, p.device_name,
                                       SlaveIdentity(p.vendor_id, p.product_code, p.revision, sl.model.serial)))
                self._request(pos, sl, ALState.INIT)
                self._request(pos, sl, ALState.PREOP)
            self._opened = True
            log.info("segment %s: %d simulated slaves found", self.segment_name, len(infos))
            return infos

    def start(self, mapping_override: Mapping[int, object] | None = None) -> int:
        """Configure the default PDO mapping and bring every slave SAFE-OP -> OP.
        Returns the expected working counter (3 per slave). Raises BusError."""
        with self._lock:
            if not self._opened:
                raise BusError(f"segment {self.segment_name}: start() before open()")
        for pos, setup in (mapping_override or {}).items():
            self._apply_setup(pos, setup)
        with self._lock:
            for pos, sl in enumerate(self._slaves):
                if not sl.plugged:
                    raise BusError(f"segment {self.segment_name}: slave {pos} does not answer (unplugged)")
                sl.configured = True
                for state in (ALState.SAFEOP, ALState.OP):
                    self._request(pos, sl, state)
                    if sl.al_error or sl.al_state is not state:
                        raise BusError(f"segment {self.segment_name}: slave {pos} refused {state.wire_name}: "
                                       f"AL status code 0x{sl.al_code:04X} ({al_status_text(sl.al_code)})")
            self._started = True
            self._last_t = self._clock()
            return self.expected_wkc

    @property
    def expected_wkc(self) -> int:
        return WKC_PER_SLAVE_OP * len(self._slaves)

    def exchange(self) -> int:
        """One process-data cycle: the models advance by the time since the last exchange,
        then take the outputs (OP only) and give their inputs (SAFE-OP and OP). Cycle-safe."""
        with self._lock:
            now = self._clock()
            dt = 0.0 if self._last_t is None else max(0.0, now - self._last_t)
            self._last_t = now
            self._changed = []
            wkc = 0
            skip_steady = self.skip_steady
            for pos, sl in enumerate(self._slaves):
                if not sl.plugged:
                    continue  # no power, no time: the model is power-cycled when plugged back
                model = sl.model
                # A steady model (DriveModel.steady: the step would change nothing) whose inputs
                # were taken in this AL state: no step, no new inputs (the outputs still go in:
                # a change there is seen by the next exchange's steady()). The idle demo's cost.
                rest = skip_steady and sl.inputs_al is sl.al_state and model.steady()
                if not rest:
                    model.step(dt)
                if sl.al_state is ALState.OP and sl.watchdog_armed:
                    sl.since_outputs_s += dt
                    if self._sm_watchdog_s is not None and sl.since_outputs_s > self._sm_watchdog_s:
                        self._al_error(pos, sl, ALState.SAFEOP, AL_SM_WATCHDOG)
                if sl.wkc_fault:
                    sl.inputs_al = None
                    continue  # datagram lost for this slave: nothing read, nothing written
                if sl.al_state is ALState.OP:
                    if not rest or sl.outputs_set:  # steady: the last apply changed nothing, nor would this
                        model.apply_outputs(sl.outputs)
                        sl.outputs_set = False
                    sl.watchdog_armed = True
                    sl.since_outputs_s = 0.0
                    wkc += WKC_PER_SLAVE_OP
                    if not rest:
                        self._take_inputs(pos, sl)
                elif sl.al_state is ALState.SAFEOP:
                    wkc += WKC_PER_SLAVE_SAFEOP
                    if not rest:
                        self._take_inputs(pos, sl)
                else:
                    sl.inputs_al = None
            return wkc

    def _take_inputs(self, pos: int, sl: _Slave) -> None:
        sl.inputs_al = sl.al_state
        new = sl.model.inputs()
        if new != sl.inputs:  # equal inputs keep their record (and the cycle its work for it)
            sl.inputs = new
            self._changed.append(pos)

    def inputs_changed(self) -> list[int]:
        """Positions of the slaves whose inputs changed at the last :meth:`exchange`. Optional
        hook of the Bus protocol. Cycle-safe."""
        return self._changed

    def inputs(self, position: int) -> DriveInputs:
        """Last received TxPDO of the slave (stale when it stopped answering). Cycle-safe."""
        return self._slave(position).inputs

    def set_outputs(self, position: int, outputs: DriveOutputs) -> None:
        """RxPDO for the next exchange (change a record only through this call: a steady drive's
        unchanged outputs are not applied again). Cycle-safe."""
        sl = self._slave(position)
        sl.outputs = outputs
        sl.outputs_set = True

    def read_al_status(self) -> list[SlaveALStatus]:
        """AL status (0x0130/0x0134) of every slave; an unplugged slave reads as NONE."""
        with self._lock:
            return [SlaveALStatus(sl.al_state, sl.al_error, sl.al_code) if sl.plugged
                    else SlaveALStatus(ALState.NONE, False, 0) for sl in self._slaves]

    def request_al_state(self, position: int | None, state: ALState) -> None:
        """Write AL control for one slave or all (None) with the error ack; does not wait.
        Leaving OP makes drives in Operation enabled lose communication (fault reaction)."""
        with self._lock:
            positions = range(len(self._slaves)) if position is None else [position]
            for pos in positions:
                self._request(pos, self._slave(pos), ALState(state))

    def recover(self, position: int) -> bool:
        """Bring a lost or fallen slave back to OP: reconfigure it if it was power-cycled, ack
        an error, step INIT/PRE-OP/SAFE-OP/OP. True when it is in OP."""
        with self._lock:
            sl = self._slave(position)
            if not sl.plugged:
                return False
            if not sl.configured:  # power-cycled: station address, SMs, FMMUs, PDO mapping again
                self._request(position, sl, ALState.INIT)
                sl.configured = True
            for state in (ALState.PREOP, ALState.SAFEOP, ALState.OP):
                if sl.al_state.value < state.value or (sl.al_error and sl.al_state is state):
                    self._request(position, sl, state)
                    if sl.al_error:
                        break
            ok = sl.al_state is ALState.OP and not sl.al_error
            log.info("segment %s slave %d: recover -> %s", self.segment_name, position,
                     "OP" if ok else sl.al_state.wire_name)
            return ok

    def _apply_setup(self, position: int, setup: object) -> None:
        """What a real segment does in PRE-OP, as far as simulated drives can honour it: their
        mapping is the project's default layout, so policies ``drive`` and ``default`` both mean
        it; start-up SDOs are written through the model. Anything else is refused by name."""
        policy = getattr(getattr(setup, "policy", None), "policy", "drive")
        if policy not in ("drive", "default"):
            raise BusError(f"segment {self.segment_name}: slave {position}: mapping policy {policy!r} is not "
                           "supported by the sim bus (its drives have the default layout: use policy "
                           "'drive' or 'default', or ecat-sim for other layouts)")
        if getattr(setup, "sync0", None) is not None:
            raise BusError(f"segment {self.segment_name}: slave {position}: the sim bus has no distributed "
                           "clocks: set dc = \"off\" (or use ecat-sim)")
        for sdo in getattr(setup, "sdos", ()):
            try:
                self.sdo_write(position, sdo.index, sdo.subindex, sdo.data)
            except SimSdoError as e:
                raise BusError(f"segment {self.segment_name}: slave {position}: start-up SDO {sdo}: {e}") from None

    def sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        """CoE SDO upload through the model (PRE-OP, SAFE-OP or OP). Raises BusError/SimSdoError."""
        with self._lock:
            sl = self._mailbox_slave(position, "read", index, subindex)
            try:
                data = sl.model.read_bytes(index, subindex)
            except SdoAbort as e:
                raise SimSdoError(position, index, subindex, e.code, str(e)) from None
            if size and len(data) > size:
                raise BusError(f"slave {position}: SDO 0x{index:04X}:{subindex} is {len(data)} bytes, "
                               f"buffer is {size}")
            return data

    def sdo_write(self, position: int, index: int, subindex: int, data: bytes) -> None:
        """CoE SDO download through the model. Raises BusError/SimSdoError (nothing changes)."""
        with self._lock:
            sl = self._mailbox_slave(position, "write", index, subindex)
            try:
                sl.model.write_bytes(index, subindex, bytes(data))
            except SdoAbort as e:
                raise SimSdoError(position, index, subindex, e.code, str(e)) from None

    def _mailbox_slave(self, position: int, what: str, index: int, subindex: int) -> _Slave:
        sl = self._slave(position)
        if not sl.plugged:
            raise NoAnswer(f"slave {position}: SDO {what} 0x{index:04X}:{subindex}: no answer (unplugged)")
        if sl.al_state in (ALState.INIT, ALState.NONE):  # as over EtherCAT: no mailbox, no answer
            raise NoAnswer(f"slave {position}: SDO {what} 0x{index:04X}:{subindex}: mailbox not available in INIT")
        return sl

    def close(self) -> None:
        """All slaves to INIT (drives in Operation enabled lose communication). Idempotent."""
        with self._lock:
            for pos, sl in enumerate(self._slaves):
                if sl.plugged and sl.al_state is not ALState.INIT:
                    self._request(pos, sl, ALState.INIT)
            self._started = False
            self._opened = False

    # ------------------------------------------------------------------ fault injection

    def inject_fault(self, position: int, error_code: int) -> None:
        """Make the drive at ``position`` detect a fault (transition 13). Raises ValueError."""
        with self._lock:
            self._slave(position).model.inject_fault(error_code)

    def unplug(self, position: int) -> None:
        """The slave stops answering (cable pulled / power lost): WKC contribution 0."""
        with self._lock:
            sl = self._slave(position)
            if sl.plugged:
                log.warning("segment %s slave %d: unplugged", self.segment_name, position)
            sl.plugged = False

    def plug(self, position: int) -> None:
        """The slave answers again, freshly powered: drive power-cycled, AL INIT, unconfigured."""
        with self._lock:
            sl = self._slave(position)
            if sl.plugged:
                return
            log.warning("segment %s slave %d: plugged back (power-cycled, INIT)", self.segment_name, position)
            sl.plugged = True
            sl.model.power_cycle()
            sl.al_state = ALState.INIT
            sl.al_error = False
            sl.al_code = 0
            sl.configured = False
            sl.watchdog_armed = False
            sl.model.set_pdo_config_locked(False)

    def set_wkc_fault(self, position: int, on: bool) -> None:
        """While on, the slave's process data is lost: it adds 0 to the working counter, its
        outputs are not applied (the SM watchdog runs) and its inputs are not updated."""
        with self._lock:
            self._slave(position).wkc_fault = bool(on)

    def control_handlers(self) -> dict[str, Callable[[int, dict], str]]:
        """Handlers for :class:`bus_agent.sim.control.SimControl`: fault {error_code},
        unplug, plug, wkc_fault {on}."""

        def fault(position: int, args: dict) -> str:
            code = _int_arg(args, "error_code")
            self.inject_fault(position, code)
            return f"slave {position}: fault 0x{code:04X} injected"

        def unplug(position: int, args: dict) -> str:
            _no_args(args)
            self.unplug(position)
            return f"slave {position}: unplugged"

        def plug(position: int, args: dict) -> str:
            _no_args(args)
            self.plug(position)
            return f"slave {position}: plugged"

        def wkc_fault(position: int, args: dict) -> str:
            on = args.get("on")
            if not isinstance(on, bool) or set(args) != {"on"}:
                raise ValueError("wkc_fault takes exactly {'on': bool}")
            self.set_wkc_fault(position, on)
            return f"slave {position}: wkc fault {'on' if on else 'off'}"

        return {"fault": fault, "unplug": unplug, "plug": plug, "wkc_fault": wkc_fault}


def _int_arg(args: dict, name: str) -> int:
    value = args.get(name)
    if set(args) != {name} or not isinstance(value, int) or isinstance(value, bool):
        raise ValueError(f"takes exactly {{'{name}': int}}, got {args!r}")
    return value


def _no_args(args: dict) -> None:
    if args:
        raise ValueError(f"takes no arguments, got {args!r}")
