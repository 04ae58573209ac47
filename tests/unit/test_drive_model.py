"""Drive model: state machine transitions 0..16, option codes, faults, modes, SDO, profiles."""

from __future__ import annotations

import struct

import pytest

from bus_agent.cia402.states import Controlword, Mode, State, decode_statusword
from bus_agent.bus.pdo import DriveOutputs
from bus_agent.sim.drive_model import (
    ABORT_DEVICE_STATE,
    ABORT_LENGTH_MISMATCH,
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    ABORT_NOT_MAPPABLE,
    ABORT_READ_ONLY,
    ABORT_VALUE_RANGE,
    ERROR_COMMUNICATION_LOST,
    ERROR_FOLLOWING_ERROR,
    OBJECT_TABLE,
    PROFILES,
    DriveModel,
    Emcy,
    SdoAbort,
    decode_command,
)

DT = 0.001
S = State


def cw_step(m: DriveModel, cw: int, steps: int = 1, **targets: int) -> None:
    out = DriveOutputs(controlword=cw, modes_of_operation=targets.pop("mode", 0), **targets)
    for _ in range(steps):
        m.apply_outputs(out)
        m.step(DT)


def assert_state(m: DriveModel, state: State) -> None:
    assert m.state is state
    assert decode_statusword(m.statusword) is state, hex(m.statusword)
    assert decode_statusword(m.inputs().statusword) is state


def booted(profile: str = "generic") -> DriveModel:
    m = DriveModel(PROFILES[profile])
    for _ in range(5):
        m.step(DT)
    if profile == "generic":
        assert_state(m, S.SWITCH_ON_DISABLED)
    return m


def to_state(state: State, **write: int) -> DriveModel:
    m = booted()
    for (index, value) in write.items():
        m.write(int(index[1:], 16), 0, value)
    path = {
        S.SWITCH_ON_DISABLED: [],
        S.READY_TO_SWITCH_ON: [Controlword.SHUTDOWN],
        S.SWITCHED_ON: [Controlword.SHUTDOWN, Controlword.SWITCH_ON],
        S.OPERATION_ENABLED: [Controlword.SHUTDOWN, Controlword.SWITCH_ON, Controlword.ENABLE_OPERATION],
        S.QUICK_STOP_ACTIVE: [Controlword.SHUTDOWN, Controlword.SWITCH_ON, Controlword.ENABLE_OPERATION,
                              Controlword.QUICK_STOP],
    }[state]
    for cw in path:
        cw_step(m, cw)
    assert_state(m, state)
    return m


# ------------------------------------------------------------------ power-up (0, 1) and profiles

def test_generic_power_up_transitions_0_and_1() -> None:
    m = DriveModel()
    assert_state(m, S.NOT_READY_TO_SWITCH_ON)  # transition 0
    m.step(DT)
    assert m.state is S.NOT_READY_TO_SWITCH_ON  # self test takes a step or two
    m.step(DT)
    assert_state(m, S.SWITCH_ON_DISABLED)  # transition 1, automatic
    assert m.statusword & 0x0200  # remote


def test_indy7_sequence_as_seed_004() -> None:
    m = DriveModel(PROFILES["indy7"])
    seen = [m.statusword]
    for _ in range(50):
        m.step(DT)
    seen.append(m.statusword)  # stays in not ready: no automatic transition 1
    for cw in (0x0006, 0x0007, 0x000F):
        cw_step(m, cw)
        seen.append(m.statusword)
    assert seen == [0x0220, 0x0220, 0x0221, 0x0233, 0x0237]
    assert m.state is S.OPERATION_ENABLED


def test_indy7_not_ready_ignores_other_commands() -> None:
    m = DriveModel(PROFILES["indy7"])
    for cw in (0x0000, 0x0002, 0x0007, 0x000F, 0x0080):
        cw_step(m, cw, steps=3)
        assert_state(m, S.NOT_READY_TO_SWITCH_ON)


