"""A simulated CiA 402 servo drive: the device side, pure (no clock, no I/O, no threads).

Shared by every simulator (the in-process :class:`bus_agent.bus.sim_bus.SimBus` and the
``ecat-sim`` virtual EtherCAT segment). Time advances only through :meth:`DriveModel.step`.

What it models (IEC 61800-7-201 / CiA 402, CiA 301):

- the drive state machine, all eight states and transitions 0..16, driven by the controlword
  (0x6040) decoded from bits 7,3,2,1,0; the fault reset (transition 15) on the rising edge of
  bit 7 across steps;
- quick stop option code 0x605A (0 coast, 1..4 ramp then Switch on disabled by transition 12,
  5..8 ramp and stay in Quick stop active, transition 16 back on Enable operation);
- the fault reaction (0x605E) in Fault reaction active, then Fault (transition 14); 0x603F error
  code, 0x1001 error register and an EMCY record on fault, an EMCY with code 0 on reset;
- modes PP 1 (:mod:`bus_agent.sim.profile_model`), PV 3, PT 4, homing 6
  (:mod:`bus_agent.sim.homing_model`: 0x6098/0x6099/0x609A/0x607C, a home switch on 0x60FD
  bit 2), CSP 8, CSV 9, CST 10 with the 0x6061 echo; halt (controlword bit 8);
  simple kinematics (position integrates velocity); CSP following error (0x8611, window 0x6065);
- an object dictionary as a constant table of :class:`ObjectEntry`, values per instance, SDO
  access with CoE abort codes (:class:`SdoAbort`).

Units: position in increments, velocity in increments/s, accelerations in increments/s^2,
torque in per mille of rated torque.
"""

from __future__ import annotations

import logging
import math
import operator
import struct
from typing import Mapping

from bus_agent.cia402.states import (
    CONTROLWORD_FAULT_RESET_BIT,
    CONTROLWORD_HALT,
    Controlword,
    STATUSWORD_OF_STATE,
    Mode,
    State,
    StatuswordBit,
)
from bus_agent.bus.pdo import RXPDO_INDEX, TXPDO_INDEX, DriveInputs, DriveOutputs
from bus_agent.sim.drive_profiles import PROFILES, DriveProfile, Emcy, decode_command
from bus_agent.sim.homing_model import HOME_SWITCH_BIT, HOMING_BITS_MASK, SimHoming
from bus_agent.sim.profile_model import SimProfilePosition, ramp
# The object dictionary, abort and error codes live in bus_agent.sim.objects; re-exported here
# for the simulators and tests that import them from the drive model.
from bus_agent.sim.objects import (
    _INDEXES, _INT_FORMATS, _INT_RANGES, _PDO_CONFIG_INDEXES, ABORT_DEVICE_STATE, ABORT_LENGTH_MISMATCH,
    ABORT_NO_OBJECT, ABORT_NO_SUBINDEX, ABORT_NOT_MAPPABLE, ABORT_READ_ONLY, ABORT_VALUE_RANGE,
    ABORT_WRITE_ONLY, ERROR_COMMUNICATION_LOST, ERROR_FOLLOWING_ERROR, ERROR_GENERIC, OBJECT_TABLE, OBJECTS,
    SDO_ABORT_TEXT, ObjectEntry, SdoAbort, _e, error_register_for,
)

__all__ = ["ABORT_DEVICE_STATE", "ABORT_LENGTH_MISMATCH", "ABORT_NO_OBJECT", "ABORT_NO_SUBINDEX", "ABORT_NOT_MAPPABLE",
           "ABORT_READ_ONLY", "ABORT_VALUE_RANGE", "ABORT_WRITE_ONLY", "ERROR_COMMUNICATION_LOST", "ERROR_FOLLOWING_ERROR",
           "ERROR_GENERIC", "OBJECT_TABLE", "OBJECTS", "SDO_ABORT_TEXT", "ObjectEntry", "SdoAbort", "_e", "_INT_FORMATS",
           "error_register_for", "Emcy", "DriveProfile", "PROFILES", "DriveModel", "decode_command"]

