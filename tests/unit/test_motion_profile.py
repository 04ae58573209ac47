"""Drive-generated profiles: the Profile Position set-point handshake (pure stepper, the
simulated drive, the agent's cycle over SimBus) with acknowledge stuck high, slow acknowledge, a
target changed mid-move and every abort path; Profile Velocity jogs."""

from __future__ import annotations

import dataclasses

import pytest

from bus_agent.motion.config import MotionConfig
from bus_agent.motion.profile import CW_CHANGE_IMMEDIATELY, CW_NEW_SETPOINT, ProfileRun, stop_position
from tests.unit.motion_rig import Rig

CFG = MotionConfig(max_velocity=100_000, max_acceleration=1_000_000, min_position=-1_000_000, max_position=1_000_000)
ACK, REACHED, FOLLOWING = 1 << 12, 1 << 10, 1 << 13
OE = 0x0237


def run(**kw) -> ProfileRun:
    return ProfileRun("pp", target=kw.pop("target", 1000.0), now_s=0.0, deadline_s=kw.pop("deadline_s", 1.0),
                      position_window=10, velocity_window=100, **kw)


# ---- the pure stepper --------------------------------------------------------------------------------

def test_handshake_target_and_bit_4_together_then_bit_4_falls_on_the_ack_edge():
    r = run()
    s = r.step(0.0, OE, 0, 0)
    assert s.controlword_bits == CW_NEW_SETPOINT | CW_CHANGE_IMMEDIATELY and r.phase == "ack"
    assert r.step(0.001, OE, 0, 0).controlword_bits & CW_NEW_SETPOINT  # slow acknowledge: bit 4 held
    assert r.step(0.002, OE | ACK, 0, 0).controlword_bits == 0 and r.phase == "moving"
    assert not r.step(0.003, OE | REACHED, 500, 0).outcome  # reached bit stale: not in the window
    assert r.step(0.5, OE | REACHED, 995, 20).outcome == "done"


def test_acknowledge_high_at_the_start_is_waited_out_never_assumed_low():
    r = run()
    for k in range(5):
        assert r.step(k * 0.001, OE | ACK, 0, 0).controlword_bits == 0  # no edge while the ack is high
    assert r.step(0.006, OE, 0, 0).controlword_bits & CW_NEW_SETPOINT


def test_acknowledge_stuck_high_times_out_naming_it_and_sends_nothing():
    r = run(deadline_s=0.05)
    steps = [r.step(k * 0.001, OE | ACK, 0, 0) for k in range(60)]
    assert all(s.controlword_bits == 0 for s in steps)
    end = next(s for s in steps if s.outcome)
    assert end.outcome == "timeout" and "stuck high" in end.reason and "bit 12" in end.reason


def test_following_error_bit_13_fails_and_parameters_refused_fail():
    r = run()
    r.step(0.0, OE, 0, 0)
    r.step(0.001, OE | ACK, 0, 0)
    end = r.step(0.002, OE | FOLLOWING, 0, 0)
    assert end.outcome == "failed" and "bit 13" in end.reason
    r = run(sdo_writes=((0x6081, 0, b"\0\0\0\0"),))
    assert r.phase == "params" and r.step(0.0, OE, 0, 0).controlword_bits == 0
    assert "0x6081" in r.sdo_done("0x6081:0: SDO abort 0x06090030")


def test_stop_position_is_where_the_deceleration_ends():
    assert stop_position(1000, 2000, 1000) == 3000
    assert stop_position(1000, -2000, 1000) == -1000
    assert stop_position(5, 0, 1000) == 5


# ---- the simulated drive's handshake, through the cycle ---------------------------------------------

def rig(mode: int = 1, cfg: MotionConfig = CFG) -> Rig:
    r = Rig(1, motion=cfg, mode=mode)
    r.tick(5)
    r.enable()
    return r


def test_pp_move_writes_the_profile_and_the_drive_follows_it():
    r = rig()
    got = r.do("move", "axis0", {"to": 30_000, "velocity": 40_000, "accel": 200_000})
    assert got[0].outcome == "done", got
    m = r.model(0)
    assert (m.read(0x6081, 0), m.read(0x6083, 0), m.read(0x6084, 0)) == (40_000, 200_000, 200_000)
    assert r.status().position == 30_000 and r.status().axis_state == "standstill"
    speeds = [abs(b[3] - a[3]) for a, b in zip(r.wire[0].rows, r.wire[0].rows[1:])]
    assert max(speeds) <= 40_000 * 0.001 + 1  # counts per cycle
    # bit 4 rose once, with 0x607A already the target in that same cycle
    edges = [k for k in range(1, len(r.wire[0].rows)) if r.wire[0].rows[k][5] & 0x10 and not r.wire[0].rows[k - 1][5] & 0x10]
    assert len(edges) == 1 and r.wire[0].rows[edges[0]][1] == 30_000
    got = r.do("move", "axis0", {"by": -5_000})
    assert got[0].outcome == "done" and r.status().position == 25_000


