"""Child processes of test beds (agents, routers, simulators, supervisors), their output kept.

One implementation for the loopback bed (``supervisor.testbed``), the system tests and the
multi-host bed: each child runs in its own session (so a kill reaches its whole process group),
its stdout and stderr are collected line by line for failure messages, and a readiness marker in
its output says when it is up. Not for production.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Callable, Sequence, TypeVar

ROOT = Path(__file__).resolve().parents[2]
T = TypeVar("T")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (the OS picks it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(pred: Callable[[], T], timeout_s: float = 10.0, what: str = "condition", poll_s: float = 0.02) -> T:
    """Poll ``pred`` until it returns something truthy (returned); AssertionError naming ``what``
    after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(poll_s)


def child_env() -> dict[str, str]:
    """The environment of a child: this checkout first on PYTHONPATH, unbuffered output."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["PYTHONUNBUFFERED"] = "1"
    return env


class ChildProcess:
    """A child process in its own session, with its output collected line by line.

    ``ready_marker``: a line containing it marks the child ready (:meth:`wait_ready`).
    """

    def __init__(self, name: str, argv: Sequence[str], *, ready_marker: str = "", stdin: bool = False) -> None:
        self.name = name
        self.argv = list(argv)
        self.ready_marker = ready_marker
        self.lines: list[str] = []
        self.stop_timed_out = False
        self._ready = threading.Event()
        self.popen = subprocess.Popen(self.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                      stdin=subprocess.PIPE if stdin else subprocess.DEVNULL, cwd=ROOT,
                                      env=child_env(), start_new_session=True)
        self._reader = threading.Thread(target=self._pump, name=f"{name}-out", daemon=True)
        self._reader.start()

    def on_line(self, line: str) -> None:
        """Hook for subclasses, called on the reader thread for every output line."""

    def _pump(self) -> None:
        assert self.popen.stdout is not None
        for raw in self.popen.stdout:
            line = raw.rstrip("\n")
            self.lines.append(line)
            self.on_line(line)
            if self.ready_marker and self.ready_marker in line:
                self._ready.set()
        self._ready.set()  # EOF: wake anyone waiting

    @property
    def pid(self) -> int:
        return self.popen.pid

    def output(self, last: int = 40) -> str:
        return "\n".join(self.lines[-last:])

    def wait_ready(self, timeout_s: float) -> bool:
        """True once the readiness line came and the child still runs."""
        return self._ready.wait(timeout_s) and self.popen.poll() is None

    def expect_ready(self, timeout_s: float) -> None:
        """:meth:`wait_ready` or AssertionError with the child's last output."""
        if not self.wait_ready(timeout_s):
            raise AssertionError(f"{self.name} not ready (exit {self.popen.poll()}):\n{self.output()}")

    def kill(self) -> None:
        """SIGKILL the child's process group: a crash, no clean-up. Reaps it."""
        if self.popen.poll() is None:
            try:
                os.killpg(self.popen.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        try:
            self.popen.wait(10)
        except subprocess.TimeoutExpired:
            pass

    def stop(self, timeout_s: float = 10.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout_s`` (``stop_timed_out`` tells); the exit code."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.stop_timed_out = True
                self.kill()
        self._reader.join(5)
        return self.popen.poll()
