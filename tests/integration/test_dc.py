"""Distributed clocks over pysoem and ``ecat-sim`` (root): SYNC0 started before OP on DC-capable
drives in cyclic synchronous modes, the cycle kept in step (offset reported), and a clear refusal
when DC is off on a drive that requires it. Also the simulated ESC's DC unit without a network."""

from __future__ import annotations

import struct
import threading
import time

import pytest

from bus_agent.bus.base import ALState, BusError
from bus_agent.bus.dc import DcConfig
from bus_agent.bus.mapping import StartupSdo
from bus_agent.config import DriveConfig
from bus_agent.sim.ecat.esc import Esc
from bus_agent.sim.ecat.profiles import as_ecat
from tests.integration.test_real_drives import Agent, _slaves, _wait

pytestmark = [pytest.mark.root, pytest.mark.timeout(120)]


def test_dc_auto_starts_sync0_and_keeps_the_cycle_in_step(ecat_segment):
    ifname, control = ecat_segment(3, "omron1s:dc-required*2,generic")
    agent = Agent(ifname)  # no configuration: [dc] mode = "auto", mode 8 (CSP)
    agent.cycle.start()
    try:
        _wait(lambda: agent.cycle.latest is not None and agent.cycle.latest.stats.cycles >= 500, 20,
              "500 cycles (two statistics windows)")
        slaves = _slaves(control)
        assert [bool(s["dc"] and s["dc"]["sync0"]) for s in slaves] == [True, True, False]
        assert slaves[0]["dc"]["sync0_cycle_ns"] == 1_000_000
        assert [d.dc for d in agent.cycle.latest.drives] == ["sync0", "sync0", "none"]
        assert struct.unpack("<H", agent.bus.sdo_read(0, 0x1C32, 1, 2))[0] == 2  # sync mode: DC SYNC0
        st = agent.cycle.latest.stats
        assert 0.0 < st.dc_offset_p50_us < 1000.0 and st.dc_offset_p99_us < 1000.0
        outs = agent.cmd("enable", "axis0", "axis1", "axis2")
        assert all(o.outcome == "done" for o in outs), outs
        assert all(s["al_state"] == "op" and not s["al_error"] for s in _slaves(control))
    finally:
        agent.cycle.stop()


def _enable_both(agent: Agent) -> None:
    _wait(lambda: agent.cycle.latest is not None and all(d.mode_display == 8 for d in agent.cycle.latest.drives),
          20, "both drives in OP, mode 8 echoed")
    outs = agent.cmd("enable", "axis0", "axis1")
    assert all(o.outcome == "done" for o in outs), outs


def _sync0_phase_ns(slave: dict) -> int:
    dc = slave["dc"]
    return dc["sync0_start_ns"] % dc["sync0_cycle_ns"]


@pytest.mark.parametrize("before_safeop", [False, True])
def test_a_recovered_dc_slave_gets_its_sdos_dc_time_and_sync0_back(ecat_segment, before_safeop):
    """Power cycle (unplug, plug) of a DC-required drive while the others run: its start-up
    SDOs, DC offset and delay, and SYNC0 (at the others' phase) are set again before it returns
    to OP; the agent keeps running, the other drive stays enabled, the recovered one is not
    enabled by itself."""
    ifname, control = ecat_segment(2, "omron1s:dc-required")
    drives = (DriveConfig(slave=0), DriveConfig(slave=1, sdos=(StartupSdo(0x6065, 0, "u32", 4321),)))
    agent = Agent(ifname, drives=drives, dc=DcConfig(before_safeop=before_safeop))
    agent.cycle.start()
    try:
        _enable_both(agent)
        before = _slaves(control)
        assert _sync0_phase_ns(before[0]) == _sync0_phase_ns(before[1])
        assert control.request("unplug", slave=1)["ok"]
        _wait(lambda: agent.drive("axis1").lost, 10, "axis1 lost")
        assert control.request("plug", slave=1)["ok"]
        _wait(lambda: not agent.drive("axis1").lost and agent.drive("axis1").al_state == "op", 30, "axis1 back in OP")
        after = _slaves(control)
        assert [s["al_state"] for s in after] == ["op", "op"] and not after[1]["al_error"]
        assert after[1]["dc"]["sync0"] and not after[1]["dc"]["sync0_late"]
        # its system time reads the other's again (power-on reset it to 0), so SYNC0 is in phase
        assert abs(after[1]["dc"]["system_time_ns"] - after[0]["dc"]["system_time_ns"]) < 2_000_000
        assert abs(_sync0_phase_ns(after[1]) - _sync0_phase_ns(after[0])) < 100_000
        assert struct.unpack("<I", agent.bus.sdo_read(1, 0x6065, 0, 4))[0] == 4321
        assert agent.cycle.state == "running"
        assert agent.drive("axis0").state == "operation_enabled"
        assert agent.drive("axis1").state == "switch_on_disabled"  # never re-enabled by itself
        assert after[1]["drive_state"] == "switch_on_disabled"
    finally:
        agent.cycle.stop()


