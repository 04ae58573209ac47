"""Homing in mode 6: the standard's status table (every statusword), the pure stepper, the
simulated drive's homing methods, and the agent's cycle over SimBus (parameters by SDO, mode 6
confirmed, bit 4, the previous mode restored, homed, every end: done, failed, timeout, aborted,
rejected)."""

from __future__ import annotations

import dataclasses

import pytest

from bus_agent.bus.pdo import DriveOutputs
from bus_agent.motion.config import HomingConfig, MotionConfig
from bus_agent.motion.homing import (
    HOMING_STATUS,
    STALE_CYCLES,
    Homing,
    HomingStatus,
    decode_homing_status,
)
from bus_agent.sim.drive_model import PROFILES, DriveModel
from bus_agent.sim.homing_model import SEARCH_LIMIT
from tests.unit.motion_rig import Rig
from tests.unit.test_motion_cycle import check_wire

HOME = HomingConfig(method=19, switch_speed=20_000, zero_speed=2_000, acceleration=400_000, offset=100)
CFG = MotionConfig(homing=HOME)


# ---- the table ------------------------------------------------------------------------------------

def test_every_statusword_decodes_by_bits_13_12_10_only():
    expected = {0x0000: "in progress", 0x0400: "interrupted or not started", 0x1000: "attained, target not reached",
                0x1400: "completed", 0x2000: "error, velocity not 0", 0x2400: "error, velocity 0"}
    for sw in range(0x10000):
        st = decode_homing_status(sw)
        assert st is HOMING_STATUS[sw & 0x3400]
        if sw & 0x3400 in expected:
            assert st.value == expected[sw & 0x3400]
        else:
            assert st is HomingStatus.RESERVED


# ---- the stepper (pure) ---------------------------------------------------------------------------

def _run(h: Homing, statuses: list[int], mode: int = 6, t0: float = 0.0):
    steps = []
    for k, sw in enumerate(statuses):
        steps.append(h.step(t0 + k * 0.001, 0x0237 | sw, mode, True))
    return steps


def _to_running(h: Homing) -> None:
    h.sdo_done("")
    assert h.step(0.0, 0x0637, 8, True).request_mode == 6
    s = h.step(0.001, 0x0637, 6, True)
    assert s.start_bit and h.phase == "running"


def _restore(h: Homing, previous: int = 8):
    s = h.step(1.0, 0x0237, 6, True)
    assert s.request_mode == previous and not s.start_bit and not s.outcome
    return h.step(1.001, 0x0237, previous, True)


def test_stepper_runs_params_mode_start_then_restores_and_replies_done():
    h = Homing(HOME, 19, 8, 0.0, 10.0)
    assert [w[0] for w in h.sdo_writes] == [0x6098, 0x6099, 0x6099, 0x609A, 0x607C]
    assert h.step(0.0, 0x0237, 8, True).start_bit is False and h.phase == "params"
    _to_running(h)
    steps = _run(h, [0x0400, 0x0000, 0x0000, 0x1000, 0x1400])
    assert all(s.start_bit for s in steps[:-1]) and not steps[-1].start_bit
    end = _restore(h)
    assert end.outcome == "done" and "method 19" in end.reason and h.homed


def test_stale_completed_from_a_previous_run_is_not_taken_for_this_one():
    h = Homing(HOME, 19, 8, 0.0, 10.0)
    h.sdo_done("")
    h.step(0.0, 0x1637, 8, True)
    h.step(0.001, 0x1637, 6, True)  # completed before the edge (a previous run)
    steps = _run(h, [0x1400] * (STALE_CYCLES - 1))
    assert all(s.start_bit for s in steps) and h.phase == "running"
    _run(h, [0x0000, 0x1400])
    assert _restore(h).outcome == "done"


def test_current_position_method_completing_at_once_counts_after_the_stale_window():
    h = Homing(HOME, 37, 8, 0.0, 10.0)
    h.sdo_done("")
    h.step(0.0, 0x1637, 8, True)
    h.step(0.001, 0x1637, 6, True)
    _run(h, [0x1400] * STALE_CYCLES)
    assert _restore(h).outcome == "done"


@pytest.mark.parametrize("sw, words", [(0x2000, "error, velocity not 0"), (0x2400, "error, velocity 0"),
                                       (0x3400, "reserved")])
