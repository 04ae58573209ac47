"""SimBus: the Bus protocol over drive models (WKC, AL states, unplug/plug, SDO, watchdog)."""

from __future__ import annotations

import struct

import pytest

from bus_agent.bus.mapping import MappingPolicy, SlaveSetup, StartupSdo

from bus_agent.bus.base import ALState, Bus, BusError
from bus_agent.bus.sim_bus import AL_INVALID_OUTPUT_CONFIG, AL_INVALID_STATE_CHANGE, AL_SM_WATCHDOG, SimBus, SimSdoError
from bus_agent.cia402.states import State, decode_statusword
from bus_agent.bus.pdo import DriveOutputs
from bus_agent.sim.drive_model import ABORT_NO_OBJECT, ABORT_READ_ONLY, ABORT_VALUE_RANGE, ERROR_COMMUNICATION_LOST


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def started(n: int = 3, profile: str = "generic", **kw) -> tuple[SimBus, FakeClock]:
    clock = FakeClock()
    bus = SimBus(n, profile=profile, clock=clock, **kw)
    bus.open()
    assert bus.start() == 3 * n
    return bus, clock


def cycle(bus: SimBus, clock: FakeClock, n: int = 1, dt: float = 0.001) -> int:
    wkc = 0
    for _ in range(n):
        clock.t += dt
        wkc = bus.exchange()
    return wkc


def enable(bus: SimBus, clock: FakeClock, position: int) -> None:
    for cw in (0x0006, 0x0007, 0x000F):
        bus.set_outputs(position, DriveOutputs(controlword=cw, modes_of_operation=9))
        cycle(bus, clock, 3)
    assert bus.model(position).state is State.OPERATION_ENABLED


def test_is_a_bus_and_identifies_slaves() -> None:
    bus: Bus = SimBus(2, profile=["generic", "indy7"], segment_name="s1")
    assert bus.backend == "sim"
    infos = bus.open()
    assert [i.position for i in infos] == [0, 1]
    assert infos[0].name == "SimDrive402" and infos[1].name == "SimIndy7Joint"
    assert infos[1].identity.product_code == 0x00402007
    assert infos[0].identity.serial == 1
    assert [s.state for s in bus.read_al_status()] == [ALState.PREOP] * 2


def test_start_reaches_op_and_wkc_is_3n() -> None:
    bus, clock = started(4)
    assert bus.expected_wkc == 12
    assert all(s.state is ALState.OP and not s.error for s in bus.read_al_status())
    assert cycle(bus, clock, 3) == 12


def test_start_before_open_and_mapping_override_refused() -> None:
    bus = SimBus(1)
    with pytest.raises(BusError, match="before open"):
        bus.start()
    bus.open()
    predefined = SlaveSetup(MappingPolicy(policy="predefined", rx=(0x1701,), tx=(0x1B01,)))
    with pytest.raises(BusError, match="slave 0: mapping policy 'predefined' is not supported"):
        bus.start({0: predefined})
    with pytest.raises(BusError, match="no distributed clocks"):
        bus.start({0: SlaveSetup(sync0=(1_000_000, 0))})


def test_start_applies_startup_sdos_and_the_default_policies() -> None:
    bus = SimBus(2)
    bus.open()
    window = StartupSdo(0x6065, 0, "u32", 12345)
    assert bus.start({0: SlaveSetup(MappingPolicy(policy="default"), sdos=(window,)),
                      1: SlaveSetup(MappingPolicy(policy="drive"))}) == 6
    assert int.from_bytes(bus.sdo_read(0, 0x6065, 0, 4), "little") == 12345
    assert int.from_bytes(bus.sdo_read(1, 0x6065, 0, 4), "little") != 12345


def test_bad_constructor_arguments() -> None:
    with pytest.raises(ValueError):
        SimBus(0)
    with pytest.raises(ValueError, match="unknown drive profile"):
        SimBus(1, profile="nope")
    with pytest.raises(ValueError):
        SimBus(2, profile=["generic"])


def test_exchange_drives_models_by_clock_time() -> None:
    bus, clock = started(2)
    cycle(bus, clock, 5)
    assert decode_statusword(bus.inputs(0).statusword) is State.SWITCH_ON_DISABLED
    enable(bus, clock, 1)
    bus.set_outputs(1, DriveOutputs(controlword=0x000F, target_velocity=1000, modes_of_operation=9))
    cycle(bus, clock, 1)
    before = bus.inputs(1).position_actual
    cycle(bus, clock, 1, dt=0.05)  # 50 ms at 1000 inc/s
    assert bus.inputs(1).position_actual - before == 50
    assert bus.inputs(0).position_actual == 0