def test_not_ready_generic_ignores_commands_until_self_test_done() -> None:
    m = DriveModel()
    cw_step(m, Controlword.SHUTDOWN)  # step 1: still in self test
    assert m.state is S.NOT_READY_TO_SWITCH_ON
    cw_step(m, Controlword.SHUTDOWN)  # transition 1
    assert m.state is S.SWITCH_ON_DISABLED
    cw_step(m, Controlword.SHUTDOWN)  # transition 2
    assert m.state is S.READY_TO_SWITCH_ON


# ------------------------------------------------------------------ transitions 2..12

@pytest.mark.parametrize("start, cw, end, number", [
    (S.SWITCH_ON_DISABLED, 0x0006, S.READY_TO_SWITCH_ON, 2),
    (S.SWITCH_ON_DISABLED, 0x000E, S.READY_TO_SWITCH_ON, 2),   # bit 3 don't care
    (S.READY_TO_SWITCH_ON, 0x0007, S.SWITCHED_ON, 3),
    (S.READY_TO_SWITCH_ON, 0x000F, S.SWITCHED_ON, 3),          # 3 then 4 on the next step
    (S.SWITCHED_ON, 0x000F, S.OPERATION_ENABLED, 4),
    (S.OPERATION_ENABLED, 0x0007, S.SWITCHED_ON, 5),
    (S.SWITCHED_ON, 0x0006, S.READY_TO_SWITCH_ON, 6),
    (S.READY_TO_SWITCH_ON, 0x0000, S.SWITCH_ON_DISABLED, 7),
    (S.READY_TO_SWITCH_ON, 0x0002, S.SWITCH_ON_DISABLED, 7),
    (S.READY_TO_SWITCH_ON, 0x0005, S.SWITCH_ON_DISABLED, 7),   # bit 1 clear = disable voltage
    (S.OPERATION_ENABLED, 0x0006, S.READY_TO_SWITCH_ON, 8),
    (S.OPERATION_ENABLED, 0x0000, S.SWITCH_ON_DISABLED, 9),
    (S.OPERATION_ENABLED, 0x000D, S.SWITCH_ON_DISABLED, 9),
    (S.SWITCHED_ON, 0x0000, S.SWITCH_ON_DISABLED, 10),
    (S.SWITCHED_ON, 0x0002, S.SWITCH_ON_DISABLED, 10),
    (S.OPERATION_ENABLED, 0x0002, S.QUICK_STOP_ACTIVE, 11),
    (S.OPERATION_ENABLED, 0x000B, S.QUICK_STOP_ACTIVE, 11),    # bit 2 clear = quick stop
    (S.QUICK_STOP_ACTIVE, 0x0000, S.SWITCH_ON_DISABLED, 12),
])
def test_transition(start: State, cw: int, end: State, number: int) -> None:
    m = to_state(start, x605A=6)  # 6: stay in quick stop active, so QSA is a stable start
    cw_step(m, cw)
    assert_state(m, end)


def test_switch_on_plus_enable_operation_reaches_oe_in_two_steps() -> None:
    m = to_state(S.READY_TO_SWITCH_ON)
    cw_step(m, 0x000F)
    assert m.state is S.SWITCHED_ON
    cw_step(m, 0x000F)
    assert_state(m, S.OPERATION_ENABLED)


def test_commands_without_transition_do_nothing() -> None:
    m = to_state(S.SWITCH_ON_DISABLED)
    for cw in (0x0007, 0x000F, 0x0002, 0x0000):
        cw_step(m, cw)
        assert m.state is S.SWITCH_ON_DISABLED  # never enabled without passing through RTSO/SO


def test_controlword_taken_at_next_step_only() -> None:
    m = to_state(S.SWITCH_ON_DISABLED)
    m.write(0x6040, 0, 0x0006)
    assert m.state is S.SWITCH_ON_DISABLED
    m.step(DT)
    assert m.state is S.READY_TO_SWITCH_ON


