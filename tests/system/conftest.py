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

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, Sequence, TypeVar

import pytest
import zenoh

from bus_agent.zenoh_config import make_zenoh_config

ROOT = Path(__file__).resolve().parents[2]
READY = "bus-agent ready"
T = TypeVar("T")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(pred: Callable[[], T], timeout_s: float = 10.0, what: str = "condition", poll_s: float = 0.02) -> T:
    """Poll ``pred`` until it returns something truthy (returned) or fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(poll_s)


class AgentProc:
    """A ``bus-agent`` child process; its output is collected line by line."""

    def __init__(self, host: str, argv: Sequence[str], listen: Sequence[str], connect: Sequence[str]) -> None:
        self.host = host
        self.argv = list(argv)
        self.listen = list(listen)
        self.connect = list(connect)
        self.lines: list[str] = []
        self._ready = threading.Event()
        env = dict(os.environ)
        env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env["PYTHONUNBUFFERED"] = "1"
        self.popen = subprocess.Popen(self.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                      cwd=ROOT, env=env, start_new_session=True)
        self._reader = threading.Thread(target=self._pump, name=f"agent-{host}-out", daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.append(line.rstrip("\n"))
            if line.startswith(READY):
                self._ready.set()
        self._ready.set()  # EOF: wake anyone waiting

    @property
    def endpoint(self) -> str:
        """The first listen endpoint (what a client connects to)."""
        return self.listen[0]

    @property
    def pid(self) -> int:
        return self.popen.pid

    def output(self, last: int = 60) -> str:
        return "\n".join(self.lines[-last:])

    def wait_ready(self, timeout_s: float) -> None:
        if not self._ready.wait(timeout_s) or self.popen.poll() is not None:
            raise AssertionError(f"agent {self.host} did not become ready (exit {self.popen.poll()}):\n{self.output()}")

    def terminate(self, timeout_s: float = 15.0) -> int:
        """SIGTERM and wait; returns the exit code (SIGKILL and fail if it does not exit)."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
        try:
            code = self.popen.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"agent {self.host} ignored SIGTERM for {timeout_s} s:\n{self.output()}")
        self._reader.join(5)
        return code

    def kill(self) -> None:
        """SIGKILL the agent's whole process group (it runs in its own session)."""
        if self.popen.poll() is None:
            try:
                os.killpg(self.popen.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        try:
            self.popen.wait(10)
        except subprocess.TimeoutExpired:
            pass


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
        proc.wait_ready(ready_timeout_s)
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
