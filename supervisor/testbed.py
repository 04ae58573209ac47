"""A loopback test bed for the supervisor's tests and benchmark: a Zenoh router and bus agents
on simulated buses, each in its own process (spawned, so every one opens its own session).

    python -m supervisor.testbed router tcp/127.0.0.1:PORT    # a router until SIGTERM
    python -m supervisor.testbed agents ROUTER h1,h2 N [CYCLE_US [SM_WATCHDOG_S]]   # N sim drives each

``agents`` runs several :class:`bus_agent.agent.Agent` in one process, each with its own Zenoh
session (peer, connected to ROUTER), and prints ``ready`` once all are running; SIGTERM runs
their ordered stop.

Not for production: it picks free loopback ports and turns multicast scouting off.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import IO, Any, Sequence


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (the OS picks it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _env() -> dict[str, str]:
    env = dict(os.environ)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


@dataclass
class Proc:
    """A child process with its output collected (for failure messages)."""

    name: str
    popen: subprocess.Popen
    lines: list[str] = field(default_factory=list)
    _ready: threading.Event = field(default_factory=threading.Event)
    ready_marker: str = ""

    def start_reader(self) -> None:
        def pump(stream: IO[str]) -> None:
            for line in stream:
                self.lines.append(line.rstrip("\n"))
                if self.ready_marker and self.ready_marker in line.lower():
                    self._ready.set()
            self._ready.set()  # EOF: stop anyone waiting
        threading.Thread(target=pump, args=(self.popen.stdout,), daemon=True).start()

    def wait_ready(self, timeout_s: float) -> bool:
        return self._ready.wait(timeout_s) and self.popen.poll() is None

    def output(self, last: int = 40) -> str:
        return "\n".join(self.lines[-last:])

    @property
    def pid(self) -> int:
        return self.popen.pid

    def kill(self) -> None:
        """SIGKILL: a crash, no clean-up in the child."""
        if self.popen.poll() is None:
            self.popen.kill()
        self.popen.wait(timeout=10)

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM, then SIGKILL after ``timeout_s``."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(timeout=10)


def spawn(name: str, argv: Sequence[str], ready_marker: str = "") -> Proc:
    popen = subprocess.Popen(list(argv), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             env=_env(), start_new_session=True)
    p = Proc(name, popen, ready_marker=ready_marker.lower())
    p.start_reader()
    return p


def start_router(port: int | None = None) -> tuple[Proc, str]:
    """A Zenoh router on 127.0.0.1 in a child process; returns it and its endpoint."""
    ep = f"tcp/127.0.0.1:{port or free_port()}"
    p = spawn("router", [sys.executable, "-m", "supervisor.testbed", "router", ep], ready_marker="router ready")
    if not p.wait_ready(20):
        p.stop()
        raise RuntimeError(f"router did not start:\n{p.output()}")
    return p, ep


def start_agents(hosts: Sequence[str], n_drives: int, router: str, *, cycle_us: int = 1000,
                 sm_watchdog_s: float = 0.1, ready_timeout_s: float = 60.0) -> Proc:
    """One process running an agent per host (own Zenoh session each) on ``n_drives`` sim drives.

    ``sm_watchdog_s``: the simulated slaves' SM watchdog (100 ms like real ones); benchmarks on a
    starved machine raise it so late cycles do not drop slaves to SAFE-OP mid-measurement."""
    argv = [sys.executable, "-m", "supervisor.testbed", "agents", router, ",".join(hosts), str(n_drives),
            str(cycle_us), str(sm_watchdog_s)]
    p = spawn(f"agents {','.join(hosts)}", argv, ready_marker="ready")
    if not p.wait_ready(ready_timeout_s):
        out = p.output()
        p.stop()
        raise RuntimeError(f"agents {', '.join(hosts)} did not become ready:\n{out}")
    return p


def start_agent(host: str, n_drives: int, router: str, *, cycle_us: int = 1000,
                ready_timeout_s: float = 60.0) -> Proc:
    """One agent in its own process."""
    return start_agents([host], n_drives, router, cycle_us=cycle_us, ready_timeout_s=ready_timeout_s)


def start_cli_agent(host: str, n_drives: int, router: str, *, ready_timeout_s: float = 60.0) -> Proc:
    """The real command line: ``python -m bus_agent.cli --sim N --host H --listen .. --connect ROUTER``."""
    argv = [sys.executable, "-m", "bus_agent.cli", "--sim", str(n_drives), "--host", host,
            "--listen", f"tcp/127.0.0.1:{free_port()}", "--connect", router, "--log-level", "WARNING"]
    p = spawn(f"bus-agent {host}", argv, ready_marker="bus-agent ready")
    if not p.wait_ready(ready_timeout_s):
        out = p.output()
        p.stop()
        raise RuntimeError(f"bus-agent {host} did not become ready:\n{out}")
    return p


def _agents_main(router: str, hosts: Sequence[str], n_drives: int, cycle_us: int, sm_watchdog_s: float) -> int:
    import logging

    from bus_agent.agent import Agent
    from bus_agent.bus.sim_bus import SimBus
    from bus_agent.config import AgentConfig, ZenohConfig

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    agents = []
    try:
        for h in hosts:
            a = Agent(AgentConfig(host=h, sim_drives=n_drives, cycle_us=cycle_us,
                                  zenoh=ZenohConfig(mode="peer", connect=(router,))),
                      bus=SimBus(n_drives, segment_name=h, sm_watchdog_s=sm_watchdog_s))
            a.start()
            agents.append(a)
        print(f"agents ready {','.join(hosts)}", flush=True)
        stop.wait()
    finally:
        for a in agents:
            a.stop()
    return 0


def _router_main(endpoint: str) -> int:
    from bus_agent.router import main as router_main  # prints "drives-router ready ..."
    return router_main(["--listen", endpoint])


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "router":
        sys.exit(_router_main(sys.argv[2]))
    if len(sys.argv) in (5, 6, 7) and sys.argv[1] == "agents":
        sys.exit(_agents_main(sys.argv[2], sys.argv[3].split(","), int(sys.argv[4]),
                              int(sys.argv[5]) if len(sys.argv) >= 6 else 1000,
                              float(sys.argv[6]) if len(sys.argv) == 7 else 0.1))
    print(__doc__, file=sys.stderr)
    sys.exit(2)