def test_voltage_enabled_bit() -> None:
    m = to_state(S.READY_TO_SWITCH_ON)
    assert not m.statusword & 0x10
    cw_step(m, 0x0007)
    assert m.statusword & 0x10


# ------------------------------------------------------------------ quick stop 0x605A

def moving_in_pv(option: int, velocity: int = 10_000) -> DriveModel:
    m = to_state(S.OPERATION_ENABLED, x605A=option)
    m.write(0x6083, 0, 10_000_000)
    cw_step(m, 0x000F, steps=10, mode=Mode.PROFILE_VELOCITY, target_velocity=velocity)
    assert m.velocity == velocity
    return m


def test_quick_stop_option_0_coasts_to_sod_at_once() -> None:
    m = moving_in_pv(0)
    cw_step(m, 0x0002, mode=3, target_velocity=10_000)
    assert m.velocity == 0
    cw_step(m, 0x0002, mode=3, target_velocity=10_000)
    assert_state(m, S.SWITCH_ON_DISABLED)  # transition 12


@pytest.mark.parametrize("option", [1, 2, 3, 4])
def test_quick_stop_ramp_then_sod(option: int) -> None:
    m = moving_in_pv(option)
    m.write(0x6084, 0, 100_000)      # slow-down ramp: 0.1 s from 10,000
    m.write(0x6085, 0, 1_000_000)    # quick stop ramp: 0.01 s
    cw_step(m, 0x0002, mode=3, target_velocity=10_000)
    assert_state(m, S.QUICK_STOP_ACTIVE)
    assert not m.statusword & 0x20   # quick stop bit low while active
    steps = 0
    while m.state is S.QUICK_STOP_ACTIVE:
        assert 0 <= m.velocity < 10_000
        cw_step(m, 0x0002, mode=3, target_velocity=10_000)
        steps += 1
        assert steps < 1000
    assert_state(m, S.SWITCH_ON_DISABLED)  # transition 12 when stopped
    assert m.velocity == 0
    expected = 100 if option == 1 else 10
    assert expected <= steps <= expected + 2


@pytest.mark.parametrize("option", [5, 6, 7, 8])
def test_quick_stop_5_to_8_stays_in_qsa_and_transition_16(option: int) -> None:
    m = moving_in_pv(option)
    cw_step(m, 0x0002, steps=500, mode=3, target_velocity=10_000)
    assert_state(m, S.QUICK_STOP_ACTIVE)
    assert m.velocity == 0
    cw_step(m, 0x000F, mode=3, target_velocity=10_000)
    assert_state(m, S.OPERATION_ENABLED)  # transition 16


@pytest.mark.parametrize("option", [0, 1, 2, 3, 4])
def test_enable_operation_in_qsa_refused_for_0_to_4(option: int) -> None:
    m = moving_in_pv(option)
    m.write(0x6084, 0, 10_000)
    m.write(0x6085, 0, 10_000)      # 1 s ramp: stays in QSA a while
    cw_step(m, 0x0002, mode=3, target_velocity=10_000)
    if option == 0:
        assert m.velocity == 0
    else:
        cw_step(m, 0x000F, mode=3, target_velocity=10_000)
        assert m.state is S.QUICK_STOP_ACTIVE  # no transition 16 for 0..4
    for _ in range(2000):
        cw_step(m, 0x000F, mode=3, target_velocity=10_000)
    assert m.state is S.SWITCH_ON_DISABLED


def test_quick_stop_option_range_checked() -> None:
    m = booted()
    with pytest.raises(SdoAbort) as e:
        m.write(0x605A, 0, 9)
    assert e.value.code == ABORT_VALUE_RANGE
    assert m.read(0x605A, 0) == 2


# ------------------------------------------------------------------ faults (13, 14, 15), 0x603F, EMCY

@pytest.mark.parametrize("start", [S.NOT_READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON,
                                   S.SWITCHED_ON, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE])