def test_indy7_sequence_over_the_bus() -> None:
    bus, clock = started(1, profile="indy7")
    cycle(bus, clock, 10)
    seen = [bus.inputs(0).statusword]
    for cw in (0x0006, 0x0007, 0x000F):
        bus.set_outputs(0, DriveOutputs(controlword=cw))
        cycle(bus, clock, 2)
        seen.append(bus.inputs(0).statusword)
    assert seen == [0x0220, 0x0221, 0x0233, 0x0237]


def test_outputs_applied_only_in_op_and_inputs_from_safeop() -> None:
    bus, clock = started(1)
    bus.request_al_state(0, ALState.SAFEOP)
    bus.set_outputs(0, DriveOutputs(controlword=0x0006))
    assert cycle(bus, clock, 5) == 1
    assert bus.model(0).state is State.SWITCH_ON_DISABLED
    bus.request_al_state(0, ALState.PREOP)
    assert cycle(bus, clock) == 0


def test_leaving_op_makes_enabled_drives_lose_communication() -> None:
    bus, clock = started(2)
    enable(bus, clock, 0)
    bus.request_al_state(None, ALState.SAFEOP)
    assert bus.model(0).state is State.FAULT_REACTION_ACTIVE
    assert bus.model(0).error_code == ERROR_COMMUNICATION_LOST
    assert bus.model(1).state is State.SWITCH_ON_DISABLED  # not enabled: nothing happens
    cycle(bus, clock, 5)
    assert decode_statusword(bus.inputs(0).statusword) is State.FAULT


def test_invalid_al_transition_sets_error_flag_and_ack_clears() -> None:
    bus = SimBus(1, clock=FakeClock())
    bus.open()
    bus.request_al_state(0, ALState.OP)  # PRE-OP -> OP skips SAFE-OP
    st = bus.read_al_status()[0]
    assert (st.state, st.error, st.status_code) == (ALState.PREOP, True, AL_INVALID_STATE_CHANGE)
    bus.request_al_state(0, ALState.PREOP)
    st = bus.read_al_status()[0]
    assert (st.state, st.error, st.status_code) == (ALState.PREOP, False, 0)


def test_unplug_plug_recover() -> None:
    bus, clock = started(3)
    enable(bus, clock, 1)
    bus.unplug(1)
    assert cycle(bus, clock) == 6
    assert bus.read_al_status()[1].state is ALState.NONE
    assert bus.recover(1) is False
    with pytest.raises(BusError, match="unplugged"):
        bus.sdo_read(1, 0x6041, 0, 2)
    bus.plug(1)
    st = bus.read_al_status()[1]
    assert st.state is ALState.INIT  # came back freshly powered
    assert bus.model(1).state is State.NOT_READY_TO_SWITCH_ON
    assert cycle(bus, clock) == 6
    # a freshly powered slave cannot go to SAFE-OP before it is reconfigured
    bus.request_al_state(1, ALState.PREOP)
    bus.request_al_state(1, ALState.SAFEOP)
    assert bus.read_al_status()[1].status_code == AL_INVALID_OUTPUT_CONFIG
    assert bus.recover(1) is True
    assert bus.read_al_status()[1].state is ALState.OP
    assert cycle(bus, clock, 3) == 9
    assert bus.model(1).state is State.SWITCH_ON_DISABLED  # never enabled again by itself


def test_wkc_fault_and_sm_watchdog() -> None:
    bus, clock = started(2)
    enable(bus, clock, 0)
    bus.set_wkc_fault(0, True)
    assert cycle(bus, clock, 1, dt=0.01) == 3
    assert bus.model(0).state is State.OPERATION_ENABLED
    cycle(bus, clock, 12, dt=0.01)  # > 100 ms without outputs
    st = bus.read_al_status()[0]
    assert (st.state, st.error, st.status_code) == (ALState.SAFEOP, True, AL_SM_WATCHDOG)
    assert bus.model(0).error_code == ERROR_COMMUNICATION_LOST
    bus.set_wkc_fault(0, False)
    assert cycle(bus, clock) == 4  # SAFE-OP: inputs only
    assert bus.recover(0) is True
    assert cycle(bus, clock) == 6


def test_master_stall_trips_the_watchdog() -> None:
    bus, clock = started(1)
    enable(bus, clock, 0)
    cycle(bus, clock, 1, dt=0.5)
    assert bus.read_al_status()[0].status_code == AL_SM_WATCHDOG
    bus2, clock2 = started(1, sm_watchdog_s=None)
    enable(bus2, clock2, 0)
    cycle(bus2, clock2, 1, dt=0.5)
    assert bus2.read_al_status()[0].state is ALState.OP


