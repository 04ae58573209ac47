"""A loopback test bed for the supervisor's tests and benchmark: a Zenoh router and bus agents
on simulated buses, each in its own process (spawned, so every one opens its own session).

    python -m supervisor.testbed router tcp/127.0.0.1:PORT [PKI IDENTITY]    # a router until SIGTERM
    python -m supervisor.testbed agents ROUTER h1,h2 N [CYCLE_US [SM_WATCHDOG_S [PKI]]]   # N sim drives each

With a PKI (a ``drives-pki`` directory), the router runs with ``--pki`` (mutual TLS, the ACL)
and each agent authenticates as its host name.

``agents`` runs several :class:`bus_agent.agent.Agent` in one process, each with its own Zenoh
session (peer, connected to ROUTER), and prints ``ready`` once all are running; SIGTERM runs
their ordered stop.

Not for production: it picks free loopback ports and turns multicast scouting off.
"""

from __future__ import annotations

import contextlib
import shutil
import sys
import tempfile
from typing import Any, Iterator, Sequence

from bus_agent.sim.child import ChildProcess, child_env, free_port
from bus_agent.stop_signals import StopSignals


# One child-process implementation for every test bed (output kept, own session).
Proc = ChildProcess
_env = child_env


def spawn(name: str, argv: Sequence[str], ready_marker: str = "") -> Proc:
    """Start ``argv`` as a test-bed child; ready once a line contains ``ready_marker``."""
    return ChildProcess(name, argv, ready_marker=ready_marker)


def start_router(port: int | None = None, *, pki: str | None = None, identity: str | None = None) -> tuple[Proc, str]:
    """A Zenoh router on 127.0.0.1 in a child process; returns it and its endpoint (``tls/``
    with ``pki`` and the router's ``identity`` in it)."""
    ep = f"{'tls' if pki else 'tcp'}/127.0.0.1:{port or free_port()}"
    secure = [pki, identity or ""] if pki else []
    p = spawn("router", [sys.executable, "-m", "supervisor.testbed", "router", ep, *secure], ready_marker="router ready")
    if not p.wait_ready(20):
        p.stop()
        raise RuntimeError(f"router did not start:\n{p.output()}")
    return p, ep


def start_agents(hosts: Sequence[str], n_drives: int, router: str, *, cycle_us: int = 1000,
                 sm_watchdog_s: float = 0.1, ready_timeout_s: float = 60.0, pki: str | None = None) -> Proc:
    """One process running an agent per host (own Zenoh session each) on ``n_drives`` sim drives.

    ``sm_watchdog_s``: the simulated slaves' SM watchdog (100 ms like real ones); benchmarks on a
    starved machine raise it so late cycles do not drop slaves to SAFE-OP mid-measurement.
    ``pki``: each agent authenticates as its host name (a certificate per host in it)."""
    argv = [sys.executable, "-m", "supervisor.testbed", "agents", router, ",".join(hosts), str(n_drives),
            str(cycle_us), str(sm_watchdog_s), *([pki] if pki else [])]
    return _spawn_ready(f"agents {', '.join(hosts)}", argv, "ready", ready_timeout_s)


def start_agent(host: str, n_drives: int, router: str, *, cycle_us: int = 1000,
                ready_timeout_s: float = 60.0) -> Proc:
    """One agent in its own process."""
    return start_agents([host], n_drives, router, cycle_us=cycle_us, ready_timeout_s=ready_timeout_s)


def start_cli_agent(host: str, n_drives: int, router: str, *, ready_timeout_s: float = 60.0,
                    log_level: str = "WARNING") -> Proc:
    """The real command line: ``python -m bus_agent.cli --sim N --host H --listen .. --connect ROUTER``."""
    argv = [sys.executable, "-m", "bus_agent.cli", "--sim", str(n_drives), "--host", host,
            "--listen", f"tcp/127.0.0.1:{free_port()}", "--connect", router, "--log-level", log_level]
    return _spawn_ready(f"bus-agent {host}", argv, "bus-agent ready", ready_timeout_s)