def test_fault_from_any_state_13_14_15(start: State) -> None:
    m = DriveModel() if start is S.NOT_READY_TO_SWITCH_ON else to_state(start, x605A=6)
    m.take_emcy()
    m.inject_fault(0x2310)
    assert_state(m, S.FAULT_REACTION_ACTIVE)  # transition 13
    assert m.read(0x603F, 0) == 0x2310
    assert m.inputs().error_code == 0x2310
    assert m.read(0x1001, 0) == 0x03  # generic + current
    assert m.take_emcy() == [Emcy(0x2310, 0x03)]
    for _ in range(3):
        m.step(DT)
    assert_state(m, S.FAULT)  # transition 14
    cw_step(m, 0x0080)  # rising edge of bit 7
    assert_state(m, S.SWITCH_ON_DISABLED)  # transition 15
    assert m.read(0x603F, 0) == 0
    assert m.read(0x1001, 0) == 0
    assert m.take_emcy() == [Emcy(0, 0)]


def test_fault_reset_needs_a_rising_edge() -> None:
    m = to_state(S.SWITCH_ON_DISABLED)
    cw_step(m, 0x0080)  # bit 7 already high before the fault
    m.inject_fault(0x5530)
    cw_step(m, 0x0080, steps=10)
    assert m.state is S.FAULT  # a level is not an edge
    cw_step(m, 0x0000)
    assert m.state is S.FAULT
    cw_step(m, 0x0080)
    assert m.state is S.SWITCH_ON_DISABLED


def test_fault_reset_ignored_during_fault_reaction() -> None:
    m = moving_in_pv(2)
    m.write(0x605E, 0, 1)
    m.write(0x6084, 0, 100_000)
    m.inject_fault(0x7300)
    cw_step(m, 0x0000)
    cw_step(m, 0x0080)
    assert m.state is S.FAULT_REACTION_ACTIVE


@pytest.mark.parametrize("option, steps", [(0, 2), (1, 100), (2, 10), (3, 10), (4, 10)])
def test_fault_reaction_option_0x605E(option: int, steps: int) -> None:
    m = moving_in_pv(2)
    m.write(0x605E, 0, option)
    m.write(0x6084, 0, 100_000)
    m.write(0x6085, 0, 1_000_000)
    m.inject_fault(0x4210)
    n = 0
    while m.state is S.FAULT_REACTION_ACTIVE:
        cw_step(m, 0x000F, mode=3, target_velocity=10_000)  # the master's command is ignored
        n += 1
        assert n < 1000
    assert m.state is S.FAULT
    assert m.velocity == 0
    assert steps <= n <= steps + 2


def test_fault_while_in_fault_updates_error_code_and_emcy() -> None:
    m = to_state(S.SWITCH_ON_DISABLED)
    m.inject_fault(0x2310)
    m.step(DT)
    m.step(DT)
    m.inject_fault(0x3210)
    assert m.state is S.FAULT
    assert m.read(0x603F, 0) == 0x3210
    assert [e.error_code for e in m.take_emcy()] == [0x2310, 0x3210]


@pytest.mark.parametrize("code", [0, -1, 0x10000, "x"])
def test_inject_fault_rejects_bad_code(code: object) -> None:
    m = to_state(S.SWITCH_ON_DISABLED)
    with pytest.raises(ValueError):
        m.inject_fault(code)  # type: ignore[arg-type]
    assert m.state is S.SWITCH_ON_DISABLED


def test_communication_lost_from_oe_faults_with_0x8130() -> None:
    m = to_state(S.OPERATION_ENABLED)
    m.communication_lost()
    assert m.state is S.FAULT_REACTION_ACTIVE
    assert m.read(0x603F, 0) == ERROR_COMMUNICATION_LOST
    assert m.read(0x1001, 0) & 0x10  # communication error bit
    m2 = to_state(S.SWITCHED_ON)
    m2.communication_lost()
    assert m2.state is S.SWITCHED_ON


