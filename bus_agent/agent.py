"""The bus agent: one EtherCAT segment (or simulated drives), its cycle, its gateway, one Zenoh session.

Life cycle (explicit, :class:`AgentState`)::

    created --start()--> running --stop()--> stopped
       |                     (start error: everything opened so far is closed, AgentError)

Two compositions (``AgentConfig.gateway``, docs/agent-gateway.md "Process model"):

- ``"process"`` (default): the gateway runs in a child process (``bus_agent.gateway.bridge``); this
  process holds only the bus, the cycle thread and the bridge's two threads, and never opens
  a Zenoh session. If the child dies, :attr:`Agent.failure` says so, ``on_failure`` is called
  and the caller (the CLI) runs the ordered shutdown and exits non-zero.
- ``"thread"``: the gateway's threads and the Zenoh session in this process (tests, debugging).

Start: open the bus and bring it to OP (identity checked, AL errors named) -> open the Zenoh
session -> declare the gateway (publishers, queryables, liveliness) -> start the cycle thread
-> with a simulated bus, serve fault injection on ``drives/@sim/<host>/*/*``. (Process mode
starts the cycle thread first, then the gateway process, which opens the session and declares.)
Stop (SIGINT/SIGTERM in the CLI): refuse new commands -> ordered shutdown of every drive
(disable operation, shutdown, disable voltage) while the gateway still publishes it -> AL
INIT, close the bus -> publish the last status -> undeclare everything -> close the session.
"""

from __future__ import annotations

import logging
import threading
from enum import Enum
from typing import Any, Callable

from bus_agent.gateway.bridge import BridgeError, GatewayProcess
from bus_agent.gateway.wire import READY_TIMEOUT_S
from bus_agent.gateway.zenoh_config import zenoh_error_text
from bus_agent.bus.base import Bus, BusError
from bus_agent.config import AgentConfig, ConfigError
from bus_agent.cycle.cycle import Cycle
from bus_agent.cycle.realtime import helper_priority
from bus_agent.startup_guard import StartupAbandoned, StartupSteps

log = logging.getLogger(__name__)

#: After an abandoned start-up: how long the gateway process gets to exit before it is killed.
ABANDON_BRIDGE_TIMEOUT_S = 0.2
#: Deadline of the gateway's start-up step (the bridge's own ready timeout, and a margin).
GATEWAY_START_S = READY_TIMEOUT_S + 2.0


class AgentError(RuntimeError):
    """A start-up failure, with a message that says what and where (bus, identity, AL, zenoh)."""


class AgentState(str, Enum):
    CREATED = "created"
    RUNNING = "running"
    STOPPED = "stopped"


def make_bus(config: AgentConfig) -> Bus:
    """The backend the configuration asks for: a NIC (pysoem), a CAN bus (canopen) or simulated drives."""
    if config.can is not None:
        try:
            from bus_agent.bus.canopen.bus import canopen_bus
        except ImportError as exc:
            raise AgentError(f"canopen backend unavailable: {exc}") from None
        return canopen_bus(config.can)
    if config.ifname:
        try:
            from bus_agent.bus.pysoem_bus import PysoemBus
        except ImportError as exc:
            raise AgentError(f"pysoem backend unavailable: {exc}") from None
        return PysoemBus(config.ifname, soem_call_s=config.soem_call_s)
    from bus_agent.bus.sim_bus import SimBus

    return SimBus(config.sim_drives, config.sim_profile, segment_name=config.host)


def _run_checked(fn: Callable[[], None], steps: StartupSteps) -> None:
    """``fn()`` on a helper thread while this one checks ``steps`` (a stop signal, the deadline):
    a wait that cannot look at them itself (the gateway process's readiness) ends with
    :class:`StartupAbandoned`; the caller then closes what ``fn`` opened (the helper thread's
    late error, if any, is dropped)."""
    done = threading.Event()
    error: list[BaseException] = []

    def run() -> None:
        try:
            fn()
        except BaseException as exc:
            error.append(exc)
        finally:
            done.set()

    threading.Thread(target=run, name="startup-step", daemon=True).start()
    while not done.wait(0.05):
        steps.check()
    if error:
        raise error[0]


