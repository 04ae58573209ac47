"""Start-up steps (deadlines, stop signal) and the guard process that ends a step stuck in C.

The guard is exercised against a real child process that holds the interpreter's lock in a call
that does not return (a regular expression with catastrophic backtracking, as SOEM's
``config_map`` walking a looping SII does): neither its own signal handler nor any thread of it
can run, only the guard can end it.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import pytest

from bus_agent.startup_guard import GUARD_MARGIN_S, STOP_GRACE_S, StartupAbandoned, StartupSteps


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_a_step_past_its_deadline_is_named_and_ends_start_up():
    clock = Clock()
    lines: list[str] = []
    steps = StartupSteps(report=lines.append, clock=clock)
    with pytest.raises(StartupAbandoned) as err:
        with steps.step("config_map", 3.0):
            clock.t += 2.9
            steps.check()
            clock.t += 0.2
            steps.check()
    assert not err.value.signalled
    assert "'config_map' did not finish within its deadline (3 s)" in str(err.value)
    assert lines[0].startswith("step 103.000000 3 config_map") and lines[-1] == "idle"


def test_an_inner_step_ends_by_its_outer_deadline_and_the_outer_comes_back():
    clock = Clock()
    lines: list[str] = []
    steps = StartupSteps(report=lines.append, clock=clock)
    with steps.step("outer", 5.0):
        with steps.step("inner", 30.0):
            assert steps.current == "inner"
        assert steps.current == "outer"
    assert lines == ["step 105.000000 5 outer", "step 105.000000 30 inner", "step 105.000000 5 outer", "idle"]


def test_a_stop_signal_ends_start_up_at_the_next_check_and_names_the_step():
    stopped = [False]
    steps = StartupSteps(stopped=lambda: stopped[0])
    with pytest.raises(StartupAbandoned) as err:
        with steps.step("to SAFE-OP", 6.0):
            steps.check()
            stopped[0] = True
            steps.sleep(10.0)  # returns at once with the stop
    assert err.value.signalled and "'to SAFE-OP'" in str(err.value)


def test_after_finish_nothing_is_checked_and_the_guard_is_told():
    lines: list[str] = []
    steps = StartupSteps(stopped=lambda: True, report=lines.append)
    steps.finish()
    with steps.step("runtime SDO", 0.0):
        steps.check()
    assert lines == ["done"]


CHILD = textwrap.dedent("""
    import re, sys, time
    from bus_agent.stop_signals import StopSignals
    from bus_agent.startup_guard import StartupSteps, start_guard
    stop = StopSignals()
    guard = start_guard("child")
    steps = StartupSteps(stopped=lambda: stop.stopped, report=guard.report)
    steps.begin("a call that never returns", float(sys.argv[1]))
    print("in the call", flush=True)
    re.match(r"(a+)+$", "a" * 64 + "b")  # holds the GIL for ever: no handler, no thread runs
    print("returned", flush=True)
""")


def _child(deadline_s: float) -> tuple[subprocess.Popen, float]:
    p = subprocess.Popen([sys.executable, "-c", CHILD, str(deadline_s)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    assert p.stdout is not None
    assert p.stdout.readline().strip() == "in the call"
    return p, time.monotonic()


def test_the_guard_ends_a_step_stuck_in_c_at_its_deadline():
    p, t0 = _child(1.0)
    try:
        p.wait(1.0 + GUARD_MARGIN_S + 5.0)
    finally:
        p.kill()
    elapsed = time.monotonic() - t0
    _, err = p.communicate()
    assert p.returncode == -signal.SIGKILL
    assert elapsed >= 1.0 + GUARD_MARGIN_S - 0.2
    assert "child: start-up step 'a call that never returns' did not return within its deadline (1 s)" in err


def test_the_guard_ends_a_step_stuck_in_c_within_2_s_of_sigterm():
    p, _ = _child(60.0)
    try:
        time.sleep(0.3)
        p.send_signal(signal.SIGTERM)  # recorded by the C handler; the Python handler cannot run
        t0 = time.monotonic()
        p.wait(10.0)
        elapsed = time.monotonic() - t0
    finally:
        p.kill()
    _, err = p.communicate()
    assert p.returncode == -signal.SIGKILL
    assert elapsed < 2.0, elapsed
    assert elapsed >= STOP_GRACE_S - 0.2
    assert f"still running {STOP_GRACE_S:g} s after a stop signal" in err