def test_power_cycle_back_to_power_on() -> None:
    m = to_state(S.OPERATION_ENABLED)
    m.write(0x605A, 0, 7)
    m.inject_fault(0x1000)
    m.power_cycle()
    assert_state(m, S.NOT_READY_TO_SWITCH_ON)
    assert m.read(0x603F, 0) == 0
    assert m.read(0x605A, 0) == 2
    assert m.take_emcy() == []


# ------------------------------------------------------------------ modes

@pytest.mark.parametrize("mode", [1, 3, 4, 8, 9, 10])
def test_mode_echo_by_pdo_and_sdo(mode: int) -> None:
    m = booted()
    cw_step(m, 0, mode=mode)
    assert m.read(0x6061, 0) == mode
    assert m.inputs().modes_of_operation_display == mode
    m2 = booted()
    m2.write(0x6060, 0, mode)
    assert m2.read(0x6061, 0) == 0  # taken at the next step
    m2.step(DT)
    assert m2.read(0x6061, 0) == mode


@pytest.mark.parametrize("mode", [0, 2, 7, -1, 11, 127])
def test_unsupported_mode_refused_by_sdo_and_ignored_by_pdo(mode: int) -> None:
    m = booted()
    cw_step(m, 0, mode=8)
    with pytest.raises(SdoAbort) as e:
        m.write(0x6060, 0, mode)
    assert e.value.code == ABORT_VALUE_RANGE
    assert m.read(0x6060, 0) == 8
    cw_step(m, 0, mode=mode, steps=3)
    assert m.read(0x6061, 0) == 8
    assert m.read(0x6060, 0) == 8


def test_mode_echo_delay_profile() -> None:
    from dataclasses import replace
    m = DriveModel(replace(PROFILES["generic"], mode_echo_delay_steps=3))
    m.write(0x6060, 0, 9)
    seen = []
    for _ in range(5):
        m.step(DT)
        seen.append(m.read(0x6061, 0))
    assert seen == [0, 0, 0, 9, 9]


# ------------------------------------------------------------------ motion

def test_no_motion_unless_operation_enabled() -> None:
    m = to_state(S.SWITCHED_ON)
    cw_step(m, 0x0007, steps=100, mode=9, target_velocity=5000)
    assert m.inputs().position_actual == 0
    assert m.inputs().velocity_actual == 0


def test_csv_integrates_position() -> None:
    m = to_state(S.OPERATION_ENABLED)
    cw_step(m, 0x000F, steps=1000, mode=9, target_velocity=5000)
    inp = m.inputs()
    assert inp.velocity_actual == 5000
    assert 4990 <= inp.position_actual <= 5000  # first step echoes the mode
    assert inp.statusword & 0x1000  # bit 12: follows the command value


def test_csv_velocity_limited_by_0x607F() -> None:
    m = to_state(S.OPERATION_ENABLED)
    m.write(0x607F, 0, 2000)
    cw_step(m, 0x000F, steps=10, mode=9, target_velocity=-5000)
    assert m.inputs().velocity_actual == -2000


def test_csp_follows_with_speed_limit() -> None:
    m = to_state(S.OPERATION_ENABLED)
    m.write(0x607F, 0, 100_000)   # 100 increments per 1 ms step
    m.write(0x6065, 0, 0xFFFFFFFF)  # check off
    cw_step(m, 0x000F, mode=8)
    cw_step(m, 0x000F, steps=5, mode=8, target_position=1000)
    assert m.inputs().position_actual == 500
    cw_step(m, 0x000F, steps=10, mode=8, target_position=1000)
    assert m.inputs().position_actual == 1000
    assert m.inputs().statusword & 0x0400  # target reached
    assert m.state is S.OPERATION_ENABLED


