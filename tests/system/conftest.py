"""System-test fixtures: bus agents as separate processes, and zenoh sessions to talk to them.

Fixtures (function scope; ``module_*`` twins live for a whole test module):

- ``start_agent(host, sim=4, connect=(), listen=None, extra_args=(), ready_timeout_s=30)``
  -> :class:`AgentProc`. Runs ``python -m bus_agent.cli --sim N --host H --listen EP ...``;
  ``listen=None`` picks one free loopback port (``proc.endpoint``). Returns once the agent
  printed its readiness line. Every agent still running at teardown gets SIGTERM, then SIGKILL.
- ``zenoh_session(connect=(), listen=(), mode="peer")`` -> an open ``zenoh.Session``
  (multicast scouting off), closed at teardown.

(Helpers are fixtures, not imports: two ``conftest`` modules share one module name.)
"""

from __future__ import annotations

import shutil
import sys
from typing import Any, Iterator, Sequence

import pytest
import zenoh

from bus_agent.sim.child import ChildProcess, free_port
from bus_agent.gateway.zenoh_config import make_zenoh_config
from supervisor.testbed import CHROMEDRIVER, CHROMIUM, headless_chromium

from tests.conftest import require

READY = "bus-agent ready"


class AgentProc(ChildProcess):
    """A ``bus-agent`` child process; its output is collected line by line."""

    def __init__(self, host: str, argv: Sequence[str], listen: Sequence[str], connect: Sequence[str]) -> None:
        super().__init__(f"agent {host}", argv, ready_marker=READY)
        self.host = host
        self.listen = list(listen)
        self.connect = list(connect)

    @property
    def endpoint(self) -> str:
        """The first listen endpoint (what a client connects to)."""
        return self.listen[0]

    def output(self, last: int = 60) -> str:
        return super().output(last)

    def terminate(self, timeout_s: float = 15.0) -> int:
        """SIGTERM and wait; returns the exit code (SIGKILL and fail if it does not exit)."""
        code = self.stop(timeout_s)
        if self.stop_timed_out:
            raise AssertionError(f"agent {self.host} ignored SIGTERM for {timeout_s} s:\n{self.output()}")
        assert code is not None
        return code


class AgentLauncher:
    def __init__(self) -> None:
        self.procs: list[AgentProc] = []

    def __call__(self, host: str, sim: int | None = 4, connect: Sequence[str] = (), listen: Sequence[str] | None = None,
                 extra_args: Sequence[str] = (), ready_timeout_s: float = 30.0) -> AgentProc:
        listen = list(listen) if listen is not None else [f"tcp/127.0.0.1:{free_port()}"]
        argv = [sys.executable, "-m", "bus_agent.cli", "--host", host]
        if sim is not None:
            argv += ["--sim", str(sim)]
        for ep in listen:
            argv += ["--listen", ep]
        for ep in connect:
            argv += ["--connect", ep]
        argv += list(extra_args)
        proc = AgentProc(host, argv, listen, connect)
        self.procs.append(proc)
        proc.expect_ready(ready_timeout_s)
        return proc

    def close(self) -> None:
        for p in self.procs:
            if p.popen.poll() is None:
                try:
                    p.terminate(10.0)
                except AssertionError:
                    p.kill()
            p.kill()  # reap; no-op when gone


class SessionFactory:
    def __init__(self) -> None:
        self.sessions: list[zenoh.Session] = []

    def __call__(self, connect: Sequence[str] = (), listen: Sequence[str] = (), mode: str = "peer") -> zenoh.Session:
        s = zenoh.open(make_zenoh_config(mode, listen, connect))
        self.sessions.append(s)
        return s

    def close(self) -> None:
        for s in reversed(self.sessions):
            try:
                s.close()
            except Exception:
                pass


@pytest.fixture
def start_agent() -> Iterator[AgentLauncher]:
    launcher = AgentLauncher()
    try:
        yield launcher
    finally:
        launcher.close()


@pytest.fixture(scope="module")
def module_start_agent() -> Iterator[AgentLauncher]:
    launcher = AgentLauncher()
    try:
        yield launcher
    finally:
        launcher.close()


@pytest.fixture
def zenoh_session() -> Iterator[SessionFactory]:
    factory = SessionFactory()
    try:
        yield factory
    finally:
        factory.close()


@pytest.fixture(scope="module")
def module_zenoh_session() -> Iterator[SessionFactory]:
    factory = SessionFactory()
    try:
        yield factory
    finally:
        factory.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Debian's headless chromium (selenium) with its console log readable, one per module."""
    require(shutil.which(CHROMIUM) is not None and shutil.which(CHROMEDRIVER) is not None,
            "Debian chromium and chromium-driver", "apt-get install chromium chromium-driver (deploy/apt-packages.txt)")
    with headless_chromium(console_log=True) as driver:
        driver.set_window_size(1400, 1000)
        yield driver