def test_a_stalled_cycle_is_a_sync_error_the_agent_reports(ecat_segment):
    """The agent's cycle stalls in its exchange (no frame for 50+ SYNC0 periods): the
    DC-required drive raises a sync error (AL 0x001A) before the SM watchdog (100 ms) of either
    drive; the agent marks that drive lost with the code and its hint, the group reacts (quick
    stop of the other member, which stays in OP), and the slave returns to OP, not enabled."""
    ifname, control = ecat_segment(2, "omron1s:dc,omron1s:dc-required")
    agent = Agent(ifname, groups={"arm": ("h1/axis0", "h1/axis1")})
    agent.cycle.start()
    try:
        _enable_both(agent)
        stall, stalled_s = threading.Event(), []
        exchange = agent.bus.exchange

        def stalling_exchange() -> int:
            if stall.is_set():  # the cycle thread stalls until the drive says sync error (at most 95 ms)
                stall.clear()
                t0 = time.monotonic()
                while time.monotonic() - t0 < 0.095 and _slaves(control)[1]["al_status_code"] != 0x001A:
                    time.sleep(0.002)
                stalled_s.append(time.monotonic() - t0)
            return exchange()

        agent.bus.exchange = stalling_exchange  # type: ignore[method-assign]
        stall.set()
        _wait(lambda: any(e.kind == "lost" and e.axis == "axis1" for e in list(agent.events)), 10, "axis1 lost")
        lost = next(e for e in list(agent.events) if e.kind == "lost" and e.axis == "axis1")
        assert lost.error_code == 0x001A and "synchronization error" in lost.detail, lost
        assert stalled_s and stalled_s[0] < 0.095, stalled_s  # the sync error came within the stall
        _wait(lambda: any(e.kind == "reflex" and e.axis == "axis0" for e in list(agent.events)), 5, "group reflex")
        _wait(lambda: _slaves(control)[0]["drive_state"] in ("quick_stop_active", "switch_on_disabled"), 5,
              "axis0 stopped by the group reflex")
        assert not agent.drive("axis0").lost  # its watchdog did not fire: only the sync error
        _wait(lambda: not agent.drive("axis1").lost and agent.drive("axis1").al_state == "op", 20, "axis1 back in OP")
        assert agent.drive("axis1").state != "operation_enabled" and agent.cycle.state == "running"
        assert _slaves(control)[1]["drive_state"] != "operation_enabled"
    finally:
        agent.cycle.stop()


def test_dc_off_on_a_dc_required_drive_is_refused_with_the_al_code(ecat_segment):
    ifname, control = ecat_segment(1, "omron1s:dc-required")
    agent = Agent(ifname, dc=DcConfig(mode="off"))
    # the refusal ends the wait for the AL state at once (it stays until acknowledged), not at the 5 s deadline
    with pytest.raises(BusError, match=r"refused after [0-9.]+ s: slave 0 .*0x0030 invalid DC SYNC configuration "
                                       r".*mode = \"auto\""):
        agent.cycle.open()
    st = _slaves(control)[0]
    assert st["al_state"] == "init" or (st["al_state"] == "safeop" and st["al_status_code"] == 0x0030)


def _reg(esc: Esc, ado: int, data: bytes) -> None:
    assert esc.write(ado, memoryview(bytearray(data)))


def _rd(esc: Esc, ado: int, n: int) -> bytes:
    buf = bytearray(n)
    esc.read(ado, memoryview(buf))
    return bytes(buf)