def test_csp_following_error_faults_8611() -> None:
    m = to_state(S.OPERATION_ENABLED)
    m.write(0x607F, 0, 100_000)
    m.write(0x6065, 0, 1000)
    cw_step(m, 0x000F, mode=8)
    cw_step(m, 0x000F, mode=8, target_position=1050)  # 950 behind: inside the window
    assert m.state is S.OPERATION_ENABLED
    cw_step(m, 0x000F, mode=8, target_position=5000)  # stale/jumped target
    assert m.state is S.FAULT_REACTION_ACTIVE
    assert m.read(0x603F, 0) == ERROR_FOLLOWING_ERROR
    assert m.statusword & 0x2000  # bit 13: following error
    assert [e.error_code for e in m.take_emcy()] == [ERROR_FOLLOWING_ERROR]


def test_pv_ramps_with_profile_acceleration() -> None:
    m = to_state(S.OPERATION_ENABLED)
    m.write(0x6083, 0, 1_000_000)
    cw_step(m, 0x000F, mode=3)
    cw_step(m, 0x000F, steps=5, mode=3, target_velocity=100_000)
    assert m.inputs().velocity_actual == 5000
    cw_step(m, 0x000F, steps=200, mode=3, target_velocity=100_000)
    assert m.inputs().velocity_actual == 100_000
    assert m.inputs().statusword & 0x0400


def test_pp_moves_to_target_on_new_setpoint() -> None:
    m = to_state(S.OPERATION_ENABLED)
    m.write(0x6081, 0, 50_000)
    cw_step(m, 0x000F, mode=1, target_position=2000, steps=10)
    assert m.inputs().position_actual == 0  # no new set-point yet
    cw_step(m, 0x001F, mode=1, target_position=2000)
    assert m.statusword & 0x1000  # set-point acknowledge
    cw_step(m, 0x000F, mode=1, target_position=2000, steps=500)
    assert m.inputs().position_actual == 2000
    assert m.inputs().velocity_actual == 0
    assert m.statusword & 0x0400


def test_torque_modes() -> None:
    m = to_state(S.OPERATION_ENABLED)
    cw_step(m, 0x000F, mode=10, target_torque=100, steps=10)
    inp = m.inputs()
    assert inp.torque_actual == 100
    assert inp.velocity_actual > 0
    assert inp.position_actual > 0


def test_halt_decelerates_and_stays_enabled() -> None:
    m = moving_in_pv(2)
    m.write(0x605D, 0, 1)
    m.write(0x6084, 0, 1_000_000)
    cw_step(m, 0x010F, mode=3, target_velocity=10_000, steps=5)
    assert 0 < m.velocity < 10_000
    cw_step(m, 0x010F, mode=3, target_velocity=10_000, steps=10)
    assert m.velocity == 0
    assert_state(m, S.OPERATION_ENABLED)
    assert m.statusword & 0x0400  # target reached while halted and stopped
    cw_step(m, 0x000F, mode=3, target_velocity=10_000, steps=10)
    assert m.velocity == 10_000


# ------------------------------------------------------------------ object dictionary and SDO

def test_object_table_is_typed() -> None:
    for e in OBJECT_TABLE:
        assert e.datatype in ("u8", "i8", "u16", "i16", "u32", "i32", "str")
        assert e.access in ("ro", "rw", "wo")
    m = DriveModel(serial=7)
    assert m.read(0x1000, 0) == 0x00020192
    assert m.read(0x1018, 4) == 7
    assert m.read(0x6502, 0) == PROFILES["generic"].supported_modes
    assert m.read_bytes(0x1008, 0) == b"SimDrive402"
    assert m.read_bytes(0x6041, 0) == struct.pack("<H", m.statusword)
    assert m.objects[(0x6041, 0)].size == 2


@pytest.mark.parametrize("index, sub, code", [
    (0x2000, 0, ABORT_NO_OBJECT),
    (0x6041, 1, ABORT_NO_SUBINDEX),
    (0x1018, 9, ABORT_NO_SUBINDEX),
])
def test_sdo_read_aborts(index: int, sub: int, code: int) -> None:
    m = DriveModel()
    with pytest.raises(SdoAbort) as e:
        m.read(index, sub)
    assert e.value.code == code
    with pytest.raises(SdoAbort):
        m.read_bytes(index, sub)


