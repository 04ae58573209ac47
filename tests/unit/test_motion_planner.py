"""The pure planner (bus_agent.motion.planner): ruckig profiles within their limits, from any
start state, ending at rest on the target; groups that arrive together."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bus_agent.motion.planner import Kinematic, Limits, PlanError, hold, plan_group, plan_position, plan_stop, plan_velocity

DT = 0.001
positions = st.floats(-2e9, 2e9)
velocities = st.floats(1e3, 2e6)
accels = st.floats(1e3, 2e7)
jerks = st.floats(1e4, 5e8)


def _samples(plan, n_max=2000):
    """Samples every cycle (1 ms), or n_max evenly spread for long plans."""
    dt = max(DT, plan.duration / n_max)
    n = int(math.ceil(plan.duration / dt)) + 2
    return [plan.sample(k * dt) for k in range(n)]


@settings(max_examples=60, deadline=None)
@given(p0=positions, target=positions, v=velocities, a=accels, j=jerks, v0_frac=st.floats(-1, 1))
def test_position_plans_stay_within_limits_and_end_at_rest_on_target(p0, target, v, a, j, v0_frac):
    lim = Limits(v, a, j)
    start = Kinematic(p0, v0_frac * v)
    plan = plan_position(start, target, lim)
    pts = _samples(plan)
    assert pts[0][0] == pytest.approx(p0)
    for p, vel, acc in pts:
        assert abs(vel) <= v * (1 + 1e-6) + 1e-6
        assert abs(acc) <= a * (1 + 1e-6) + 1e-6
    end = plan.sample(plan.duration + 1.0)
    assert end[0] == pytest.approx(target, rel=1e-9, abs=1e-3)
    assert end[1] == pytest.approx(0.0, abs=1e-6 * v)


@settings(max_examples=40, deadline=None)
@given(p0=positions, v0=st.floats(-2e6, 2e6), v=velocities, a=accels, j=jerks)
def test_stop_plans_come_to_rest_without_velocity_reversal(p0, v0, v, a, j):
    lim = Limits(max(v, abs(v0)), a, j)
    plan = plan_stop(Kinematic(p0, v0), lim)
    pts = _samples(plan)
    for _, vel, _ in pts:
        assert vel * v0 >= -1e-6 * max(1.0, abs(v0))  # never backwards
    assert plan.sample(plan.duration + 1)[1] == pytest.approx(0.0, abs=1e-6 * max(1.0, abs(v0)))


def test_velocity_plan_keeps_its_velocity_after_the_ramp():
    plan = plan_velocity(Kinematic(0.0), 5000.0, Limits(10_000, 100_000, 1e7))
    p1, v1, _ = plan.sample(plan.duration + 1.0)
    p2, v2, _ = plan.sample(plan.duration + 2.0)
    assert v1 == v2 == pytest.approx(5000.0)
    assert p2 - p1 == pytest.approx(5000.0)


def test_group_plans_arrive_together_with_each_axis_in_its_own_limits():
    starts = [Kinematic(0.0), Kinematic(1000.0), Kinematic(-5e5), Kinematic(0.0, 2000.0)]
    targets = [100_000.0, 1000.0 + 10.0, 5e5, -20_000.0]
    limits = [Limits(1e5, 1e6, 2e7), Limits(1e3, 1e4, 1e6), Limits(5e5, 1e6, 2e7), Limits(3e4, 1e5, 1e6)]
    plans = plan_group(starts, targets, limits)
    durations = {round(p.duration, 9) for p in plans}
    assert len(durations) == 1
    for plan, lim, t in zip(plans, limits, targets):
        for _, vel, acc in _samples(plan):
            assert abs(vel) <= lim.velocity * (1 + 1e-6) and abs(acc) <= lim.acceleration * (1 + 1e-6)
        assert plan.sample(plan.duration)[0] == pytest.approx(t, abs=1e-3)
    longer = plan_group(starts, targets, limits, min_duration_s=plans[0].duration + 1.0)
    assert all(p.duration == pytest.approx(plans[0].duration + 1.0) for p in longer)


def test_bad_limits_and_targets_raise_plan_error():
    with pytest.raises(PlanError, match="velocity limit"):
        plan_position(Kinematic(0.0), 1.0, Limits(0.0, 1.0, 1.0))
    with pytest.raises(PlanError, match="not a finite"):
        plan_position(Kinematic(0.0), math.inf, Limits(1.0, 1.0, 1.0))
    assert hold(5.0).sample(10.0) == (5.0, 0.0, 0.0)
