"""The twin: a router and one bus agent per host of a fleet file, supervised, with faults on demand.

``Twin(fleet, backend="sim"|"ecat", listen=EP).start()`` starts, each in its own process:

- one ``drives-router`` listening on ``listen`` (what supervisors connect to; default a free
  loopback port) and on a UNIX socket in the twin's work directory (for the twin's links);
- per host a :class:`~twin.relay.LinkRelay` (the host's cuttable link to the router, a thread of
  this process) and one ``bus-agent --config`` whose TOML (``twin.plan``) names exactly the fleet's
  host, axes and groups, connected through that relay;
- with ``backend="ecat"`` (root) per host a network namespace with an EtherCAT veth pair
  (``twin.ecat``), ``ecat-sim --name <host>`` on one end and the agent's pysoem on the other
  (``--esi`` with the host's ESI files, when its fleet entry names them);
- per host whose fleet entry names EDS files (either backend, no root) ``canopen-sim --eds``
  with those files and the agent's ``[can]`` backend, on a udp_multicast group of its own that
  never leaves the machine (``twin.plan.can_channel``).

With ``pki=DIR`` (sim backend) every link is mutual TLS and the router enforces the ACL: the twin
issues its router's, agents' and its own certificates into a copy of DIR (``twin.secure``), the
links are loopback TCP ports relayed to the router's ``tls/`` endpoint, and :attr:`fleet` is an
operator (``twin-operator``, or ``identity``).

It is ready when every expected drive answered on Zenoh with exactly the expected axes per host.
A monitor thread watches the children: one that exits without being asked to is recorded in
:attr:`Twin.unexpected_exits` and reported through ``on_unexpected_exit`` (the CLI then stops
everything). :meth:`stop` stops agents first (their ordered shutdown), then simulators and the
router, closes the links and removes namespaces and the work directory; it is idempotent and runs
also after a failed start. Every child dies with the twin's process (``bus_agent.sim.child``); what
a SIGKILLed twin leaves (work directory, namespaces) the next start removes (``twin.stale``).
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import tomli_w
import zenoh

from bus_agent.gateway.zenoh_config import make_zenoh_config
from bus_agent.sim.child import ChildProcess, free_port
from bus_agent.sim.control import sim_inject
from supervisor.fleet import Fleet, FleetError
from supervisor.fleetfile import ExpectedFleet, load
from supervisor.selectors import DriveRef
from supervisor.simctl import sim_targets
from schemas.messages import DriveStatus

from .ecat import EcatHost, ecat_down, ecat_plan, ecat_up, prerequisites
from .plan import BACKENDS, HostPlan, PlanError, can_channel, check_host, parse_ref, plan, sim_device_args
from .relay import RelayHub
from .secure import CONTROL, OPERATOR, ROUTER, prepare, tls_endpoint, twin_principals
from .stale import WORKDIR_PREFIX, clean_stale, write_owner

log = logging.getLogger(__name__)

READY_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 15.0
MONITOR_PERIOD_S = 0.2
#: SCHED_FIFO priority of each ecat-sim (as the test beds run it): on a loaded machine the
#: simulated slaves must answer pysoem's start-up reads in time.
SIM_RT_PRIORITY = 20


class TwinError(RuntimeError):
    """The twin could not start, or a helper could not do what was asked; the message says why."""


class Twin:
    """A simulated twin of ``fleet`` (a fleet file path, a dict of the same content, or an
    :class:`ExpectedFleet`). See the module docstring; use as a context manager or call
    :meth:`start` and :meth:`stop`."""

    def __init__(self, fleet: str | os.PathLike[str] | Mapping[str, Any] | ExpectedFleet, *,
                 backend: str = "sim", listen: str | None = None, ready_timeout_s: float = READY_TIMEOUT_S,
                 on_unexpected_exit: Callable[[str], None] | None = None, log_level: str = "WARNING",
                 pki: str | os.PathLike[str] | None = None, identity: str | None = None) -> None:
        self.expected = fleet if isinstance(fleet, ExpectedFleet) else load(fleet)
        if backend not in BACKENDS:
            raise PlanError(f"backend {backend!r} is not one of {', '.join(BACKENDS)}")
        if identity is not None and pki is None:
            raise PlanError("--identity needs --pki (a drives-pki directory holding that principal)")
        if pki is not None and backend != "sim":
            raise PlanError("--pki works with the sim backend only (the ecat backend's namespaced agents reach "
                            "the router through UNIX sockets, which carry no TLS)")
        self.backend = backend
        #: The user's drives-pki directory (None: an insecure twin), and who ``fleet`` is (twin.secure).
        self.pki = None if pki is None else os.fspath(pki)
        self.identity = identity
        self.pki_copy = ""  # the copy in the work directory the twin's own processes use
        if self.pki is not None:
            twin_principals(self.expected.hosts, identity)  # a name clash fails before anything starts
        self.endpoint = listen or f"tcp/127.0.0.1:{free_port()}"
        if self.pki is not None:
            self.endpoint = tls_endpoint(self.endpoint)
        self.ready_timeout_s = ready_timeout_s
        self.on_unexpected_exit = on_unexpected_exit
        self.log_level = log_level
        self.unexpected_exits: list[str] = []
        self.workdir = ""
        self.prefix = f"tw{os.getpid() % 100000}"
        self.plans: dict[str, HostPlan] = {}
        self.ecat_hosts: dict[str, EcatHost] = {}
        #: Hosts with EDS devices -> their CAN group (canopen-sim and the agent's [can] backend).
        self.can_hosts: dict[str, str] = {h: can_channel(os.getpid(), i) for i, (h, spec)
                                          in enumerate(self.expected.hosts.items()) if spec.device_kind == "eds"}
        self.router: ChildProcess | None = None
        self.agents: dict[str, ChildProcess] = {}
        self.sims: dict[str, ChildProcess] = {}
        self._fleet: Fleet | None = None
        self._control: zenoh.Session | None = None   # fault injection as twin-control (secure twin)
        self._hub: RelayHub | None = None
        self._expected_down: set[int] = set()   # pids we stopped or killed on purpose
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        self._monitor: threading.Thread | None = None
        self.started_monotonic = 0.0
        self.ready_s = 0.0

    # ---- lifecycle -------------------------------------------------------------------------

    def __enter__(self) -> "Twin":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def router_socket(self) -> str:
        return os.path.join(self.workdir, "router.sock")

    def start(self) -> "Twin":
        """Start everything and wait until every expected drive answers; TwinError otherwise
        (everything started so far is stopped again)."""
        if self.backend == "ecat" and set(self.expected.hosts) - set(self.can_hosts) and (why := prerequisites()):
            raise TwinError(why)
        self.started_monotonic = time.monotonic()
        clean_stale()  # what a SIGKILLed twin left (work directory, namespaces): it may block our names
        self.workdir = tempfile.mkdtemp(prefix=WORKDIR_PREFIX)
        if self.backend == "ecat":
            self.ecat_hosts = {h: ecat_plan(self.prefix, i + 1) for i, h in enumerate(self.expected.hosts)
                               if h not in self.can_hosts}
        try:
            write_owner(self.workdir, self.ecat_hosts)  # before any namespace exists
            self._start()
        except BaseException:
            self.stop()
            raise
        self.ready_s = time.monotonic() - self.started_monotonic
        return self

    def _start(self) -> None:
        self._hub = RelayHub()
        if self.pki is not None:
            self.pki_copy = prepare(self.pki, os.path.join(self.workdir, "pki"), self.expected.hosts, self.identity)
            # TLS runs over TCP only: each link a loopback port relayed to the router's TLS endpoint
            host, _, port = self.endpoint.partition("/")[2].rpartition(":")
            links = {h: self._hub.add(h, ("127.0.0.1", 0), (host.strip("[]"), int(port))) for h in self.expected.hosts}
        else:
            links = {h: self._hub.add(h, os.path.join(self.workdir, f"{h}.link"), self.router_socket)
                     for h in self.expected.hosts}
        self.plans = {p.name: p for p in plan(self.expected, self.backend, {h: r.endpoint for h, r in links.items()},
                                              {h: e.master for h, e in self.ecat_hosts.items()}, self.pki_copy,
                                              self.can_hosts)}
        self.router = self._spawn_router()
        for h, e in self.ecat_hosts.items():
            ecat_up(e)
            self.sims[h] = self._spawn_sim(h)
        for h in self.can_hosts:
            self.sims[h] = self._spawn_sim(h)
        for h in self.plans:
            Path(self.workdir, f"{h}.toml").write_text(tomli_w.dumps(dict(self.plans[h].agent_toml)))
        self._expect_ready(self.router)
        for h in self.sims:
            self._expect_ready(self.sims[h])
        for h in self.plans:
            self.agents[h] = self._spawn_agent(h)
        for h in self.plans:
            self._expect_ready(self.agents[h])
        who = self.identity or OPERATOR
        self._fleet = Fleet(connect=[self.endpoint], name=who if self.pki else f"twin-{os.getpid()}",
                            connect_timeout_s=10.0, pki=self.pki_copy or None, identity=who if self.pki else None)
        try:
            self._fleet.open()
        except FleetError as exc:
            self._fleet = None
            raise TwinError(f"twin: its supervisor cannot reach the router at {self.endpoint}: {exc}") from None
        if self.pki is not None:
            try:
                self._control = zenoh.open(make_zenoh_config("client", connect=[self.endpoint], pki=self.pki_copy,
                                                             identity=CONTROL))
            except zenoh.ZError as exc:
                raise TwinError(f"twin: its control session cannot reach the router at {self.endpoint}: {exc}") \
                    from None
        self._monitor = threading.Thread(target=self._watch, name="twin-monitor", daemon=True)
        self._monitor.start()
        self.wait_answering(self.expected.hosts, self._deadline_left())

    def _deadline_left(self) -> float:
        return max(1.0, self.started_monotonic + self.ready_timeout_s - time.monotonic())

    def stop(self) -> None:
        """Stop everything this twin started (agents first: their ordered shutdown). Idempotent."""
        self._stopping.set()
        if self._monitor is not None:
            self._monitor.join(5)
            self._monitor = None
            self._check_children()  # a crash just before the stop is still reported
        if self._fleet is not None:
            try:
                self._fleet.close()
            except Exception as exc:
                log.warning("twin: closing its supervisor session: %s", exc)
            self._fleet = None
        if self._control is not None:
            self._control.close()
            self._control = None
        groups = [list(self.agents.values()), list(self.sims.values()), [self.router] if self.router else []]
        for group in groups:
            for p in group:
                self._expected_down.add(p.pid)
                if p.popen.poll() is None:
                    p.popen.terminate()
            for p in group:
                p.stop(STOP_TIMEOUT_S)
                if p.stop_timed_out:
                    log.warning("twin: %s ignored SIGTERM for %.0f s: killed", p.name, STOP_TIMEOUT_S)
        if self._hub is not None:
            self._hub.close()
            self._hub = None
        for e in self.ecat_hosts.values():
            try:
                ecat_down(e)
            except Exception as exc:
                log.warning("twin: removing namespace %s: %s", e.netns, exc)
        if self.workdir:
            shutil.rmtree(self.workdir, ignore_errors=True)

    # ---- children --------------------------------------------------------------------------

    def _argv(self, host: str | None, *argv: str) -> list[str]:
        e = self.ecat_hosts.get(host) if host else None
        return e.exec_argv(*argv) if e else list(argv)

    def _spawn_router(self) -> ChildProcess:
        links = ["--pki", self.pki_copy, "--identity", ROUTER] if self.pki else \
            ["--listen", f"unixsock-stream/{self.router_socket}"]
        return ChildProcess("drives-router", [sys.executable, "-m", "bus_agent.router", "--listen", self.endpoint,
                                              *links, "--log-level", self.log_level], ready_marker="drives-router ready")

    def sim_argv(self, host: str) -> list[str]:
        """The command line of ``host``'s simulator: ``ecat-sim`` in its namespace (``--esi`` with
        its ESI files), or ``canopen-sim --eds`` for a host with EDS files."""
        spec = self.expected.hosts[host]
        control = ["--name", host, "--zenoh-connect", f"unixsock-stream/{self.router_socket}",
                   "--log-level", self.log_level]
        if host in self.can_hosts:
            return [sys.executable, "-m", "bus_agent.sim.canopen.cli", "--channel", self.can_hosts[host],
                    "--interface", "udp_multicast", *sim_device_args(spec), *control]
        argv = [sys.executable, "-m", "bus_agent.sim.cli", "--ifname", self.ecat_hosts[host].sim,
                "--drives", str(len(spec.axes)), *control, "--rt-priority", str(SIM_RT_PRIORITY)]
        if spec.profile:
            argv += ["--profile", spec.profile]
        return self._argv(host, *argv, *sim_device_args(spec))

    def _spawn_sim(self, host: str) -> ChildProcess:
        kind = "canopen-sim" if host in self.can_hosts else "ecat-sim"
        return ChildProcess(f"{kind} {host}", self.sim_argv(host), ready_marker=f"{kind} ready")

    def _spawn_agent(self, host: str) -> ChildProcess:
        argv = [sys.executable, "-m", "bus_agent.cli", "--config", os.path.join(self.workdir, f"{host}.toml"),
                "--log-level", self.log_level]
        return ChildProcess(f"bus-agent {host}", self._argv(host, *argv), ready_marker="bus-agent ready")

    @staticmethod
    def _ready(p: ChildProcess, timeout_s: float) -> bool:
        # wait_ready also wakes at EOF, which a dying child may reach just before it is reaped
        return p.wait_ready(timeout_s) and any(p.ready_marker in line for line in p.lines)

    @staticmethod
    def _not_ready(p: ChildProcess, what: str) -> TwinError:
        try:
            code = p.popen.wait(2)  # a child that closed its output is about to exit: name its code
        except subprocess.TimeoutExpired:
            code = None
        return TwinError(f"twin: {p.name} did not {what} ({'still running' if code is None else f'exit {code}'}):\n"
                         f"{p.output(20)}")

    def _expect_ready(self, p: ChildProcess) -> None:
        if not self._ready(p, self._deadline_left()):
            raise self._not_ready(p, "become ready")

    def _children(self) -> list[ChildProcess]:
        with self._lock:
            return [*([self.router] if self.router else []), *self.sims.values(), *self.agents.values()]

    def _watch(self) -> None:
        while not self._stopping.wait(MONITOR_PERIOD_S):
            self._check_children()

    def _check_children(self) -> None:
        """Record and report every child that exited without being asked to."""
        for p in self._children():
            code = p.popen.poll()
            with self._lock:
                if code is None or p.pid in self._expected_down:
                    continue
                self._expected_down.add(p.pid)
                msg = f"twin: {p.name} exited unexpectedly (exit code {code}); its last output:\n{p.output(15)}"
                self.unexpected_exits.append(msg)
            log.error("%s", msg)
            if self.on_unexpected_exit is not None:
                self.on_unexpected_exit(msg)

    # ---- readiness and state ---------------------------------------------------------------

    @property
    def fleet(self) -> Fleet:
        """The twin's own connected supervisor (client of the router)."""
        if self._fleet is None:
            raise TwinError("twin is not running")
        return self._fleet

    def answering(self, host: str) -> bool:
        """Whether ``host``'s agent is alive with exactly its expected axes, each with a status."""
        f = self.fleet
        axes = list(self.expected.hosts[host].axes)
        return (host in f.hosts() and f.host_axes().get(host) == axes
                and all(f.status(DriveRef(host, a)) is not None for a in axes))

    def wait_answering(self, hosts: Any, timeout_s: float) -> None:
        """Wait until every host of ``hosts`` is :meth:`answering`; TwinError naming the others."""
        hosts = list(hosts)
        if not self.fleet.wait_until(lambda _f: all(self.answering(h) for h in hosts), timeout_s):
            f = self.fleet
            missing = [f"{h} (alive: {h in f.hosts()}, axes: {f.host_axes().get(h)}, "
                       f"expected: {list(self.expected.hosts[h].axes)})" for h in hosts if not self.answering(h)]
            raise TwinError(f"twin: not answering after {timeout_s:.0f} s: {'; '.join(missing)}")

    def wait_state(self, ref: str, state: str, timeout_s: float = 10.0) -> DriveStatus:
        """Wait until drive ``ref`` (``"host/axis"``) reports CiA 402 ``state`` (e.g. ``"fault"``,
        ``"operation_enabled"``); returns that status. TwinError with the last state seen."""
        host, axis = parse_ref(self.expected, ref)
        r = DriveRef(host, axis)
        if not self.fleet.wait_until(lambda f: (st := f.status(r)) is not None and st.state == state, timeout_s):
            st = self.fleet.status(r)
            raise TwinError(f"drive {ref}: not {state} after {timeout_s} s (last: "
                            f"{st.state if st else 'no status'}{', lost' if st and st.lost else ''})")
        st = self.fleet.status(r)
        assert st is not None
        return st

    # ---- fault injection (the drive's simulator) -------------------------------------------

    def inject(self, ref: str, action: str, **args: Any) -> str:
        """Any simulator action on drive ``ref`` (``fault``, ``unplug``, ``plug``, ``wkc_fault``;
        with ecat also ``drop_frames``, ``delay_frames``); returns the simulator's detail."""
        parse_ref(self.expected, ref)
        try:
            # the slave position as the drive's agent published it; any action the simulator serves
            (target,) = sim_targets(self.fleet, [ref])
            session = self._control or self.fleet.session
            return "; ".join(sim_inject(session, target.segment, target.slave, action, **args))
        except Exception as exc:
            raise TwinError(f"drive {ref}: {action} refused: {exc}") from None

    def fault(self, ref: str, code: int = 0x5530) -> str:
        """Make drive ``ref`` fault with 0x603F error ``code`` (CiA 402 transition 13)."""
        return self.inject(ref, "fault", error_code=code)

    def unplug(self, ref: str) -> str:
        """The slave of ``ref`` stops answering (cable or power lost)."""
        return self.inject(ref, "unplug")

    def plug(self, ref: str) -> str:
        """The slave of ``ref`` is back, power-cycled (AL INIT; the agent brings it back to OP)."""
        return self.inject(ref, "plug")

    # ---- network and processes -------------------------------------------------------------

    def cut(self, host: str) -> None:
        """Pull ``host``'s network cable: its agent and the router stop hearing each other; both
        notice when the link lease (3 s) runs out."""
        check_host(self.expected, host)
        assert self._hub is not None
        self._hub.set_cut(host, True)

    def restore(self, host: str) -> None:
        """Plug ``host``'s cable back; its agent reconnects by itself (wait with :meth:`wait_answering`)."""
        check_host(self.expected, host)
        assert self._hub is not None
        self._hub.set_cut(host, False)

    def _kill(self, p: ChildProcess) -> None:
        with self._lock:
            self._expected_down.add(p.pid)
        p.kill()

    def kill_agent(self, host: str) -> None:
        """SIGKILL ``host``'s agent (and its gateway): a crash, no ordered shutdown."""
        check_host(self.expected, host)
        self._kill(self.agents[host])

    def restart_agent(self, host: str, timeout_s: float = 30.0) -> None:
        """Start ``host``'s agent again (stopping it first if it still runs) and wait until it answers."""
        check_host(self.expected, host)
        self._respawn(self.agents[host], lambda: self._spawn_agent(host),
                      lambda p: self.agents.__setitem__(host, p), timeout_s)
        self.wait_answering([host], timeout_s)

    def kill_router(self) -> None:
        """SIGKILL the router: every host loses the others and every supervisor."""
        assert self.router is not None
        self._kill(self.router)

    def restart_router(self, timeout_s: float = 30.0) -> None:
        """Start the router again on the same endpoints and wait until every host answers again."""
        assert self.router is not None
        self._respawn(self.router, self._spawn_router, lambda p: setattr(self, "router", p), timeout_s)
        self.wait_answering(self.expected.hosts, timeout_s)

    def _respawn(self, old: ChildProcess, spawn: Callable[[], ChildProcess], keep: Callable[[ChildProcess], None],
                 timeout_s: float) -> None:
        """Stop ``old`` on purpose (not reported), start its successor, ``keep`` it (so the monitor
        watches it and :meth:`stop` stops it, ready or not) and wait for its readiness line."""
        with self._lock:
            self._expected_down.add(old.pid)
        old.stop(STOP_TIMEOUT_S)
        p = spawn()
        with self._lock:
            keep(p)
        if not self._ready(p, timeout_s):
            raise self._not_ready(p, "restart")

    def pids(self) -> dict[str, int]:
        """Process id of every running child, by name (leftover checks)."""
        return {p.name: p.pid for p in self._children() if p.popen.poll() is None}