def test_target_changed_mid_move_aborts_the_first_and_reaches_the_second():
    r = rig()
    first = r.send("move", "axis0", {"to": 200_000})
    r.tick(300)
    second = r.send("move", "axis0", {"to": -20_000})
    r.run_until(lambda: first and second)
    assert first[0].outcome == "aborted" and "aborted by" in first[0].reason
    assert second[0].outcome == "done" and r.status().position == -20_000


def test_slow_and_stuck_acknowledge_through_the_cycle():
    r = rig()
    r.model(0).pp_ack_delay_steps = 25
    got = r.do("move", "axis0", {"to": 2_000})
    assert got[0].outcome == "done" and r.status().position == 2_000
    r.model(0).pp_ack_delay_steps = 0
    r.model(0).pp_ack_stuck = True
    assert r.do("move", "axis0", {"to": 3_000})[0].outcome == "done"  # acknowledged, then stays high
    got = r.do("move", "axis0", {"to": 9_000}, timeout_s=0.5)
    assert got[0].outcome == "timeout" and "stuck high" in got[0].reason
    assert r.status().position == 3_000  # nothing was sent


@pytest.mark.parametrize("how, outcome, words", [
    ("stop", "aborted", "stop"), ("quick_stop", "aborted", "quick_stop"), ("fault", "failed", "drive fault 0x2310"),
    ("halt", "aborted", "halt"),
])
def test_pp_abort_paths_end_once_and_the_axis_comes_to_rest(how, outcome, words):
    r = rig()
    move = r.send("move", "axis0", {"to": 500_000})
    r.tick(300)
    if how == "fault":
        r.model(0).inject_fault(0x2310)
    elif how == "halt":
        r.send("halt", "axis0", {"on": True})
    else:
        r.send(how, "axis0")
    r.run_until(lambda: move)
    r.tick(1500)
    assert len(move) == 1 and move[0].outcome == outcome and words in move[0].reason, move
    assert r.model(0).velocity == 0
    if how == "stop":
        assert r.status().axis_state == "stopping" and r.status().position < 500_000
        r.do("stop", "axis0", {"release": True})
        r.tick(300)
        assert r.model(0).velocity == 0  # nothing resumes the old set-point


def test_pp_rejections_software_limit_and_synchronized():
    r = rig()
    got = r.do("move", "axis0", {"to": 2_000_000})
    assert got[0].outcome == "rejected" and "max_position" in got[0].reason
    got = r.do("move", "axis0", {"to": 10, "sync": True})
    assert got[0].outcome == "rejected" and "cyclic synchronous position" in got[0].reason


# ---- Profile Velocity jog ------------------------------------------------------------------------

def test_pv_jog_runs_stops_at_the_software_limit_and_leaves_no_stale_velocity():
    r = rig(mode=3, cfg=dataclasses.replace(CFG, max_position=60_000))
    got = r.do("jog", "axis0", {"velocity": 20_000, "for_s": 0.5})
    assert got[0].outcome == "done" and 8_000 < r.status().position < 14_000
    assert r.model(0).read(0x60FF, 0) == 0
    got = r.do("jog", "axis0", {"velocity": 50_000}, timeout_s=20)
    assert got[0].outcome == "aborted" and "max_position" in got[0].reason
    r.tick(5)  # done within the velocity window; at rest a few cycles later
    assert r.status().position <= 60_000 and r.model(0).velocity == 0
    jog = r.send("jog", "axis0", {"velocity": -30_000}, timeout_s=20)
    r.tick(200)
    r.model(0).inject_fault(0x2310)
    r.run_until(lambda: jog)
    assert jog[0].outcome == "failed"
    r.tick(5)
    assert r.model(0).read(0x60FF, 0) == 0  # a re-enable cannot start it moving
    got = r.do("move", "axis0", {"to": 0})
    assert got[0].outcome == "rejected"
