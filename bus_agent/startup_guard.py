"""Deadlines for every blocking start-up step, and a stop signal that ends start-up in any step.

Start-up (the bus to OP, the gateway up) is a sequence of blocking steps. Each runs inside
:meth:`StartupSteps.step` with a deadline. Two things enforce it:

- **in the agent**: :meth:`StartupSteps.check` raises :class:`StartupAbandoned` once the stop
  signal (SIGTERM/SIGINT) came or the step's deadline passed. Every loop and every transfer of
  start-up calls it between its blocking calls, so start-up ends in order: what was opened is
  closed, the CLI prints why and exits (3 for a deadline, 0 for a stop signal).
- **outside the agent**, for a call into C that does not return (SOEM's ``config_map`` walking a
  malformed SII holds the interpreter's lock, so no Python code of the agent runs, its signal
  handler included): a guard process (:func:`start_guard`, this file run as a script with the
  standard library only) is told each step and its deadline through a pipe, and learns of a stop
  signal through the interpreter's wakeup fd, which the C-level signal handler writes without
  the lock. If the agent has not ended the step :data:`GUARD_MARGIN_S` after its deadline, or
  has not exited :data:`STOP_GRACE_S` after the signal, the guard prints the reason to the
  agent's stderr and kills it (SIGKILL).

Safe to end at any step: no drive is enabled before start-up is over (drives are enabled only by
commands, which come through the gateway, which is declared last); a slave already in SAFE-OP or
OP sees its process data stop and its SM watchdog drops it to SAFE-OP with outputs off.
"""

from __future__ import annotations

import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator

#: After a stop signal the agent ends start-up itself, or the guard kills it this much later.
STOP_GRACE_S = 1.0
#: The guard kills a step this long after its deadline (the agent's own check goes first).
GUARD_MARGIN_S = 1.0
#: SCHED_FIFO priority of the guard (when allowed): it must act on time on a loaded machine, and
#: it only ever sleeps in select (below any cycle thread's priority).
GUARD_RT_PRIORITY = 1
#: How often a cooperative wait (:meth:`StartupSteps.sleep`) looks for a stop.
POLL_S = 0.05

log = logging.getLogger("bus_agent.startup")


class StartupAbandoned(Exception):
    """Start-up ended before it was done: a stop signal (``signalled``) or a step's deadline."""

    def __init__(self, message: str, signalled: bool) -> None:
        super().__init__(message)
        self.signalled = signalled