class Agent:
    """One bus agent. ``bus``: inject a backend (tests); default from the configuration.
    ``on_failure(reason)``: called once, from a bridge thread, if the gateway process dies."""

    def __init__(self, config: AgentConfig, bus: Bus | None = None,
                 on_failure: Callable[[str], None] | None = None) -> None:
        self.config = config
        self.bus = bus
        self.on_failure = on_failure
        self.state = AgentState.CREATED
        self.cycle: Cycle | None = None
        self.session: Any = None        # zenoh.Session, thread mode only
        self.gateway: Any = None        # gateway.Gateway, thread mode only
        self.bridge: GatewayProcess | None = None  # process mode only
        self.sim_control: Any = None
        self._stop_lock = threading.Lock()

    @property
    def axes(self) -> tuple[str, ...]:
        return self.cycle.axes if self.cycle else ()

    def start(self, steps: StartupSteps | None = None) -> None:
        """Bring everything up; raise :class:`AgentError` (after closing what was opened).

        ``steps``: the start-up's steps and deadlines (the CLI's, guarded, ends on a stop signal);
        the bus and the gateway start go through it. Raises :class:`StartupAbandoned` when it
        ends start-up (after closing what was opened)."""
        cfg = self.config
        steps = steps or StartupSteps()
        try:
            self._start(steps)
        except StartupAbandoned:
            # a gateway process not ready yet has nothing to publish: not waited for
            self._abort(bridge_timeout_s=ABANDON_BRIDGE_TIMEOUT_S)
            raise
        finally:
            steps.finish()
        self.state = AgentState.RUNNING
        assert self.bus is not None
        log.info("agent %s running: %d drive(s) on %s, gateway in %s", cfg.host, len(self.axes), self.bus.backend,
                 f"process {self.bridge.pid}" if self.bridge else "this process")

    def _start(self, steps: StartupSteps) -> None:
        cfg = self.config
        try:
            self.bus = self.bus or make_bus(cfg)
            if hasattr(self.bus, "startup_steps"):
                self.bus.startup_steps = steps  # type: ignore[attr-defined]
            self.cycle = Cycle(self.bus, cfg, rt_priority=cfg.rt_priority)
            self.cycle.express_reflex = cfg.express_reflex
            self.cycle.spin_at_rest = cfg.spin_at_rest
            self.cycle.open()
        except (BusError, ConfigError, ValueError, OSError) as exc:
            self._abort()
            raise AgentError(f"agent {cfg.host}: bus start-up failed: {exc}") from None
        if cfg.gateway == "process":
            self._start_process_gateway(steps)
        else:
            with steps.step("zenoh session and gateway", GATEWAY_START_S):
                self._start_thread_gateway()

    def _zenoh_error(self, exc: object) -> AgentError:
        z = self.config.zenoh
        return AgentError(f"agent {self.config.host}: zenoh session failed (listen {', '.join(z.listen) or '-'}, "
                          f"connect {', '.join(z.connect) or '-'}): {zenoh_error_text(exc)}")

    def _start_process_gateway(self, steps: StartupSteps) -> None:
        assert self.cycle is not None and self.bus is not None
        sim = self.bus.control_handlers() if self.bus.backend == "sim" and hasattr(self.bus, "control_handlers") \
            else None
        self.bridge = GatewayProcess(self.cycle, self._gateway_settings(), self.config.zenoh, sim_handlers=sim,
                                     n_slaves=len(self.cycle.slaves), on_lost=self._gateway_lost,
                                     rt_priority=helper_priority(self.cycle.rt_priority))
        try:
            # The cycle first: the child needs a second or so to import and open its session, far
            # beyond a slave's SM watchdog (~100 ms) without process data. Drives stay disabled
            # until a command comes, and commands come only through the gateway.
            self.cycle.start()
            with steps.step("gateway process (zenoh session, declarations)", GATEWAY_START_S):
                _run_checked(self.bridge.start, steps)
        except StartupAbandoned:
            raise
        except BridgeError as exc:
            self._abort()
            if exc.what == "zenoh":
                raise self._zenoh_error(exc) from None
            raise AgentError(f"agent {self.config.host}: start-up failed: {exc}") from None
        except Exception as exc:
            self._abort()
            raise AgentError(f"agent {self.config.host}: start-up failed: {exc}") from None

    def _start_thread_gateway(self) -> None:
        import zenoh

        from bus_agent.gateway.gateway import Gateway, GatewaySettings
        from bus_agent.gateway.zenoh_config import ZenohConfigError, from_settings

        assert self.cycle is not None and self.bus is not None
        cfg = self.config
        try:
            self.session = zenoh.open(from_settings(cfg.zenoh))
        except (ZenohConfigError, zenoh.ZError) as exc:
            self._abort()
            raise self._zenoh_error(exc) from None
        try:
            self.gateway = Gateway(self.session, self.cycle, GatewaySettings(**self._gateway_settings()))
            self.gateway.start()
            self.cycle.start()
            if self.bus.backend == "sim" and hasattr(self.bus, "control_handlers"):
                from bus_agent.sim.control import SimControl

                self.sim_control = SimControl(self.session, cfg.host, self.bus.control_handlers(),
                                              len(self.cycle.slaves))
        except Exception as exc:
            self._abort()
            raise AgentError(f"agent {cfg.host}: start-up failed: {exc}") from None

    def _gateway_settings(self) -> dict[str, Any]:
        """``GatewaySettings`` keyword arguments (plain data: they cross to the gateway process)."""
        assert self.cycle is not None
        cfg = self.config
        drives = cfg.drive_configs(len(self.cycle.slaves))
        return dict(
            host=cfg.host, axes=self.cycle.axes,
            heartbeat_s=cfg.heartbeat_s, agent_period_s=cfg.heartbeat_s, backend=self.bus.backend if self.bus else "",
            cycle_us=cfg.cycle_us, groups={g: tuple(ms) for g, ms in cfg.groups.items()},
            lease_reaction={d.axis: d.policy.lease_reaction for d in drives},
            lease_ttl_s={d.axis: d.policy.lease_ttl_s for d in drives},
            has_connect=bool(cfg.zenoh.connect),
            secure=bool(cfg.zenoh.pki),
        )

    def _gateway_lost(self, reason: str) -> None:
        if self.on_failure is not None:
            self.on_failure(reason)

    @property
    def failure(self) -> str | None:
        """Why the agent must stop, or None: the cycle thread died, or the gateway process did."""
        if self.cycle is not None and self.cycle.state == "error":
            return f"the cycle failed: {self.cycle.error}"
        if self.bridge is not None and self.bridge.lost_reason:
            return self.bridge.lost_reason
        return None

    @property
    def failed(self) -> bool:
        """The cycle thread or the gateway process died (the log says why): the agent must stop."""
        return self.failure is not None

    def stop(self, ordered: bool = True) -> None:
        """Ordered shutdown (see the module docstring). Idempotent."""
        with self._stop_lock:
            if self.state is AgentState.STOPPED:
                return
            if self.bridge is not None:
                self.bridge.stop_commands()
            gw = self.gateway
            if gw is not None:
                gw.stop_commands()
                gw.agent_state_override = "stopping"
            if self.cycle is not None:
                log.info("agent %s: ordered shutdown", self.config.host)
                self.cycle.stop(ordered=ordered)
                if self.bridge is not None and self.bridge.lost_reason and self.cycle.latest is not None:
                    log.warning("agent %s: drives at stop: %s", self.config.host, ", ".join(
                        f"{d.axis}={'lost' if d.lost else d.state}" for d in self.cycle.latest.drives))
            self._close_zenoh()
            self.state = AgentState.STOPPED
            log.info("agent %s stopped", self.config.host)

    def _close_zenoh(self, bridge_timeout_s: float = 10.0) -> None:
        if self.bridge is not None:
            self.bridge.close(bridge_timeout_s)
            self.bridge = None
        if self.sim_control is not None:
            self.sim_control.close()
            self.sim_control = None
        if self.gateway is not None:
            self.gateway.close()
            self.gateway = None
        if self.session is not None:
            try:
                self.session.close()
            except Exception as exc:
                log.warning("zenoh session close: %s", exc)
            self.session = None

    def _abort(self, bridge_timeout_s: float = 10.0) -> None:
        """Close what a failed start opened: drives were never enabled, so no ordered sequence."""
        try:
            if self.cycle is not None:
                self.cycle.stop(ordered=False)
            elif self.bus is not None:
                self.bus.close()
        except Exception as exc:
            log.warning("agent %s: closing after a failed start: %s", self.config.host, exc)
        self._close_zenoh(bridge_timeout_s)
        self.state = AgentState.STOPPED
