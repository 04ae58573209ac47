"""The PI that keeps the cycle in step with SYNC0 (bus_agent.bus.dc.DcSync), against a model
of the segment: the frame passes the reference clock ``latency`` after the master's wake-up,
SYNC0 fires every cycle from 0, and the master's clock may drift against DC time."""

from __future__ import annotations

import random

import pytest

from bus_agent.bus.dc import DcSync, phase_ns

CYCLE = 1_000_000


def _run(pi: DcSync, cycles: int, start_ns: int = 123_456, latency=lambda k: 40_000, late=lambda k: 0,
         drift_ppm: float = 0.0, stepped: list[int] | None = None) -> tuple[list[int], list[int]]:
    """The cycle's schedule t0 + k * cycle + adjust, as Cycle._run keeps it. Returns the frame
    phases and the corrections."""
    adjust, phases, steps = 0, [], []
    last_wake = None
    for k in range(cycles):
        wake = start_ns + k * CYCLE + adjust + late(k)
        if last_wake is not None and wake <= last_wake:
            continue  # a slot already passed during a stall: the loop skips it
        last_wake = wake
        if stepped is not None:
            stepped.append(k)
        dc_time = int((wake + latency(k)) * (1 + drift_ppm * 1e-6))
        step = pi.step(dc_time, late(k))
        phases.append(pi.offset_ns)
        steps.append(step)
        adjust += step
    return phases, steps


def test_frames_settle_at_the_target_phase_and_each_correction_is_small():
    pi = DcSync(CYCLE)
    phases, steps = _run(pi, 3000)
    assert all(abs(p - CYCLE // 2) < 5_000 for p in phases[-500:]), phases[-5:]
    assert max(abs(s) for s in steps) <= CYCLE // 100  # a correction moves one period by at most 1 %


def test_a_drifting_master_clock_is_followed_by_the_integral():
    pi = DcSync(CYCLE)
    phases, _ = _run(pi, 20000, drift_ppm=50.0)  # 50 ns per cycle
    assert all(abs(p - CYCLE // 2) < 10_000 for p in phases[-1000:]), phases[-5:]


def test_noisy_frame_times_move_the_schedule_by_little():
    rng = random.Random(8)
    pi = DcSync(CYCLE)
    phases, steps = _run(pi, 5000, latency=lambda k: 40_000 + rng.randint(0, 300_000))
    assert max(abs(s) for s in steps[-2000:]) <= CYCLE // 100
    mean = sum(phases[-2000:]) / 2000
    assert abs(mean - CYCLE // 2) < 30_000, mean


def test_late_cycles_do_not_wind_the_pi_up():
    """A loaded host: every other cycle starts 600 us late, and stalls of 3 cycles. The PI sees
    the phase the frame would have had on time, holds on cycles later than a quarter cycle, and
    the schedule stays where it was (it does not run away)."""
    def late(k: int) -> int:
        return 3 * CYCLE if k % 97 == 0 else (600_000 if k % 2 else 20_000)
    pi = DcSync(CYCLE)
    ks: list[int] = []
    _, steps = _run(pi, 10000, late=late, stepped=ks)
    assert len(ks) < 10000  # slots passed during the 3-cycle stalls were skipped
    assert pi.held == len([k for k in ks if late(k) > CYCLE // 4])
    assert abs(sum(steps)) < CYCLE  # without holding, this sum grew by milliseconds
    on_time = phase_ns(123_456 + sum(steps) + 40_000, CYCLE)  # the schedule, without lateness
    assert abs(on_time - CYCLE // 2) < 5_000


def test_shift_moves_the_phase_reference():
    pi = DcSync(CYCLE, shift_ns=200_000)
    phases, _ = _run(pi, 3000)
    assert abs(phases[-1] - CYCLE // 2) < 5_000  # offset is measured from the shifted SYNC0
    assert phase_ns(1_700_000, CYCLE, 200_000) == 500_000


def test_cycle_must_be_positive():
    with pytest.raises(ValueError, match="cycle_ns"):
        DcSync(0)


def test_a_time_that_is_not_the_slaves_holds_the_pi():
    """The reference clock gone (its time stands still in the frames), back from a power cycle
    (restarted near 0), its time restored (a jump forward), or the caller's hold: each holds the
    PI and leaves the integral alone; a time advancing by about one cycle steers again."""
    pi = DcSync(CYCLE)
    t = 10**12 + 123_456
    assert pi.step(t) != 0 or pi.held == 0
    integral = pi.integral
    for dc_time in (t, t, 5_000, 1_005_000, t + 10**10, t + 10**10 + CYCLE):
        pi.step(dc_time)
    assert pi.held == 4  # t twice (stood still), 5_000 (back), t + 10 s (jump); the rest steered
    assert pi.step(t + 10**10 + 2 * CYCLE, hold=True) == 0 and pi.held == 5
    assert pi.step(t + 10**10 + 3 * CYCLE) != 0 and pi.held == 5
    assert abs(pi.integral - integral) < 3 * CYCLE  # only the steered cycles added to it