def test_homing_error_fails_naming_the_status(sw, words):
    h = Homing(HOME, 19, 8, 0.0, 10.0)
    _to_running(h)
    _run(h, [0x0000, sw])
    end = _restore(h)
    assert end.outcome == "failed" and words in end.reason and not h.homed


def test_interrupted_after_it_started_fails_but_not_started_waits():
    h = Homing(HOME, 19, 8, 0.0, 10.0)
    _to_running(h)
    steps = _run(h, [0x0400, 0x0400])  # not started yet: the drive has not seen the edge
    assert all(s.start_bit for s in steps) and h.phase == "running"
    _run(h, [0x0000, 0x0400])
    end = _restore(h)
    assert end.outcome == "failed" and "interrupted" in end.reason


def test_deadline_ends_in_timeout_naming_the_phase_and_sdo_refusal_fails():
    h = Homing(dataclasses.replace(HOME, timeout_s=0.5), 19, 8, 0.0, 10.0)
    _to_running(h)
    _run(h, [0x0000] * 3)
    assert h.step(0.6, 0x0237, 6, True).request_mode == 8
    end = h.step(0.601, 0x0237, 8, True)
    assert end.outcome == "timeout" and "deadline" in end.reason and "in progress" in end.reason
    h = Homing(HOME, 19, 9, 0.0, 10.0)
    h.sdo_done("0x6098:0: SDO abort 0x06090030")
    end = _restore(h, previous=9)
    assert end.outcome == "failed" and "0x6098" in end.reason


# ---- the simulated drive ---------------------------------------------------------------------------

def _enabled_model(method: int, offset: int = 0, switch: int | None = 5_000) -> DriveModel:
    m = DriveModel(PROFILES["generic"])
    m.home_switch_position = switch
    m.write(0x6098, 0, method)
    m.write(0x607C, 0, offset)
    m.write(0x6099, 1, 20_000)
    m.write(0x6099, 2, 2_000)
    for cw, n in ((0x06, 5), (0x07, 2), (0x0F, 3)):
        _drive(m, cw, n)
    assert m.read(0x6061, 0) == 6 and m.state.value == "operation_enabled"
    return m


def _drive(m: DriveModel, cw: int, n: int) -> list[int]:
    seen = []
    for _ in range(n):
        m.apply_outputs(DriveOutputs(controlword=cw, modes_of_operation=6))
        m.step(0.001)
        seen.append(m.statusword & 0x3400)
    return seen


@pytest.mark.parametrize("method, edge_dir", [(19, -1), (20, +1)])
def test_model_switch_methods_find_the_edge_and_latch_the_offset(method, edge_dir):
    m = _enabled_model(method, offset=100)
    assert _drive(m, 0x0F, 1) == [0x0400]  # not started
    seen = _drive(m, 0x1F, 3000)
    assert seen[-1] == 0x1400 and 0x0000 in seen and 0x1000 in seen
    assert abs(m.position - 100) < 50 and m.velocity == 0
    assert m.read(0x60FD, 0) & 0x4 == (0x4 if m.position >= 5_000 else 0)


def test_model_current_position_method_and_unknown_method_and_no_switch():
    m = _enabled_model(37, offset=-7)
    assert _drive(m, 0x1F, 2)[-1] == 0x1400 and m.position == -7
    m = _enabled_model(1)
    assert _drive(m, 0x1F, 2)[-1] == 0x2400  # a method the simulated drive does not perform
    m = _enabled_model(19, switch=None)
    seen = _drive(m, 0x1F, int(SEARCH_LIMIT / 20_000 * 1000) + 500)
    assert 0x2000 in seen and seen[-1] == 0x2400


def test_model_bit_4_falling_interrupts():
    m = _enabled_model(19)
    _drive(m, 0x1F, 100)
    assert _drive(m, 0x0F, 200)[-1] == 0x0400 and m.velocity == 0


# ---- the agent's cycle over SimBus ------------------------------------------------------------------

def rig(cfg: MotionConfig = CFG, **kw) -> Rig:
    r = Rig(1, motion=cfg, **kw)
    r.tick(5)
    r.enable()
    return r