@pytest.mark.parametrize("index, sub, data, code", [
    (0x2000, 0, b"\0\0", ABORT_NO_OBJECT),
    (0x6040, 3, b"\0\0", ABORT_NO_SUBINDEX),
    (0x6041, 0, b"\0\0", ABORT_READ_ONLY),
    (0x1000, 0, b"\0\0\0\0", ABORT_READ_ONLY),
    (0x6040, 0, b"\0", ABORT_LENGTH_MISMATCH),
    (0x6040, 0, b"\0\0\0\0", ABORT_LENGTH_MISMATCH),
    (0x605A, 0, struct.pack("<h", -1), ABORT_VALUE_RANGE),
    (0x605E, 0, struct.pack("<h", 5), ABORT_VALUE_RANGE),
    (0x6060, 0, struct.pack("<b", 7), ABORT_VALUE_RANGE),
    (0x1600, 1, struct.pack("<I", 0x60410010), ABORT_NOT_MAPPABLE),  # RxPDO: read-only
    (0x1600, 1, struct.pack("<I", 0x60650020), ABORT_NOT_MAPPABLE),  # not mappable
    (0x1600, 1, struct.pack("<I", 0x60400020), ABORT_NOT_MAPPABLE),  # wrong bit length
    (0x1C12, 1, struct.pack("<H", 0x1A00), ABORT_VALUE_RANGE),
])
def test_sdo_write_aborts_change_nothing(index: int, sub: int, data: bytes, code: int) -> None:
    m = booted()
    before = {k: m.read(*k) for k in m.objects}
    with pytest.raises(SdoAbort) as e:
        m.write_bytes(index, sub, data)
    assert e.value.code == code
    assert f"0x{code:08X}" in str(e.value)
    assert {k: m.read(*k) for k in m.objects} == before


def test_sdo_write_roundtrip_and_int_range() -> None:
    m = booted()
    m.write_bytes(0x607A, 0, struct.pack("<i", -123456))
    assert m.read(0x607A, 0) == -123456
    with pytest.raises(SdoAbort) as e:
        m.write(0x6040, 0, 0x10000)
    assert e.value.code == ABORT_VALUE_RANGE


def test_pdo_mapping_locked_outside_preop() -> None:
    m = booted()
    m.write(0x1C12, 0, 0)
    m.write(0x1600, 6, 0x60810020)  # profile velocity is mappable
    m.set_pdo_config_locked(True)
    with pytest.raises(SdoAbort) as e:
        m.write(0x1C12, 0, 1)
    assert e.value.code == ABORT_DEVICE_STATE


def test_decode_command_table() -> None:
    C = Controlword
    cases = {0x0006: C.SHUTDOWN, 0x000E: C.SHUTDOWN, 0x0007: C.SWITCH_ON, 0x000F: C.ENABLE_OPERATION,
             0x0000: C.DISABLE_VOLTAGE, 0x0004: C.DISABLE_VOLTAGE, 0x0002: C.QUICK_STOP, 0x000B: C.QUICK_STOP,
             0x008F: C.ENABLE_OPERATION, 0x010F: C.ENABLE_OPERATION}  # bits 7 and 8 are not the command
    assert {cw: decode_command(cw) for cw in cases} == cases


def test_communication_lost_from_quick_stop_active() -> None:
    m = to_state(S.QUICK_STOP_ACTIVE, x605A=6)
    m.communication_lost()
    assert m.state is S.FAULT_REACTION_ACTIVE
    assert m.read(0x603F, 0) == ERROR_COMMUNICATION_LOST


def test_step_rejects_bad_dt_and_changes_nothing() -> None:
    m = to_state(S.SWITCH_ON_DISABLED)
    m.write(0x6040, 0, 0x0006)
    for dt in (-0.001, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            m.step(dt)
    assert m.state is S.SWITCH_ON_DISABLED
