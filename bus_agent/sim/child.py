"""Child processes of test beds (agents, routers, simulators, supervisors), their output kept.

One implementation for the loopback bed (``supervisor.testbed``), the system tests and the
multi-host bed: each child runs in its own session (so a kill reaches its whole process group),
its stdout and stderr are collected line by line for failure messages, and a readiness marker in
its output says when it is up. Not for production.

Every child dies with this process: it starts under util-linux's ``setpriv --pdeathsig KILL``
(``prctl(PR_SET_PDEATHSIG)``, kept across the exec of the command), so a bed, a twin or a test
run that is itself SIGKILLed leaves no orphan router, agent or simulator behind. The kernel sends
that signal when the *thread* that forked the child ends, so children are forked on the main
thread or on one long-lived spawner thread (a child started from a short-lived thread, such as
a command handler, would otherwise die with that thread).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Sequence, TypeVar

ROOT = Path(__file__).resolve().parents[2]
T = TypeVar("T")
#: Prefix of every child's argv: the child gets SIGKILL when its forking thread (see below) ends.
DIE_WITH_PARENT = ("setpriv", "--pdeathsig", "KILL", "--")

_spawner: ThreadPoolExecutor | None = None
_spawner_lock = threading.Lock()


def _on_lasting_thread(fn: Callable[[], T]) -> T:
    """``fn()`` on the main thread, or on the one spawner thread that lives as long as the process."""
    global _spawner
    if threading.current_thread() is threading.main_thread():
        return fn()
    with _spawner_lock:
        if _spawner is None:
            _spawner = ThreadPoolExecutor(1, thread_name_prefix="child-spawner")
    return _spawner.submit(fn).result()


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


def descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (from /proc), whatever its session; ``pid`` itself not included."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue  # gone meanwhile
            children.setdefault(ppid, []).append(int(d))
    out: set[int] = set()
    todo = [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


def running(pids: set[int]) -> set[int]:
    """Those of ``pids`` still running (a zombie counts as gone: it runs no code)."""
    left = set()
    for p in pids:
        try:
            if Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                left.add(p)
        except (OSError, IndexError):
            pass
    return left


def cmdline(pid: int) -> str:
    """The command line of process ``pid`` ("" if it is gone)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


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
        self.popen = _on_lasting_thread(lambda: subprocess.Popen(
            [*DIE_WITH_PARENT, *self.argv], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL, cwd=ROOT, env=child_env(), start_new_session=True))
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