log = logging.getLogger(__name__)


_POWERED = frozenset({State.SWITCHED_ON, State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE})
#: States in which a step with an unchanged controlword changes nothing: no torque (the rest path
#: of ``_motion``), no automatic transition, no timer (see :meth:`DriveModel.steady`).
_STEADY = frozenset({State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.FAULT})
_POSITION_WINDOW = 10  # increments: target reached (statusword bit 10) in position modes
_VELOCITY_WINDOW = 10  # increments/s: target reached in velocity modes


class DriveModel:
    """One CiA 402 drive (device side). Pure and single-threaded: the caller serialises access.

    Controlword writes (SDO or :meth:`apply_outputs`) are evaluated at the next :meth:`step`.
    """

    #: The short path of a step in a state without torque (see ``_motion``); False: the general
    #: path (tests compare both).
    rest_fast_path = True

    objects: Mapping[tuple[int, int], ObjectEntry] = OBJECTS

    def __init__(self, profile: DriveProfile = PROFILES["generic"], serial: int = 0,
                 dictionary: Mapping[tuple[int, int], ObjectEntry] | None = None,
                 hidden: Mapping[tuple[int, int], int] | None = None) -> None:
        """``dictionary``: the object dictionary served by SDO (default: :data:`OBJECTS`), e.g.
        from a device's ESI; its defaults replace the model's. The model keeps its own objects
        either way (those the dictionary lacks are internal: SDO abort 0x06020000). ``hidden``:
        further internal values (PDO entries of objects the dictionary lacks) -> power-on value."""
        if isinstance(profile, str):  # tolerated convenience
            profile = PROFILES[profile]
        self.profile = profile
        if dictionary is not None:
            self.objects = dictionary
        self._indexes = _INDEXES if dictionary is None else frozenset(i for i, _s in dictionary)
        self._power_on_values = {**{k: e.default for k, e in OBJECTS.items()}, **(hidden or {}),
                                 **({} if dictionary is None else {k: e.default for k, e in dictionary.items()})}
        self.serial = serial
        self.pdo_config_locked = False
        self._emcy: list[Emcy] = []
        #: Counts every change from outside a step (object writes, outputs that differ, faults,
        #: power cycles); :meth:`steady` compares it with its value at the last step.
        self._mutations = 0
        self._steady_mark = -1
        self._steady_home: int | None = None
        self._reset_power_on()

    # ---------------------------------------------------------------- lifecycle

    def _reset_power_on(self) -> None:
        p = self.profile
        self._values: dict[tuple[int, int], int | str | bytes] = dict(self._power_on_values)
        self._values[(0x1008, 0)] = p.device_name
        self._values[(0x1018, 1)] = p.vendor_id
        self._values[(0x1018, 2)] = p.product_code
        self._values[(0x1018, 3)] = p.revision
        self._values[(0x1018, 4)] = self.serial & 0xFFFFFFFF
        if (0x6502, 0) not in self.objects or self.objects is OBJECTS:
            self._values[(0x6502, 0)] = p.supported_modes  # else the device file's value (some give 0)
        self._values[(0x6060, 0)] = self._values[(0x6061, 0)] = p.power_on_mode
        # 0x60FD: manufacturer bits 16..31 carry the serial, so each drive's inputs differ
        self._values[(0x60FD, 0)] = (self.serial & 0xFFFF) << 16
        self._state = State.NOT_READY_TO_SWITCH_ON       # transition 0
        self._steps_in_state = 0
        self._prev_fault_reset_bit = False
        self._position = float(p.power_on_position * self.serial)
        self._values[(0x6064, 0)] = int(self._position)
        self._velocity = 0.0
        self._torque = 0.0
        self._mode_pending: int | None = None
        self._mode_delay = 0
        self._pp = SimProfilePosition()  # mode 1: the set-point handshake and its target
        #: test knobs of the PP handshake: steps before a set-point is acknowledged, and an
        #: acknowledge that never falls (a drive bug the master must survive)
        self.pp_ack_delay_steps = 0
        self.pp_ack_stuck = False
        self._following_error = False
        self._target_reached = False
        self._homing = SimHoming()
        self._prev_home_start = False
        self.home_switch_position = p.home_switch_position
        self._update_statusword()

    def power_cycle(self) -> None:
        """Power off and on: every value back to its default, state Not ready (transition 0)."""
        log.info("drive model serial=%d: power cycle", self.serial)
        self._emcy.clear()
        self._mutations += 1
        self._reset_power_on()

    @property
    def state(self) -> State:
        return self._state

    @property
    def statusword(self) -> int:
        return int(self._values[(0x6041, 0)])

    @property
    def error_code(self) -> int:
        return int(self._values[(0x603F, 0)])

    @property
    def position(self) -> float:
        return self._position

    @property
    def velocity(self) -> float:
        return self._velocity

    # ---------------------------------------------------------------- object access (SDO)

    def _entry(self, index: int, subindex: int) -> ObjectEntry:
        entry = self.objects.get((index, subindex))
        if entry is None:
            if index in self._indexes:
                raise SdoAbort(ABORT_NO_SUBINDEX, f"0x{index:04X} has no subindex {subindex}")
            raise SdoAbort(ABORT_NO_OBJECT, f"no object 0x{index:04X}")
        return entry

    def value(self, index: int, subindex: int) -> int | str | bytes:
        """The model's current value of an object, whether or not its dictionary serves it."""
        return self._values[(index, subindex)]

    def read(self, index: int, subindex: int) -> int | str | bytes:
        """SDO upload of one entry (value as int, str for "str" and bytes for "bytes" entries).
        Raises SdoAbort."""
        entry = self._entry(index, subindex)
        if entry.access == "wo":
            raise SdoAbort(ABORT_WRITE_ONLY, f"0x{index:04X}:{subindex} is write only")
        return self._values[(index, subindex)]

    def write(self, index: int, subindex: int, value: int) -> None:
        """SDO download of one entry. Raises SdoAbort (unknown, read only, range, state);
        a refused write changes nothing."""
        entry = self._entry(index, subindex)
        if entry.access == "ro":
            raise SdoAbort(ABORT_READ_ONLY, f"0x{index:04X}:{subindex} ({entry.name}) is read only")
        if entry.datatype in ("str", "bytes") or not isinstance(value, int) or isinstance(value, bool):
            raise SdoAbort(ABORT_LENGTH_MISMATCH, f"0x{index:04X}:{subindex} takes an integer")
        lo, hi = entry.value_range()
        if not lo <= value <= hi:
            raise SdoAbort(ABORT_VALUE_RANGE, f"0x{index:04X}:{subindex} ({entry.name}) = {value} outside {lo}..{hi}")
        if index in _PDO_CONFIG_INDEXES:
            self._check_pdo_config_write(entry, value)
        if (index, subindex) == (0x6060, 0):
            if not self._mode_supported(value):
                raise SdoAbort(ABORT_VALUE_RANGE, f"mode {value} not in 0x6502=0x{self.profile.supported_modes:08X}")
            self._request_mode(value)
        self._values[(index, subindex)] = value
        self._mutations += 1

    def _check_pdo_config_write(self, entry: ObjectEntry, value: int) -> None:
        if self.pdo_config_locked:
            raise SdoAbort(ABORT_DEVICE_STATE, f"0x{entry.index:04X} writable only in PRE-OP")
        if entry.index in (RXPDO_INDEX, TXPDO_INDEX) and entry.subindex > 0 and value != 0:
            mapped = OBJECTS.get((value >> 16, (value >> 8) & 0xFF))
            # RxPDOs carry writable objects only, TxPDOs readable ones
            wrong_way = mapped is not None and (
                mapped.access == "ro" if entry.index == RXPDO_INDEX else mapped.access == "wo")
            if mapped is None or not mapped.pdo_mappable or mapped.bits != value & 0xFF or wrong_way:
                raise SdoAbort(ABORT_NOT_MAPPABLE, f"0x{value:08X} cannot be mapped")

    def read_bytes(self, index: int, subindex: int) -> bytes:
        """SDO upload as little-endian bytes of the entry's size (UTF-8 for strings)."""
        entry = self._entry(index, subindex)
        value = self.read(index, subindex)
        if entry.datatype == "str":
            return str(value).encode()
        if isinstance(value, bytes):  # a "bytes" entry
            return value
        return struct.pack(_INT_FORMATS[entry.datatype], int(value))

    def write_bytes(self, index: int, subindex: int, data: bytes) -> None:
        """SDO download from little-endian bytes; the length must be the entry's (0x06070010)."""
        entry = self._entry(index, subindex)
        if entry.access == "ro":
            raise SdoAbort(ABORT_READ_ONLY, f"0x{index:04X}:{subindex} ({entry.name}) is read only")
        if entry.datatype == "str" or len(data) != entry.size:
            raise SdoAbort(ABORT_LENGTH_MISMATCH,
                           f"0x{index:04X}:{subindex} takes {entry.size} bytes, got {len(data)}")
        if entry.datatype == "bytes":
            self._values[(index, subindex)] = bytes(data)
            self._mutations += 1
            return
        (value,) = struct.unpack(_INT_FORMATS[entry.datatype], bytes(data))
        self.write(index, subindex, value)

    def write_mapped(self, index: int, subindex: int, value: int) -> None:
        """An RxPDO value other than the model's own outputs: as :meth:`write` for an object of
        the dictionary; one the dictionary lacks (an ESI maps it anyway) is stored as it is."""
        if (index, subindex) in self.objects:
            self.write(index, subindex, value)
        elif self._values.get((index, subindex)) != value:
            self._values[(index, subindex)] = value
            self._mutations += 1

    def set_pdo_config_locked(self, locked: bool) -> None:
        """Lock 0x1C12/0x1C13/0x1600/0x1A00 against writes (SAFE-OP and OP: abort 0x08000022)."""
        self.pdo_config_locked = locked

    # ---------------------------------------------------------------- process data

    def apply_outputs(self, outputs: DriveOutputs) -> None:
        """RxPDO: 0x6040, 0x607A, 0x60FF, 0x6071, 0x6060. A mode outside 0x6502 is ignored
        (0x6061 keeps the old value); the controlword is evaluated at the next step."""
        v = self._values
        new = (outputs.controlword & 0xFFFF, _clamp_int(outputs.target_position, "i32"),
               _clamp_int(outputs.target_velocity, "i32"), _clamp_int(outputs.target_torque, "i16"))
        if new != (v[(0x6040, 0)], v[(0x607A, 0)], v[(0x60FF, 0)], v[(0x6071, 0)]):
            v[(0x6040, 0)], v[(0x607A, 0)], v[(0x60FF, 0)], v[(0x6071, 0)] = new
            self._mutations += 1
        mode = outputs.modes_of_operation
        if mode != v[(0x6060, 0)]:
            if self._mode_supported(mode):
                v[(0x6060, 0)] = mode
                self._request_mode(mode)
                self._mutations += 1
            elif mode != 0:
                log.debug("drive model serial=%d: PDO mode %d not supported, ignored", self.serial, mode)

    def reader(self, keys: list[tuple[int, int]]):
        """A function returning the current values of the entries ``keys`` (a TxPDO layout) as a
        tuple, in order: one itemgetter over the object values, so a mapped layout costs the ESC
        no per-object Python work per step. The entries are readable, integer objects (the PDO
        configuration only maps those)."""
        get = operator.itemgetter(*keys)
        values = self._values
        if len(keys) == 1:
            return lambda: (get(values),)
        return lambda: get(values)

    def inputs(self) -> DriveInputs:
        """TxPDO: 0x6041, 0x6064, 0x606C, 0x6077, 0x6061, 0x603F."""
        v = self._values
        return DriveInputs(
            statusword=int(v[(0x6041, 0)]), position_actual=int(v[(0x6064, 0)]),
            velocity_actual=int(v[(0x606C, 0)]), torque_actual=int(v[(0x6077, 0)]),
            modes_of_operation_display=int(v[(0x6061, 0)]), error_code=int(v[(0x603F, 0)]),
        )

    # ---------------------------------------------------------------- modes

    def _mode_supported(self, mode: int) -> bool:
        try:
            m = Mode(mode)
        except ValueError:
            return False
        return bool(self.profile.supported_modes >> m.supported_bit & 1)

    def _request_mode(self, mode: int) -> None:
        if mode == self._values[(0x6061, 0)]:
            self._mode_pending = None
            return
        self._mode_pending = mode
        self._mode_delay = self.profile.mode_echo_delay_steps

    # ---------------------------------------------------------------- faults and emergencies

    def inject_fault(self, error_code: int) -> None:
        """A fault detected now (transition 13 from any state): 0x603F, 0x1001, an EMCY,
        then the fault reaction (0x605E) in Fault reaction active and Fault (transition 14)."""
        if not isinstance(error_code, int) or not 0 < error_code <= 0xFFFF:
            raise ValueError(f"error code must be 1..0xFFFF, got {error_code!r}")
        reg = error_register_for(error_code)
        self._mutations += 1
        self._values[(0x603F, 0)] = error_code
        self._values[(0x1001, 0)] = reg
        self._emcy.append(Emcy(error_code, reg))
        if self._state not in (State.FAULT_REACTION_ACTIVE, State.FAULT):
            log.warning("drive model serial=%d: fault 0x%04X in %s (transition 13)",
                        self.serial, error_code, self._state.value)
            self._enter(State.FAULT_REACTION_ACTIVE)
        self._update_statusword()

    def communication_lost(self) -> None:
        """Outputs stopped (SM watchdog, AL left OP): a drive in Operation enabled or Quick stop
        active performs a fault reaction with 0x8130 (CiA 301 heartbeat/life guard error).
        In the other states it holds no torque and nothing changes."""
        if self._state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            self.inject_fault(ERROR_COMMUNICATION_LOST)

    def take_emcy(self) -> list[Emcy]:
        """EMCY records produced since the last call (oldest first)."""
        out, self._emcy = self._emcy, []
        return out

    # ---------------------------------------------------------------- the step

    def _enter(self, state: State) -> None:
        self._state = state
        self._steps_in_state = 0
        if state is State.OPERATION_ENABLED:
            self._pp.target = None
        else:
            self._homing.interrupt()

    def step(self, dt_s: float) -> None:
        """Advance the drive by ``dt_s`` seconds: controlword commands, automatic transitions,
        fault reaction, mode echo and motion. Never raises on any controlword."""
        if not dt_s >= 0.0 or math.isinf(dt_s):
            raise ValueError(f"dt_s must be a finite number >= 0, got {dt_s!r}")
        cw = int(self._values[(0x6040, 0)])
        reset_bit = bool(cw & CONTROLWORD_FAULT_RESET_BIT)
        reset_edge = reset_bit and not self._prev_fault_reset_bit
        self._prev_fault_reset_bit = reset_bit
        self._steps_in_state += 1
        before = self._state
        self._transition(cw, reset_edge)
        if self._mode_pending is not None:
            if self._mode_delay <= 0:
                self._values[(0x6061, 0)] = self._mode_pending
                self._mode_pending = None
            else:
                self._mode_delay -= 1
        self._motion(cw, dt_s)
        self._update_statusword()
        steady = before is self._state and self._state in _STEADY and self._mode_pending is None and self.rest_fast_path
        self._steady_mark = self._mutations if steady else -1
        self._steady_home = self.home_switch_position

    def steady(self) -> bool:
        """True when the next :meth:`step` would change nothing (the caller may skip it): the last
        step ended in a state without torque, timer or automatic transition (``_STEADY``) that it
        did not change, no mode change is pending, and nothing changed the drive since (no object
        write, no different outputs, no fault, no power cycle, the same home switch). A step
        there only counts ``_steps_in_state``, which those states do not read."""
        return self._steady_mark == self._mutations and self._steady_home == self.home_switch_position

    def _transition(self, cw: int, reset_edge: bool) -> None:
        s = self._state
        cmd = decode_command(cw)
        S = State
        if s is S.NOT_READY_TO_SWITCH_ON:
            if self.profile.not_ready_on_power_up:
                if cmd == Controlword.SHUTDOWN:       # indy7: accepts Shutdown here (seed 004)
                    self._enter(S.READY_TO_SWITCH_ON)
            elif self._steps_in_state >= self.profile.self_test_steps:
                self._enter(S.SWITCH_ON_DISABLED)     # transition 1
        elif s is S.SWITCH_ON_DISABLED:
            if cmd == Controlword.SHUTDOWN:
                self._enter(S.READY_TO_SWITCH_ON)     # 2
        elif s is S.READY_TO_SWITCH_ON:
            if cmd in (Controlword.SWITCH_ON, Controlword.ENABLE_OPERATION):
                self._enter(S.SWITCHED_ON)            # 3 (Enable operation: 3 now, 4 next step)
            elif cmd in (Controlword.DISABLE_VOLTAGE, Controlword.QUICK_STOP):
                self._enter(S.SWITCH_ON_DISABLED)     # 7
        elif s is S.SWITCHED_ON:
            if cmd == Controlword.ENABLE_OPERATION:
                self._enter(S.OPERATION_ENABLED)      # 4
            elif cmd == Controlword.SHUTDOWN:
                self._enter(S.READY_TO_SWITCH_ON)     # 6
            elif cmd in (Controlword.DISABLE_VOLTAGE, Controlword.QUICK_STOP):
                self._enter(S.SWITCH_ON_DISABLED)     # 10
        elif s is S.OPERATION_ENABLED:
            if cmd == Controlword.SWITCH_ON:
                self._enter(S.SWITCHED_ON)            # 5 (disable operation)
            elif cmd == Controlword.SHUTDOWN:
                self._enter(S.READY_TO_SWITCH_ON)     # 8
            elif cmd == Controlword.DISABLE_VOLTAGE:
                self._enter(S.SWITCH_ON_DISABLED)     # 9
            elif cmd == Controlword.QUICK_STOP:
                self._enter(S.QUICK_STOP_ACTIVE)      # 11
                if self._quick_stop_option() == 0:    # coast: torque off at once
                    self._velocity = 0.0
        elif s is S.QUICK_STOP_ACTIVE:
            option = self._quick_stop_option()
            if cmd == Controlword.DISABLE_VOLTAGE:
                self._enter(S.SWITCH_ON_DISABLED)     # 12 (disable voltage)
            elif cmd == Controlword.ENABLE_OPERATION and option >= 5:
                self._enter(S.OPERATION_ENABLED)      # 16
            elif option <= 4 and self._velocity == 0.0:
                self._enter(S.SWITCH_ON_DISABLED)     # 12 (quick stop completed)
        elif s is S.FAULT_REACTION_ACTIVE:
            if self._velocity == 0.0 and self._steps_in_state > 1:
                self._enter(S.FAULT)                  # 14
        elif s is S.FAULT:
            if reset_edge:                            # 15
                log.info("drive model serial=%d: fault 0x%04X reset (transition 15)",
                         self.serial, self.error_code)
                self._values[(0x603F, 0)] = 0
                self._values[(0x1001, 0)] = 0
                self._following_error = False
                self._emcy.append(Emcy(0, 0))
                self._enter(S.SWITCH_ON_DISABLED)

    def _quick_stop_option(self) -> int:
        return int(self._values[(0x605A, 0)])

    def _decel_for_option(self, option: int) -> float:
        """Deceleration of a stop option: 1 slow-down ramp (0x6084), 2..4 quick stop (0x6085)."""
        if option == 1:
            return float(self._values[(0x6084, 0)]) or 1.0
        return float(self._values[(0x6085, 0)]) or 1.0

    # ---------------------------------------------------------------- motion

    def _stop(self, option: int, dt: float) -> None:
        if option == 0:
            self._velocity = 0.0
        else:
            self._velocity = ramp(self._velocity, 0.0, 0.0, self._decel_for_option(option), dt)

    def _motion(self, cw: int, dt: float) -> None:
        v = self._values
        s = self._state
        self._target_reached = False
        self._torque = 0.0
        if s is State.OPERATION_ENABLED:
            if cw & CONTROLWORD_HALT:
                self._homing.interrupt()
                self._pp.target = None  # halt ends a profile position set-point (nothing resumes)
                self._stop(int(v[(0x605D, 0)]), dt)
                self._target_reached = self._velocity == 0.0
            else:
                self._operate(cw, dt)
        elif s is State.QUICK_STOP_ACTIVE:
            option = self._quick_stop_option()
            self._stop(option - 4 if option >= 5 else option, dt)  # 5..8 ramp like 1..4
            self._target_reached = self._velocity == 0.0
        elif s is State.FAULT_REACTION_ACTIVE:
            self._stop(int(v[(0x605E, 0)]), dt)
        elif self.rest_fast_path:
            # no torque (modelled without load inertia): at rest, the actual values exactly as
            # the general path below computes them for velocity and torque 0 (a test compares)
            self._velocity = 0.0
            p = self._position = max(min(self._position, 0x7FFFFFFF), -0x80000000)
            v[(0x6064, 0)] = int(round(p))
            v[(0x60FD, 0)] = (int(v[(0x60FD, 0)]) & ~HOME_SWITCH_BIT) | (HOME_SWITCH_BIT if self._switch_active() else 0)
            v[(0x60F4, 0)] = v[(0x606C, 0)] = v[(0x6077, 0)] = 0
            return
        else:
            self._velocity = 0.0
        self._position += self._velocity * dt
        self._position = max(min(self._position, 0x7FFFFFFF), -0x80000000)
        if (s is State.OPERATION_ENABLED and int(v[(0x6061, 0)]) == Mode.CYCLIC_SYNC_POSITION
                and not cw & CONTROLWORD_HALT):
            error = abs(int(v[(0x607A, 0)]) - self._position)
            window = int(v[(0x6065, 0)])
            self._target_reached = error <= _POSITION_WINDOW
            if window != 0xFFFFFFFF and error > window:  # 0xFFFFFFFF: following error check off
                self._following_error = True
                self.inject_fault(ERROR_FOLLOWING_ERROR)
        v[(0x6064, 0)] = int(round(self._position))
        switch = self._switch_active()
        v[(0x60FD, 0)] = (int(v[(0x60FD, 0)]) & ~HOME_SWITCH_BIT) | (HOME_SWITCH_BIT if switch else 0)
        v[(0x60F4, 0)] = (_clamp_int(int(v[(0x607A, 0)]) - int(round(self._position)), "i32")
                          if s is State.OPERATION_ENABLED and int(v[(0x6061, 0)]) == Mode.CYCLIC_SYNC_POSITION else 0)
        v[(0x606C, 0)] = _clamp_int(int(round(self._velocity)), "i32")
        v[(0x6077, 0)] = _clamp_int(int(round(self._torque)), "i16")

    def _operate(self, cw: int, dt: float) -> None:
        v = self._values
        mode = int(v[(0x6061, 0)])
        vmax = float(v[(0x607F, 0)])
        accel = float(v[(0x6083, 0)]) or 1.0
        decel = float(v[(0x6084, 0)]) or 1.0
        if mode == Mode.CYCLIC_SYNC_POSITION:
            # follow the target with the speed limit 0x607F; following error checked in _motion
            limit = vmax * dt
            delta = max(-limit, min(limit, self._within_limits(float(int(v[(0x607A, 0)]))) - self._position))
            self._velocity = delta / dt if dt > 0 else 0.0
        elif mode == Mode.CYCLIC_SYNC_VELOCITY:
            self._velocity = max(-vmax, min(vmax, float(int(v[(0x60FF, 0)]))))
            self._target_reached = True
        elif mode in (Mode.CYCLIC_SYNC_TORQUE, Mode.PROFILE_TORQUE):
            tmax = float(v[(0x6072, 0)])
            self._torque = max(-tmax, min(tmax, float(int(v[(0x6071, 0)]))))
            self._velocity += self._torque * self.profile.torque_accel * dt
            self._velocity = max(-vmax, min(vmax, self._velocity))
        elif mode == Mode.PROFILE_VELOCITY:
            target_v = max(-vmax, min(vmax, float(int(v[(0x60FF, 0)]))))
            self._velocity = ramp(self._velocity, target_v, accel, decel, dt)
            self._target_reached = abs(self._velocity - target_v) <= _VELOCITY_WINDOW
        elif mode == Mode.PROFILE_POSITION:
            self._velocity, self._target_reached = self._pp.step(
                cw, int(v[(0x607A, 0)]), self._position, self._velocity, profile_velocity=float(v[(0x6081, 0)]),
                vmax=vmax, accel=accel, decel=decel, dt=dt, within_limits=self._within_limits,
                ack_delay_steps=self.pp_ack_delay_steps, ack_stuck=self.pp_ack_stuck)
        elif mode == Mode.HOMING:
            self._home(cw, dt)
        else:
            self._velocity = ramp(self._velocity, 0.0, accel, decel, dt)  # no mode: hold

    def _within_limits(self, target: float) -> float:
        """A position target limited to the software position limits 0x607D:1/2 (CiA 402)."""
        lo, hi = int(self._values[(0x607D, 1)]), int(self._values[(0x607D, 2)])
        return max(float(lo), min(float(hi), target)) if lo < hi else target

    def _switch_active(self) -> bool:
        s = self.home_switch_position
        return s is not None and self._position >= s

    def _home(self, cw: int, dt: float) -> None:
        """Mode 6 (bus_agent.sim.homing_model): bit 4 edges start and interrupt the procedure."""
        v = self._values
        h = self._homing
        start = bool(cw & 0x10)
        if start and not self._prev_home_start:
            h.start(int(v[(0x6098, 0)]), self._position, self._switch_active())
        elif not start and self._prev_home_start:
            h.interrupt()
        self._prev_home_start = start
        want, at_edge = h.step(self._position, self._switch_active(), float(v[(0x6099, 1)]), float(v[(0x6099, 2)]))
        if at_edge:
            self._position = float(int(v[(0x607C, 0)]))  # the edge latched: position = home offset
        accel = float(v[(0x609A, 0)]) or 1.0
        self._velocity = ramp(self._velocity, want or 0.0, accel, accel, dt)
        if self._velocity == 0.0:
            h.at_rest()

    def _update_statusword(self) -> None:
        s = self._state
        sw = STATUSWORD_OF_STATE[s] | self.profile.statusword_extra
        if s in _POWERED:
            sw |= 1 << StatuswordBit.VOLTAGE_ENABLED
        if s in (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED):
            sw |= 1 << StatuswordBit.QUICK_STOP  # quick stop bit is low-active: not active here
        if self._target_reached:
            sw |= 1 << StatuswordBit.TARGET_REACHED
        mode = int(self._values[(0x6061, 0)])
        if s is State.OPERATION_ENABLED:
            if mode in (Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_VELOCITY, Mode.CYCLIC_SYNC_TORQUE):
                sw |= 1 << StatuswordBit.OPERATION_MODE_SPECIFIC_12  # drive follows the command value
            elif mode == Mode.PROFILE_POSITION and self._pp.ack:
                sw |= 1 << StatuswordBit.OPERATION_MODE_SPECIFIC_12  # set-point acknowledge
            elif mode == Mode.HOMING:
                sw = (sw & ~HOMING_BITS_MASK) | self._homing.bits(self._velocity)
        if self._following_error and mode == Mode.CYCLIC_SYNC_POSITION:
            sw |= 1 << StatuswordBit.OPERATION_MODE_SPECIFIC_13
        self._values[(0x6041, 0)] = sw


def _clamp_int(value: int, datatype: str) -> int:
    lo, hi = _INT_RANGES[datatype]
    v = int(value)
    return v if lo <= v <= hi else (lo if v < lo else hi)  # no max/min calls: 3 per drive and step