def test_home_switch_method_done_homed_offset_mode_restored_no_jump():
    r = rig(dataclasses.replace(CFG, require_homing=True))
    assert r.do("move", "axis0", {"to": 10})[0].reason.startswith("not homed")
    got = r.send("home", "axis0", timeout_s=10)
    r.tick(30)
    st = r.status()
    assert st.axis_state == "homing" and st.motion_request_id.endswith("home") and st.mode_display == 6
    assert r.model(0).read(0x6098, 0) == 19 and r.model(0).read(0x607C, 0) == 100
    assert r.model(0).read(0x6099, 1) == 20_000 and r.model(0).read(0x609A, 0) == 400_000
    r.run_until(lambda: got)
    assert got[0].outcome == "done" and "method 19" in got[0].reason
    st = r.status()
    assert st.homed and st.mode_display == 8 and st.axis_state == "standstill" and abs(st.position - 100) < 50
    # 0x607A followed the actual position throughout homing (a cycle behind: only the latch of
    # the home offset shows), so nothing jumps when CSP comes back ...
    assert len([1 for (_, t, _, p, _, _) in r.wire[0].rows if abs(t - p) > 60]) == 1
    homed_at = len(r.wire[0].rows)
    assert r.do("move", "axis0", {"to": 1_000})[0].outcome == "done"
    assert r.status().position == 1_000
    # ... and the move after it starts from there within the limits
    del r.wire[0].rows[:homed_at - 2]
    check_wire(r)


def test_home_method_from_the_command_and_bad_method_rejected_naming_it():
    r = rig()
    got = r.do("home", "axis0", {"method": 37})
    assert got[0].outcome == "done" and r.status().position == 100 and r.model(0).read(0x6098, 0) == 37
    got = r.do("home", "axis0", {"method": 99})
    assert got[0].outcome == "rejected" and "homing method 99" in got[0].reason and "0x6098" in got[0].reason
    assert r.model(0).read(0x6098, 0) == 37


def test_fault_during_homing_fails_and_restores_the_mode():
    r = rig()
    got = r.send("home", "axis0", timeout_s=10)
    r.tick(100)
    r.model(0).inject_fault(0x2310)
    r.run_until(lambda: got)
    assert got[0].outcome == "failed" and "drive fault 0x2310" in got[0].reason
    st = r.status()
    assert not st.homed and st.mode_display == 8 and st.axis_state == "error_stop"


def test_homing_error_from_the_drive_fails_and_timeout_is_reported():
    r = rig()
    r.model(0).home_switch_position = None  # no switch: the drive gives up (error)
    got = r.do("home", "axis0", timeout_s=30)
    assert got[0].outcome == "failed" and "homing error" in got[0].reason and not r.status().homed
    r = rig(dataclasses.replace(CFG, homing=dataclasses.replace(HOME, timeout_s=0.2)))
    got = r.do("home", "axis0", timeout_s=10)
    assert got[0].outcome == "timeout" and "deadline" in got[0].reason and r.status().mode_display == 8


def test_stop_and_quick_stop_abort_homing_and_moves_wait_for_it():
    r = rig()
    got = r.send("home", "axis0", timeout_s=10)
    r.tick(100)
    move = r.do("move", "axis0", {"to": 5})
    assert move[0].outcome == "rejected" and "homing in progress" in move[0].reason
    mode = r.do("set_mode", "axis0", {"mode": 9})
    assert mode[0].outcome == "rejected" and "homing" in mode[0].reason
    stop = r.do("stop", "axis0")
    r.run_until(lambda: got)
    assert got[0].outcome == "aborted" and "stop" in got[0].reason and stop[0].outcome == "done"
    assert r.status().mode_display == 8 and r.status().axis_state == "stopping"
    r.do("stop", "axis0", {"release": True})
    got = r.send("home", "axis0", timeout_s=10)
    r.tick(100)
    r.send("quick_stop", "axis0")
    r.run_until(lambda: got)
    assert got[0].outcome == "aborted" and "quick_stop (r" in got[0].reason


def test_home_rejected_when_the_drive_lacks_mode_6():
    no_homing = dataclasses.replace(PROFILES["generic"], name="csp_only", supported_modes=(1 << 7) | (1 << 8))
    r = rig(profile=no_homing)
    got = r.do("home", "axis0")
    assert got[0].outcome == "rejected" and "mode 6" in got[0].reason and "0x6502" in got[0].reason
