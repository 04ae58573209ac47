"""AxisMotion's parts on their own: AxisLimits (what a command may ask) and DriveRuns (the
drive's own profiles), and the simulated drive's Profile Position sub-model."""

from __future__ import annotations

import pytest

from bus_agent.motion.axis_limits import AxisLimits
from bus_agent.motion.config import MotionConfig
from bus_agent.motion.drive_runs import DriveRuns
from bus_agent.motion.planner import Limits
from bus_agent.motion.records import Rejected
from bus_agent.sim.profile_model import SimProfilePosition, ramp


def test_requested_limits_clamp_or_reject_in_user_units() -> None:
    cfg = MotionConfig(max_velocity=100.0, counts_per_unit=10.0, unit="mm", min_position=-50.0, max_position=50.0)
    b = AxisLimits(cfg, 0.001)
    notes: list[str] = []
    assert b.requested({"velocity": 50.0}, notes).velocity == 500.0 and notes == []
    with pytest.raises(Rejected, match="exceeds the axis velocity limit 100"):
        b.requested({"velocity": 150.0}, notes)
    clamp = AxisLimits(MotionConfig(max_velocity=100.0, limit_policy="clamp"), 0.001)
    assert clamp.requested({"velocity": 150.0}, notes).velocity == 100.0 and "clamped" in notes[0]
    with pytest.raises(Rejected, match="beyond the software limit max_position 50"):
        b.check_target(501.0)
    assert b.limit_ahead(0.0, 10.0) == "" and b.limit_ahead(499.0, 100.0) == "max_position 50"


def test_jog_end_defaults_to_the_deadline_less_the_stop_and_refuses_what_cannot_stop() -> None:
    assert AxisLimits.jog_end({}, 0.0, 10.0, 1.0) == pytest.approx(8.95)
    assert AxisLimits.jog_end({"for_s": 2.0}, 1.0, 10.0, 1.0) == 3.0
    with pytest.raises(Rejected, match="cannot stop within"):
        AxisLimits.jog_end({"for_s": 9.5}, 0.0, 10.0, 1.0)


def test_drive_runs_write_the_profile_once_and_stop_a_pp_run_at_rest() -> None:
    cfg = MotionConfig().in_counts()
    runs = DriveRuns(cfg, 1000.0)
    first = runs.start_profile("pp", 0.0, 5.0, Limits(100.0, 1000.0, 1e6), target=500.0)
    assert first and runs.start_profile("pp", 0.0, 5.0, Limits(100.0, 1000.0, 1e6), target=500.0) == ()
    assert runs.sdo_written("") is None and runs.profile_run is not None
    runs.stop_profile(1.0, enabled=True, position=0, velocity=100)
    assert runs.profile_run is not None and not runs.profile_run.replies and runs.profile_run.target == 5.0
    runs.stop_profile(1.0, enabled=False, position=0, velocity=0)
    assert runs.profile_run is None and not runs.abort_homing("aborted", "x")


def test_sim_profile_position_takes_the_setpoint_on_the_edge_and_arrives() -> None:
    assert ramp(0.0, 10.0, 100.0, 200.0, 0.01) == 1.0 and ramp(10.0, 0.0, 100.0, 200.0, 0.01) == 8.0
    pp = SimProfilePosition()
    kw = dict(profile_velocity=1000.0, vmax=1000.0, accel=10_000.0, decel=10_000.0, dt=0.001,
              within_limits=lambda t: t, ack_delay_steps=0, ack_stuck=False)
    v, reached = pp.step(0x0F, 100, 0.0, 0.0, **kw)
    assert pp.target is None and not reached and v == 0.0
    pos, vel = 0.0, 0.0
    for _ in range(2000):
        vel, reached = pp.step(0x1F, 100, pos, vel, **kw)
        pos += vel * 0.001
        if reached:
            break
    assert pp.ack and pp.target == 100.0 and reached and abs(pos - 100.0) < 0.5
    pp.step(0x0F, 100, pos, 0.0, **kw)
    assert not pp.ack
