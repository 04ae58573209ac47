"""Supported drive modes (0x6502) read at start-up (SimBus, no root): an unsupported set_mode is
rejected at once with the reason, a drive without 0x6502 is tolerated, a configured mode the
drive does not support is a start-up error."""

from __future__ import annotations

import dataclasses

import pytest

from bus_agent.bus.sim_bus import SimBus, SimSdoError
from bus_agent.cia402.states import Mode
from bus_agent.config import AgentConfig, ConfigError, DriveConfig
from bus_agent.cycle.cycle import Cycle, decode_supported_modes
from bus_agent.runtime import DriveCommand, Outcome
from bus_agent.sim.drive_model import PROFILES

CSP, CSV, PT = int(Mode.CYCLIC_SYNC_POSITION), int(Mode.CYCLIC_SYNC_VELOCITY), int(Mode.PROFILE_TORQUE)
# A drive that offers only CSP and CSV (bits 7 and 8 of 0x6502).
CSP_CSV = dataclasses.replace(PROFILES["generic"], name="csp_csv", supported_modes=(1 << 7) | (1 << 8))


class NoModesObject(SimBus):
    """A drive without 0x6502: the SDO upload aborts with 0x06020000 (object does not exist)."""

    def sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        if index == 0x6502:
            raise SimSdoError(position, index, subindex, 0x06020000, "object does not exist")
        return super().sdo_read(position, index, subindex, size)


class Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


def _cycle(bus: SimBus, **cfg) -> tuple[Cycle, Clock]:
    clock = Clock()
    bus._clock = lambda: clock.ns / 1e9
    cyc = Cycle(bus, AgentConfig(host="h1", sim_drives=bus.n_drives, **cfg), clock_ns=clock,
                manage_gc=False, switch_interval_s=None)
    return cyc, clock


def _set_mode(cyc: Cycle, clock: Clock, mode: int, rid: str) -> list[Outcome]:
    got: list[Outcome] = []
    assert cyc.submit(DriveCommand(request_id=rid, op="set_mode", axes=("axis0",), args={"mode": mode},
                                   received_ns=clock.ns, on_outcome=got.append))
    clock.ns += 1_000_000
    cyc.tick()
    return got


def test_decode_supported_modes():
    assert decode_supported_modes(0) == frozenset()
    assert decode_supported_modes(PROFILES["generic"].supported_modes) == {1, 3, 4, 6, 8, 9, 10}
    assert decode_supported_modes((1 << 7) | (1 << 8) | (1 << 4)) == {CSP, CSV}  # bit 4 is reserved


def test_unsupported_mode_rejected_at_once_with_the_reason():
    cyc, clock = _cycle(SimBus(2, [CSP_CSV, "generic"]))
    cyc.open()
    try:
        assert cyc.drives[0].ctrl.supported_modes == {CSP, CSV}
        assert cyc.drives[1].ctrl.supported_modes == {1, 3, 4, 6, 8, 9, 10}
        got = _set_mode(cyc, clock, PT, "m1")
        # answered in the very cycle that applied it; the drive's mode is unchanged
        assert [o.outcome for o in got] == ["rejected"]
        assert "not supported" in got[0].reason and "0x6502" in got[0].reason and "[8, 9]" in got[0].reason
        assert cyc.drives[0].ctrl.mode == CSP
        for _ in range(20):
            clock.ns += 1_000_000
            cyc.tick()
        assert cyc.bus.model(0).inputs().modes_of_operation_display == CSP
        got = _set_mode(cyc, clock, CSV, "m2")
        for _ in range(50):
            if got:
                break
            clock.ns += 1_000_000
            cyc.tick()
        assert [o.outcome for o in got] == ["done"]
    finally:
        cyc.stop(timeout_s=1.0)


def test_drive_without_0x6502_is_tolerated():
    cyc, clock = _cycle(NoModesObject(1))
    cyc.open()
    try:
        assert cyc.drives[0].ctrl.supported_modes is None  # unknown: every mode is tried
        got = _set_mode(cyc, clock, CSV, "m1")
        for _ in range(50):
            if got:
                break
            clock.ns += 1_000_000
            cyc.tick()
        assert [o.outcome for o in got] == ["done"]
    finally:
        cyc.stop(timeout_s=1.0)


def test_configured_mode_not_supported_is_a_startup_error():
    bus = SimBus(1, [CSP_CSV])
    cyc, _clock = _cycle(bus, drives=(DriveConfig(slave=0, mode=PT),))
    with pytest.raises(ConfigError, match=r"axis0.*mode 4 .*not supported.*0x6502"):
        cyc.open()
    assert cyc.state == "error"
