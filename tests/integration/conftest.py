"""Fixtures for tests against a virtual EtherCAT segment (``ecat-sim`` on a veth pair).

``ecat_segment(n, profile)`` creates a uniquely named veth pair, starts ``ecat-sim`` on one end
as a subprocess, waits for its readiness line, and returns ``(ifname, control)``: the master
end for pysoem and a :class:`~bus_agent.sim.ecat.control.ControlClient` for fault injection.
Everything is torn down after the test, also when it fails.
"""

from __future__ import annotations

import itertools
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import pytest

from bus_agent.sim.ecat.control import ControlClient
from bus_agent.sim.netns import pair_names, veth_down, veth_up
from tests.conftest import require, require_root

ROOT = Path(__file__).resolve().parents[2]
READY_TIMEOUT_S = 20.0
_counter = itertools.count()


class EcatSegment(NamedTuple):
    ifname: str
    control: ControlClient


class SimProcess:
    def __init__(self, proc: subprocess.Popen, master: str, workdir: str, control: ControlClient):
        self.proc, self.master, self.workdir, self.control = proc, master, workdir, control

    def stop(self) -> None:
        self.control.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        veth_down(self.master)
        shutil.rmtree(self.workdir, ignore_errors=True)


def _wait_ready(proc: subprocess.Popen, stderr_path: Path) -> str:
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            break
        ready, _, _ = select.select([proc.stdout], [], [], 0.2)
        if ready:
            line = proc.stdout.readline()
            if line.startswith("ecat-sim ready"):
                return line
    raise RuntimeError(f"ecat-sim not ready (exit {proc.poll()}): {stderr_path.read_text()[-2000:]}")


@pytest.fixture
def ecat_segment():
    """Factory: ``ifname, control = ecat_segment(16, "generic")``; slaves from ESI files:
    ``ecat_segment(2, esi=("FILE@PRODUCT*2",))``."""
    require_root()
    require(shutil.which("ip") is not None, "iproute2 (`ip`)", "install iproute2")
    started: list[SimProcess] = []

    def factory(n: int, profile: str = "generic", *extra: str, esi: tuple[str, ...] = ()) -> EcatSegment:
        prefix = f"ecs{os.getpid() % 100000:05d}{next(_counter) % 10}"
        master, sim = pair_names(prefix, 0)
        veth_up(master, sim)
        workdir = tempfile.mkdtemp(prefix="ecat-sim-")
        sock_path = os.path.join(workdir, "ctl.sock")
        stderr_path = Path(workdir) / "stderr.log"
        proc = subprocess.Popen(
            [sys.executable, "-m", "bus_agent.sim.cli", "--ifname", sim, "--drives", str(n),
             *([a for spec in esi for a in ("--esi", spec)] if esi else ["--profile", profile]), "--name", prefix, "--control", sock_path, "--rt-priority", "20", "--log-level", "INFO", *extra],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=stderr_path.open("w"), text=True)
        handle = SimProcess(proc, master, workdir, ControlClient(sock_path))
        started.append(handle)
        _wait_ready(proc, stderr_path)
        return EcatSegment(master, handle.control)

    try:
        yield factory
    finally:
        for handle in started:
            handle.stop()