def test_esc_dc_unit_sync0_and_sync_error():
    esc = Esc(0, as_ecat("generic:dc-required"))
    assert struct.unpack("<H", _rd(esc, 0x0008, 2))[0] & 0x0004
    _reg(esc, 0x0920, struct.pack("<Q", 10**12))  # offset: system time = local + 1000 s
    t = struct.unpack("<Q", _rd(esc, 0x0910, 8))[0]
    assert 10**12 <= t < 10**12 + 60 * 10**9
    # FRMW of a reference 1 s ahead: the (positive) difference shows in 0x092C
    _reg(esc, 0x0910, struct.pack("<Q", struct.unpack("<Q", _rd(esc, 0x0910, 8))[0] + 10**9))
    diff = struct.unpack("<I", _rd(esc, 0x092C, 4))[0]
    assert not diff & 0x80000000 and 5 * 10**8 <= diff <= 10**9
    now = struct.unpack("<Q", _rd(esc, 0x0910, 8))[0]
    _reg(esc, 0x0990, struct.pack("<Q", now - 1))  # a start time already past never fires
    _reg(esc, 0x09A0, struct.pack("<I", 1_000_000))
    _reg(esc, 0x0981, b"\x03")
    assert not esc.dc.sync0_running() and esc.dc.sync0_late
    _reg(esc, 0x0981, b"\x00")
    _reg(esc, 0x0990, struct.pack("<Q", now + 2_000_000))
    _reg(esc, 0x0981, b"\x03")
    _wait(esc.dc.sync0_running, 2, "SYNC0 running after its start time")
    # in OP with SYNC0, DC time stepped by the test (no scheduling in the way)
    esc.al_state = ALState.OP
    esc.model.write(0x6060, 0, 8)
    t = [esc.dc.clock_ns() + 3_000_000]
    esc.dc.clock_ns = lambda: t[0]

    def periods(n: int, outputs_every: int = 1) -> int:
        """n SYNC0 periods, outputs mid-period every ``outputs_every`` (0: none); the periods
        run until the sync error, or n."""
        for k in range(n):
            t[0] += 500_000
            esc.check_sync(0.0)
            if outputs_every and k % outputs_every == 0:
                esc.out_count += 1
            t[0] += 500_000
            esc.check_sync(0.0)
            if esc.al_state != ALState.OP:
                return k + 1
        return n

    assert periods(40) == 40 and esc.sync_error_counter == 0  # in step
    # a 40-period stall: +3 for each but the first (one output may be due in the running period)
    assert periods(40, 0) == 40 and esc.sync_error_counter == 3 * 39
    assert periods(150) == 150 and esc.sync_error_counter == 0  # -1 per period in step again
    n = periods(400, 2)  # a master at half the SYNC0 rate: +3 -1 per two periods
    assert 140 <= n <= 160, n
    assert esc.al_state == ALState.SAFEOP and esc.al_error and esc.al_code == 0x001A


def test_a_power_cycled_reference_clock_holds_the_pi_and_comes_back_in_phase(ecat_segment):
    """The first DC slave is the reference clock: every frame's FRMW reads its system time. While
    it is gone the time in the frames stands still, and after a power cycle it restarts from 0:
    the PI holds on both instead of steering the cycle after a time that is not the slaves'. The
    recovered reference gets its system time back from another DC slave (not 0), SYNC0 in phase,
    and the cycle ends up where it was in the SYNC0 period; the other drive stays enabled."""
    ifname, control = ecat_segment(2, "omron1s:dc-required")
    agent = Agent(ifname)
    agent.cycle.start()
    try:
        _enable_both(agent)
        dcs = agent.cycle.dc.sync
        assert dcs is not None
        _wait(lambda: abs(dcs.error_ns) < 50_000, 20, "the PI settled")
        held0 = dcs.held
        assert control.request("unplug", slave=0)["ok"]
        _wait(lambda: agent.drive("axis0").lost, 10, "axis0 (the reference clock) lost")
        time.sleep(0.5)
        assert dcs.held - held0 >= 300, "the PI steered on a time that stood still"
        assert abs(dcs.integral) * dcs.ki < dcs.max_step_ns  # not wound up
        assert control.request("plug", slave=0)["ok"]
        _wait(lambda: not agent.drive("axis0").lost and agent.drive("axis0").al_state == "op", 30, "axis0 back in OP")
        after = _slaves(control)
        assert abs(after[0]["dc"]["system_time_ns"] - after[1]["dc"]["system_time_ns"]) < 2_000_000
        assert abs(_sync0_phase_ns(after[0]) - _sync0_phase_ns(after[1])) < 100_000
        held1 = dcs.held
        _wait(lambda: dcs.held == held1 and 400_000 <= dcs.offset_ns <= 600_000, 20,
              "the PI steering again, frames mid-period after SYNC0 as before")
        assert agent.drive("axis1").state == "operation_enabled"
        assert agent.drive("axis0").state == "switch_on_disabled"  # never re-enabled by itself
        assert agent.cycle.state == "running"
    finally:
        agent.cycle.stop()