def test_inject_fault() -> None:
    bus, clock = started(2)
    bus.inject_fault(1, 0x7500)
    cycle(bus, clock, 3)
    assert decode_statusword(bus.inputs(1).statusword) is State.FAULT
    assert bus.inputs(1).error_code == 0x7500
    with pytest.raises(BusError):
        bus.inject_fault(5, 0x7500)
    with pytest.raises(ValueError):
        bus.inject_fault(0, 0)


def test_sdo_through_the_model() -> None:
    bus, clock = started(1)
    assert bus.sdo_read(0, 0x1000, 0, 4) == struct.pack("<I", 0x00020192)
    bus.sdo_write(0, 0x605A, 0, struct.pack("<h", 6))
    assert bus.sdo_read(0, 0x605A, 0, 2) == struct.pack("<h", 6)
    for index, data, code in ((0x2222, b"\0\0", ABORT_NO_OBJECT), (0x6041, b"\0\0", ABORT_READ_ONLY),
                              (0x6060, b"\x07", ABORT_VALUE_RANGE)):
        with pytest.raises(SimSdoError) as e:
            bus.sdo_write(0, index, 0, data)
        assert e.value.abort_code == code
        assert f"0x{index:04X}" in str(e.value) and "slave 0" in str(e.value) and f"0x{code:08X}" in str(e.value)
    with pytest.raises(BusError, match="buffer"):
        bus.sdo_read(0, 0x1000, 0, 2)
    with pytest.raises(SimSdoError):  # PDO mapping locked outside PRE-OP
        bus.sdo_write(0, 0x1C12, 0, b"\0")


def test_close_is_idempotent_and_stops_drives() -> None:
    bus, clock = started(1)
    enable(bus, clock, 0)
    bus.close()
    bus.close()
    assert bus.read_al_status()[0].state is ALState.INIT
    assert bus.model(0).state is State.FAULT_REACTION_ACTIVE
    with pytest.raises(BusError, match="INIT"):
        bus.sdo_read(0, 0x1000, 0, 4)


def test_skipping_steady_models_changes_nothing_a_master_can_see() -> None:
    """SimBus.skip_steady (a steady model is not stepped, its inputs not re-read; the idle demo's
    cost): random outputs, modes, SDO writes, faults, resets, AL changes, unplug/plug, WKC faults
    and home-switch moves through two buses, one skipping and one not: after every exchange the
    same WKC, inputs, changed-inputs report, drive states and object values."""
    import random

    rng = random.Random(402)
    (fast, cf), (full, cl) = started(3), started(3)
    full.skip_steady = False
    words = (0x0000, 0x0006, 0x0007, 0x000F, 0x0080, 0x0002, 0x010F, 0x000B)
    skipped = 0
    for step in range(8000):
        r = rng.random()
        pos = rng.randrange(3)
        if r < 0.08:
            out = DriveOutputs(controlword=rng.choice(words), target_position=rng.randint(-200, 200),
                               target_velocity=rng.choice((0, 0, 300)), target_torque=0,
                               modes_of_operation=rng.choice((8, 8, 9, 1, 0)))
            for b in (fast, full):
                b.set_outputs(pos, out)
        elif r < 0.085:
            for b in (fast, full):
                b.inject_fault(pos, 0x7305)
        elif r < 0.09:
            data = struct.pack("<h", rng.choice((2, 6, 1)))
            for b in (fast, full):
                if b._slaves[pos].plugged:
                    b.sdo_write(pos, 0x605A, 0, data)
        elif r < 0.092:
            state = rng.choice((ALState.SAFEOP, ALState.OP, ALState.PREOP))
            for b in (fast, full):
                b.request_al_state(pos, state)
        elif r < 0.0935:
            on = rng.random() < 0.5
            for b in (fast, full):
                b.set_wkc_fault(pos, on)
        elif r < 0.094:
            for b in (fast, full):
                b.unplug(pos)
        elif r < 0.096:
            for b in (fast, full):
                b.plug(pos)
                b.recover(pos)
        elif r < 0.097:
            where = rng.choice((None, -50, 0, 50))
            for b in (fast, full):
                b.model(pos).home_switch_position = where
        skipped += sum(1 for k in range(3) if fast._slaves[k].plugged and fast._slaves[k].inputs_al is
                       fast._slaves[k].al_state and fast.model(k).steady())
        cf.t += 0.001
        cl.t += 0.001
        assert fast.exchange() == full.exchange(), step
        assert fast.inputs_changed() == full.inputs_changed(), step
        for k in range(3):
            assert fast.inputs(k) == full.inputs(k), (step, k)
            assert fast.model(k).state is full.model(k).state, (step, k)
            assert fast.model(k)._values == full.model(k)._values, (step, k)
        assert [s.state for s in fast.read_al_status()] == [s.state for s in full.read_al_status()], step
    assert skipped > 4000  # the fast path was taken, most of the time
