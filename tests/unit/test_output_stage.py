"""The output stage (bus_agent/motion/output_stage.py), pure: whatever target sequence comes in,
the targets written keep the axis limits (up to count rounding); a constant target is reached and
held; a path within the limits passes unchanged and uncounted; anything else is counted."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bus_agent.motion.output_stage import MODE_CSP, MODE_CSV, ROUND_CHANGE, ROUND_STEP, OutputStage
from bus_agent.motion.planner import Kinematic, Limits, plan_position, plan_velocity

T = 0.001
VMAX, AMAX = 100_000.0, 1_000_000.0          # 100 counts per cycle, 1 count per cycle^2


def stage() -> OutputStage:
    return OutputStage(VMAX, AMAX, T)


def assert_within_limits(written: list[int], vmax: float = VMAX, amax: float = AMAX) -> None:
    step_max, change_max = vmax * T + ROUND_STEP, amax * T * T + ROUND_CHANGE
    for k in range(2, len(written)):
        s1, s0 = written[k] - written[k - 1], written[k - 1] - written[k - 2]
        assert abs(s1) <= step_max, f"cycle {k}: step {s1}"
        assert abs(s1 - s0) <= change_max, f"cycle {k}: change of step {s1 - s0}"


def cycles_to_reach(distance: float, vmax: float = VMAX, amax: float = AMAX) -> int:
    """A generous bound on the cycles the stage needs from any state within the limits to a
    constant target ``distance`` away: stop, travel, stop again."""
    s, d = vmax * T, amax * T * T
    return int(3 * s / d + abs(distance) / s + 2 * math.sqrt(abs(distance) / d) + 50)


# targets: small steps (a stream), medium steps, jumps, and holds
moves = st.lists(st.one_of(st.integers(-150, 150), st.integers(-3000, 3000), st.integers(-10**6, 10**6),
                           st.just(0)), min_size=1, max_size=120)


@settings(max_examples=200, deadline=None)
@given(moves, st.integers(-200_000, 200_000))
def test_property_any_target_sequence_reaches_the_wire_within_the_limits_and_converges(deltas, final):
    s = stage()
    written, x = [0, 0], 0
    for dx in deltas:
        x += dx
        s.step(MODE_CSP, x, 0)
        written.append(s.position)
    for _ in range(cycles_to_reach(final - s.position)):
        s.step(MODE_CSP, final, 0)
        written.append(s.position)
    assert_within_limits(written)
    assert s.position == final and s.settled
    for _ in range(20):  # and stays there
        s.step(MODE_CSP, final, 0)
        written.append(s.position)
    assert written[-21:] == [final] * 21


@settings(max_examples=100, deadline=None)
@given(st.integers(-90, 90), st.integers(-20_000, 20_000))
def test_property_a_moving_target_slower_than_the_limit_is_caught_up(rate, offset):
    """A target moving at a constant rate below the velocity limit, the stage starting behind it
    (a producer that jumped): it catches up, then writes the target as given."""
    s = stage()
    written = [0, 0]
    for k in range(20_000):
        s.step(MODE_CSP, offset + rate * k, 0)
        written.append(s.position)
        if s.settled and s.position == offset + rate * k and k > 10:
            break
    assert_within_limits(written)
    assert s.settled and s.position == offset + rate * k, (k, s.position)


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([100_000.0, 33_333.3, 7_500.0]), st.sampled_from([1e6, 3e5, 2e7]),
       st.sampled_from([2e7, 1e9]), st.integers(-10**6, 10**6), st.integers(-60_000, 60_000))
def test_property_a_planned_path_passes_unchanged_and_uncounted(vmax, amax, jerk, start, distance):
    """The planner's profiles (ruckig, rounded to counts) keep the limits: the stage writes them
    as they are and counts nothing; so does a CSV velocity ramp."""
    lim = Limits(vmax, amax, jerk)
    s = OutputStage(vmax, amax, T)
    s.step(0, start, 0)  # not enabled yet: follows the actual position
    plan = plan_position(Kinematic(float(start)), float(start + distance), lim)
    for k in range(int(plan.duration / T) + 5):
        x = int(round(plan.sample((k + 1) * T)[0]))
        s.step(MODE_CSP, x, 0)
        assert s.position == x
    v = OutputStage(vmax, amax, T)
    jog = plan_velocity(Kinematic(0.0), math.copysign(vmax, distance or 1), lim)
    for k in range(int(jog.duration / T) + 5):
        w = int(round(jog.sample((k + 1) * T)[1]))
        v.step(MODE_CSV, 0, w)
        assert v.velocity == w
    assert s.clamps == 0 and v.clamps == 0 and s.settled and v.settled


def test_the_rounding_allowance_does_not_accumulate():
    """A stream that accelerates at 3 counts per cycle^2 (each step inside the per-cycle rounding
    allowance of a 1 count/cycle^2 axis) is limited within a few cycles."""
    s = stage()
    x, step = 0, 0
    for _ in range(10):
        step += 3
        x += step
        s.step(MODE_CSP, x, 0)
    assert s.clamps > 0 and s.position < x


def test_follow_never_limits_nor_counts_and_limiting_resumes_from_there():
    """Not in Operation enabled (mode 0): the targets follow the actual position, however far it
    moves; enabling then starts from it, at rest, without a jump."""
    s = stage()
    for x in (0, 500_000, -3, 12_345):
        s.step(0, x, 777)
        assert (s.position, s.velocity) == (x, 777)
    assert s.clamps == 0
    s.step(MODE_CSP, 12_345, 0)
    assert s.position == 12_345 and s.clamps == 0
    s.step(MODE_CSP, 22_345, 0)  # a jump after enable is limited: from rest, 1 count
    assert s.position - 12_345 <= 1 + ROUND_STEP and s.clamps == 1


@pytest.mark.parametrize("target", [150_000, -90_000, 40])
def test_csv_velocity_is_limited_in_magnitude_and_change(target):
    s = stage()
    written = []
    for _ in range(300):
        s.step(MODE_CSV, 0, target)
        written.append(s.velocity)
    assert all(abs(v) <= VMAX for v in written)
    assert all(abs(b - a) <= AMAX * T + 1 for a, b in zip([0] + written, written))
    assert written[-1] == max(-VMAX, min(VMAX, target))
    assert (s.clamps > 0) is (abs(target) > AMAX * T + 0.5)


def test_limits_must_be_positive():
    with pytest.raises(ValueError, match="output stage limits must be > 0"):
        OutputStage(0.0, AMAX, T)