class StartupSteps:
    """The current start-up step and its deadline; see the module docstring.

    ``stopped``: tells whether a stop signal came (the CLI's :class:`~bus_agent.stop_signals.StopSignals`).
    ``report``: called with one line per step begun or ended (the guard's pipe). After
    :meth:`finish` nothing is checked any more (the same bus serves the running agent).
    """

    def __init__(self, stopped: Callable[[], bool] = lambda: False,
                 report: Callable[[str], None] | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self._stopped = stopped
        self._report = report
        self._clock = clock
        #: (name, deadline on the monotonic clock, its length in s), innermost last
        self._stack: list[tuple[str, float, float]] = []
        self.finished = False

    @property
    def current(self) -> str:
        """The innermost step under way ("" when none)."""
        return self._stack[-1][0] if self._stack else ""

    @contextmanager
    def step(self, name: str, deadline_s: float) -> Iterator[None]:
        """A blocking step that must end within ``deadline_s`` (and within its enclosing steps')."""
        self.begin(name, deadline_s)
        try:
            yield
        finally:
            self.end()
        self.check()

    def begin(self, name: str, deadline_s: float) -> None:
        """Enter a step (see :meth:`step`); :meth:`end` leaves it. Checks first."""
        if self.finished:
            return
        self.check()
        deadline = self._clock() + deadline_s
        if self._stack:
            deadline = min(deadline, self._stack[-1][1])
        self._stack.append((name, deadline, deadline_s))
        log.debug("start-up step %r (deadline %g s)", name, deadline_s)
        self._tell(f"step {deadline:.6f} {deadline_s:g} {name}")

    def end(self) -> None:
        """Leave the innermost step (no check: also on the way out of an error)."""
        if self.finished or not self._stack:
            return
        self._stack.pop()
        if self._stack:
            outer, at, told = self._stack[-1]
            self._tell(f"step {at:.6f} {told:g} {outer}")
        else:
            self._tell("idle")

    def check(self) -> None:
        """Raise :class:`StartupAbandoned` if a stop signal came or a step's deadline passed."""
        if self.finished:
            return
        if self._stopped():
            raise StartupAbandoned(f"stop signal during start-up step {self.current or 'start-up'!r}: "
                                   "start-up abandoned (no drive was enabled)", signalled=True)
        now = self._clock()
        for name, deadline, told in self._stack:
            if now > deadline:
                raise StartupAbandoned(f"start-up step {name!r} did not finish within its deadline ({told:g} s)",
                                       signalled=False)

    def sleep(self, seconds: float) -> None:
        """``time.sleep`` that ends early with :class:`StartupAbandoned`."""
        end = self._clock() + seconds
        while True:
            self.check()
            left = end - self._clock()
            if left <= 0:
                return
            time.sleep(min(POLL_S, left))

    def finish(self) -> None:
        """Start-up is over: no more checks, the guard (if any) is told and goes."""
        if not self.finished:
            self.finished = True
            self._tell("done")

    def _tell(self, line: str) -> None:
        if self._report is not None:
            self._report(line)


class Guard:
    """The guard process of this agent's start-up (:func:`start_guard`)."""

    def __init__(self, proc: subprocess.Popen, steps_w: int, signals_r: int, signals_w: int) -> None:
        self.proc = proc
        self._steps_w = steps_w
        self._fds = [signals_r, signals_w]

    def report(self, line: str) -> None:
        try:
            os.write(self._steps_w, line.encode() + b"\n")  # one write < PIPE_BUF: atomic
        except OSError:
            pass  # the guard is gone: nothing to tell

    def close(self) -> None:
        """After start-up (done or abandoned): the wakeup fd back to none, the guard told to go."""
        try:
            signal.set_wakeup_fd(-1)
        except ValueError:
            pass  # not the main thread
        self.report("done")
        for fd in (self._steps_w, *self._fds):
            try:
                os.close(fd)
            except OSError:
                pass
        # Not waited for here: after a short start-up the guard may still be booting (it reads
        # "done", or EOF, and leaves); a daemon thread reaps it.
        threading.Thread(target=self.proc.wait, name="startup-guard-reaper", daemon=True).start()


def start_guard(what: str = "bus-agent") -> Guard:
    """Start the guard process for this process (from the main thread: it takes the wakeup fd).
    ``what`` prefixes the guard's messages."""
    steps_r, steps_w = os.pipe()
    signals_r, signals_w = os.pipe()
    os.set_blocking(signals_w, False)  # the C signal handler must never block on it
    proc = subprocess.Popen([sys.executable, "-I", "-S", os.path.abspath(__file__), str(os.getpid()),
                             str(signals_r), what], stdin=steps_r, pass_fds=(signals_r,), stdout=subprocess.DEVNULL)
    os.close(steps_r)
    signal.set_wakeup_fd(signals_w, warn_on_full_buffer=False)
    return Guard(proc, steps_w, signals_r, signals_w)


# ---- the guard process (stdlib only: it runs with -I -S) ---------------------------------------

def _guard_main(pid: int, what: str, signal_fd: int) -> int:
    # Stop signals are for the agent: the guard stays until the agent is gone.
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(GUARD_RT_PRIORITY))
    except OSError:
        pass  # not allowed: ordinary scheduling
    steps_fd = sys.stdin.fileno()
    buf = b""
    step, limit = "", ""  # the step under way and its deadline (s) as told
    deadline: float | None = None  # ... and when, on the monotonic clock
    stop_at: float | None = None
    fds = [steps_fd, signal_fd]
    while True:
        ends = [t for t in (None if deadline is None else deadline + GUARD_MARGIN_S, stop_at) if t is not None]
        timeout = max(0.0, min(ends) - time.monotonic()) if ends else None
        ready, _, _ = select.select(fds, [], [], timeout)
        if signal_fd in ready:
            if not os.read(signal_fd, 64):
                fds.remove(signal_fd)
            elif stop_at is None:
                stop_at = time.monotonic() + STOP_GRACE_S
        if steps_fd in ready:
            data = os.read(steps_fd, 4096)
            if not data:
                return 0  # the agent is gone (or closed the pipe): nothing to guard
            buf += data
            *lines, buf = buf.split(b"\n")
            for raw in lines:
                line = raw.decode(errors="replace")
                if line == "done":
                    return 0
                if line == "idle":
                    step, deadline = "", None
                elif line.startswith("step "):
                    _, at, limit, step = line.split(" ", 3)
                    deadline = float(at)
        now = time.monotonic()
        if stop_at is not None and now >= stop_at:
            why = (f"start-up step {step or 'start-up (between steps)'!r} still running {STOP_GRACE_S:g} s after a stop signal "
                   "(a call that cannot be interrupted)")
        elif deadline is not None and now >= deadline + GUARD_MARGIN_S:
            why = f"start-up step {step!r} did not return within its deadline ({limit} s)"
        else:
            continue
        try:
            os.write(2, f"{what}: {why}: ended by its start-up guard (SIGKILL); no drive was enabled\n".encode())
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
        return 0


if __name__ == "__main__":
    sys.exit(_guard_main(int(sys.argv[1]), sys.argv[3], int(sys.argv[2])))