@contextlib.contextmanager
def enabled_sim_bed(hosts: Sequence[str], n_drives: int, *, sm_watchdog_s: float = 2.0) -> Iterator[str]:
    """A router and one agent process for ``hosts`` (``n_drives`` sim drives each), every drive
    enabled; yields the router's endpoint. SM watchdog 2 s by default, so a starved test machine
    does not trip it between the steps."""
    from supervisor.fleet import Fleet

    router, ep = start_router()
    try:
        agents = start_agents(hosts, n_drives, ep, sm_watchdog_s=sm_watchdog_s)
        try:
            with Fleet(connect=[ep]) as f:
                assert f.wait_for_agents(hosts, 10, drives=len(hosts) * n_drives)
                assert f.enable(*(f"{h}/*" for h in hosts)).ok
            yield ep
        finally:
            agents.stop()
    finally:
        router.stop()


def start_dashboard(router: str, *extra: str, ready_timeout_s: float = 60.0) -> tuple[Proc, str]:
    """``drives-dashboard --connect ROUTER --http 127.0.0.1:<free port> [extra]`` in a child
    process; returns it and its base URL."""
    port = free_port()
    argv = [sys.executable, "-m", "dashboard.cli", "--connect", router, "--http", f"127.0.0.1:{port}", *extra]
    return _spawn_ready("drives-dashboard", argv, "drives-dashboard ready", ready_timeout_s), f"http://127.0.0.1:{port}"


#: Debian's chromium and its driver (deploy/apt-packages.txt).
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"


@contextlib.contextmanager
def headless_chromium(console_log: bool = False) -> Iterator[Any]:
    """A selenium driver of Debian's headless chromium with a profile of its own (removed at the
    end); ``console_log``: the page's console is readable with ``driver.get_log("browser")``."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="testbed-chromium-")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-dev-shm-usage",
                 f"--user-data-dir={profile}"):
        opts.add_argument(flag)
    if console_log:
        opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    try:
        driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=opts)
        try:
            yield driver
        finally:
            driver.quit()
    finally:
        shutil.rmtree(profile, ignore_errors=True)


def _spawn_ready(name: str, argv: Sequence[str], marker: str, timeout_s: float) -> Proc:
    """Start ``argv`` and wait for its ready line; stopped, with its output in the error, if it never comes."""
    p = spawn(name, list(argv), ready_marker=marker)
    if not p.wait_ready(timeout_s):
        out = p.output()
        p.stop()
        raise RuntimeError(f"{name} did not become ready:\n{out}")
    return p


def _agents_main(router: str, hosts: Sequence[str], n_drives: int, cycle_us: int, sm_watchdog_s: float,
                 pki: str | None = None) -> int:
    import logging

    from bus_agent.agent import Agent
    from bus_agent.bus.sim_bus import SimBus
    from bus_agent.config import AgentConfig, ZenohConfig

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = StopSignals()
    agents = []
    try:
        for h in hosts:
            a = Agent(AgentConfig(host=h, sim_drives=n_drives, cycle_us=cycle_us,
                                  zenoh=ZenohConfig(mode="peer", connect=(router,), pki=pki)),
                      bus=SimBus(n_drives, segment_name=h, sm_watchdog_s=sm_watchdog_s))
            a.start()
            agents.append(a)
        print(f"agents ready {','.join(hosts)}", flush=True)
        stop.wait()
    finally:
        for a in agents:
            a.stop()
    return 0


def _router_main(endpoint: str, pki: str | None = None, identity: str | None = None) -> int:
    from bus_agent.router import main as router_main  # prints "drives-router ready ..."
    return router_main(["--listen", endpoint, *(["--pki", pki, "--identity", identity or ""] if pki else [])])


if __name__ == "__main__":
    if len(sys.argv) in (3, 5) and sys.argv[1] == "router":
        sys.exit(_router_main(*sys.argv[2:]))
    if len(sys.argv) in (5, 6, 7, 8) and sys.argv[1] == "agents":
        sys.exit(_agents_main(sys.argv[2], sys.argv[3].split(","), int(sys.argv[4]),
                              int(sys.argv[5]) if len(sys.argv) >= 6 else 1000,
                              float(sys.argv[6]) if len(sys.argv) >= 7 else 0.1,
                              sys.argv[7] if len(sys.argv) == 8 else None))
    print(__doc__, file=sys.stderr)
    sys.exit(2)
