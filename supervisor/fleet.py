"""The supervisor's Python API: discover agents and drives, select, command, lease, watch.

``Fleet`` is the facade of the supervisor: it holds the settings and delegates to its parts,
each owning its state (docs/supervisor.md, "Parts of the Fleet"):

- :class:`~supervisor.link.FleetLink`: one Zenoh session (multicast scouting off), the
  supervisor's liveliness token (``drives/@v1/@sup/<name>``), the subscriptions and gets;
- :class:`~supervisor.view.FleetView`: agents by liveliness token (``drives/@v1/<host>/alive``,
  history replayed), the latest status per drive and agent, host-name conflicts;
- :class:`~supervisor.commands.FleetCommands`: fan-out queries (target ALL, consolidation NONE)
  collected until every addressed drive answered, its agent is gone, or the deadline passed;
- :class:`~supervisor.leases.FleetLeases`: leases and their renewal thread;
- :class:`~supervisor.events.FleetEvents`: listeners and the dispatcher thread they run on;
- the coordination across drives as functions over the Fleet: :mod:`supervisor.orchestration`
  (two-phase enable, ordered shutdown) and :mod:`supervisor.motion` (group moves).

Threading: Zenoh callbacks only decode, update the view under its lock and enqueue; user
callbacks (arrival, departure, status, lease lost) run on the events' dispatcher thread, so they
may call back into the Fleet (never on a Zenoh thread, where that could deadlock).
"""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Any, Callable, Iterable, Mapping, Sequence

import zenoh

from schemas import keys
from schemas.messages import DriveStatus, MODES

from .commands import DEFAULT_TIMEOUT_S, FleetCommands, acting_for
from .events import FleetEvents, Listener
from .fleetfile import ExpectedFleet, load as load_fleet
from .leases import FleetLeases
from .link import FleetError, FleetLink, NoAgentError
from .motion import group_move, move_args, sync_move
from .orchestration import ordered_shutdown, two_phase_enable
from .results import CommandResult, DriveResult, Report, single
from .selectors import (
    DriveRef,
    Selection,
    SelectorError,
    exact_selection,
    parse_selector,
    plan_queries,
    resolve,
    unknown_selector_problems,
)
from .session import DEFAULT_CONNECT, default_name, zenoh_config  # the session settings (re-exported)
from .view import CONFLICT_HOLD_S, AgentInfo, FleetView

log = logging.getLogger(__name__)

DEFAULT_LEASE_TTL_S = 3.0


class Fleet:
    """A supervisor's view of and handle on every agent and drive reachable through Zenoh.

    Use as a context manager::

        with Fleet(connect=["tcp/127.0.0.1:7447"]) as fleet:
            fleet.wait_for_agents(3)
            report = fleet.enable("h1/*", "h2/*")

    Events (``on(event, fn)``): ``arrival(host)``, ``departure(host)``, ``status(DriveStatus)``,
    ``agent(AgentStatus)``, ``lease_lost(DriveResult)``; called on the Fleet's dispatcher thread.
    """

    def __init__(
        self,
        connect: Sequence[str] = DEFAULT_CONNECT,
        name: str | None = None,
        mode: str = "client",
        *,
        listen: Sequence[str] = (),
        groups: Mapping[str, Iterable[str]] | None = None,
        connect_timeout_s: float = 2.0,
        discovery_timeout_s: float = 1.0,
        lease_ttl_s: float = DEFAULT_LEASE_TTL_S,
        expected: "ExpectedFleet | str | os.PathLike[str] | Mapping[str, Any] | None" = None,
        pki: str | os.PathLike[str] | None = None,
        identity: str | None = None,
    ) -> None:
        if (pki is None) != (identity is None):
            raise ValueError("pki and identity go together (a drives-pki directory and a principal in it)")
        if identity is not None:
            keys.validate_name(identity, "identity")
            if name and name != identity:
                raise ValueError(f"name {name!r}: with a pki the supervisor's name is its identity {identity!r}")
            name = identity
        #: The drives-pki directory and principal this supervisor authenticates as (None: insecure).
        self.pki = None if pki is None else str(pki)
        self.identity = identity
        self.name = keys.validate_name(name or default_name(), "supervisor name")
        #: The expected fleet (``supervisor.fleetfile``): absent drives are selectable, listed as
        #: offline and reported ``missing``; hosts outside it are flagged. None: only what is seen.
        self.expected: ExpectedFleet | None = (expected if expected is None or isinstance(expected, ExpectedFleet)
                                               else load_fleet(expected))
        self.mode = mode
        self.connect = tuple(connect)
        self.listen = tuple(listen)
        self.local_groups = {g: list(m) for g, m in (groups or {}).items()}
        self.connect_timeout_s = connect_timeout_s
        self.discovery_timeout_s = discovery_timeout_s
        self.lease_ttl_s = lease_ttl_s
        # The parts (module docstring), each given what it needs.
        self._events = FleetEvents(self.name)
        self._view = FleetView(self.name, self._events.emit, self._departed)
        self._link = FleetLink(self.name, self._view)
        self._commands = FleetCommands(self.name, self.identity, lambda: self.session, self._view,
                                       self.selection_of)
        self._leases = FleetLeases(self.name, lease_ttl_s, self.command, self.selection_of,
                                   self._events.emit)

    def _departed(self, host: str) -> None:
        self._commands.departed(host)  # a command waiting for this agent stops waiting

    # ---- lifecycle -----------------------------------------------------------------------

    def __enter__(self) -> "Fleet":
        self.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def open(self) -> "Fleet":
        """Open the session, declare liveliness and subscriptions, and take a first snapshot.

        Raise :class:`NoAgentError` when no endpoint answers within ``connect_timeout_s``.
        """
        self._link.open(dict(mode=self.mode, connect=self.connect, listen=self.listen,
                             connect_timeout_ms=int(self.connect_timeout_s * 1000), pki=self.pki,
                             identity=self.identity))
        self._events.start()
        self._link.declare()
        self.refresh(self.discovery_timeout_s)
        log.info("supervisor %s: %d agent(s), %d drive(s)", self.name, len(self.hosts()), len(self.roster()))
        return self

    def close(self) -> None:
        """Release held leases (a clean exit runs no lease reaction), then close everything."""
        if not self._link.is_open:
            return
        try:
            if self.leases():
                self.release()
        except Exception:  # closing must finish; the token's loss then triggers the reaction
            log.exception("supervisor %s: releasing leases on close failed", self.name)
        self._leases.stop()
        self._link.close()
        self._events.stop()

    @property
    def session(self) -> zenoh.Session:
        return self._link.session

    def refresh(self, timeout_s: float = 1.0) -> None:
        """Query liveliness tokens, drive status and agent status once (a synchronous snapshot)."""
        self._link.refresh(timeout_s)

    def fetch_status(self, target: "Selection | str | Sequence[str]", timeout_s: float = 2.0) -> dict[DriveRef, DriveStatus]:
        """Ask the agents for the current status of the selected drives (one get per planned key
        expression), merge it into the snapshot and return it. Decisions that depend on a
        drive's state use this, not the snapshot alone: published status may lag or be dropped."""
        sel = self._as_selection(target)
        wanted = set(sel.drives)
        out: dict[DriveRef, DriveStatus] = {}
        for st in self._link.get_status(sel.plan.pairs, timeout_s):
            ref = DriveRef(st.host, st.axis)
            if ref in wanted:
                out[ref] = st
        return out

    def on(self, event: str, fn: Listener) -> None:
        """Register ``fn`` for ``arrival``, ``departure``, ``status``, ``agent`` or ``lease_lost``."""
        self._events.on(event, fn)

    # ---- snapshot (the view) -------------------------------------------------------------

    def hosts(self) -> list[str]:
        """Hosts whose agent is alive now."""
        return self._view.hosts()

    def agents(self) -> dict[str, AgentInfo]:
        return self._view.agents()

    def drives(self) -> dict[DriveRef, DriveStatus]:
        """Last status of every drive seen (including those of agents now gone)."""
        return self._view.drives()

    def status(self, ref: DriveRef | str) -> DriveStatus | None:
        return self._view.status(ref if isinstance(ref, DriveRef) else DriveRef.parse(ref))

    def missed(self) -> dict[DriveRef, int]:
        """Status publications lost per drive (gaps in sequence numbers)."""
        return self._view.missed()

    @property
    def status_count(self) -> int:
        return self._view.status_count

    def supervisors(self) -> list[str]:
        return self._view.supervisors()

    def host_axes(self) -> dict[str, list[str]]:
        """Each live agent's own complete axis list (AgentStatus.axes), where known."""
        return self._view.host_axes()

    def roster(self) -> list[DriveRef]:
        """Drives of live agents: from their status publications and their agent status."""
        return self._view.roster()

    def conflicts(self) -> dict[str, str]:
        """Hosts whose name two agents use (two instance ids within :data:`CONFLICT_HOLD_S`, or an
        agent saying so), with what is known. Commands to them are refused (``rejected``)."""
        return self._view.conflicts()

    def expected_drives(self) -> list[DriveRef]:
        """Drives of the expected fleet ([] without one)."""
        return [DriveRef(h, a) for h, a in self.expected.refs()] if self.expected else []

    def known_drives(self) -> list[DriveRef]:
        """What selectors resolve against: the live roster plus the expected fleet."""
        return sorted(set(self.roster()) | set(self.expected_drives()))

    def absent(self) -> list[DriveRef]:
        """Expected drives that no live agent reports (their agent is offline, or lacks them)."""
        present = set(self.roster())
        return [r for r in self.expected_drives() if r not in present]

    def unexpected_hosts(self) -> list[str]:
        """Live hosts the expected fleet does not list ([] without an expected fleet)."""
        if self.expected is None:
            return []
        return [h for h in self.hosts() if not self.expected.expects(h)]

    def groups(self) -> dict[str, list[str]]:
        """Named groups: the expected fleet's, the agents' (AgentStatus.groups) merged, then the
        local table on top."""
        out: dict[str, list[str]] = {g: list(ms) for g, ms in (self.expected.groups if self.expected else {}).items()}
        for groups in self._view.host_groups():
            for g, members in groups.items():
                out.setdefault(g, [])
                out[g].extend(m for m in members if m not in out[g])
        out.update(self.local_groups)
        return out

    def wait_until(self, predicate: Callable[["Fleet"], bool], timeout_s: float) -> bool:
        """Wait until ``predicate(fleet)`` holds (re-checked on every update) or the deadline."""
        return self._view.wait_until(lambda: predicate(self), timeout_s)

    def wait_for_agents(self, hosts: int | Iterable[str], timeout_s: float = 5.0, drives: int = 0) -> bool:
        """Wait until ``hosts`` (a count or names) are alive and at least ``drives`` are known."""
        if isinstance(hosts, int):
            n = hosts
            return self.wait_until(lambda f: len(f.hosts()) >= n and len(f.roster()) >= drives, timeout_s)
        want = set(hosts)
        return self.wait_until(lambda f: want <= set(f.hosts()) and len(f.roster()) >= drives, timeout_s)

    # ---- selection -----------------------------------------------------------------------

    def check_known(self, *selectors: str) -> None:
        """Raise :class:`SelectorError` with "did you mean" hints when a selector names a drive
        that is neither live nor expected (a concrete name :meth:`select` would address and
        report ``missing``). For front ends that want a typo to be an error (drivectl)."""
        problems = unknown_selector_problems(selectors, self.known_drives(), self.groups())
        if problems:
            raise SelectorError("; ".join(problems))

    def select(self, *selectors: str, allow_empty: bool = False) -> Selection:
        """Resolve selectors against the live roster and the expected fleet; raise
        :class:`SelectorError` (nothing sent)."""
        if len(selectors) == 1 and not isinstance(selectors[0], str):
            selectors = tuple(selectors[0])  # a list passed as one argument
        parsed = [parse_selector(s) for s in selectors]
        drives = resolve(parsed, self.known_drives(), self.groups(), allow_empty=allow_empty)
        return Selection(tuple(s.text for s in parsed), tuple(drives),
                         plan_queries(parsed, drives, self.host_axes()))

    def selection_of(self, refs: Iterable[DriveRef], *, per_host: bool = False) -> Selection:
        """A selection of exactly these drives (one query per host where the host is whole).
        ``per_host``: one ``<host>/drive/*`` query per host whatever the axes (for a command the
        agent narrows itself, a group move's ``targets``)."""
        return exact_selection(refs, self.host_axes() if not per_host else {}, per_host=per_host)

    def _as_selection(self, target: "Selection | str | Sequence[str]") -> Selection:
        if isinstance(target, Selection):
            return target
        if isinstance(target, str):
            return self.select(target)
        return self.select(*target)

    # ---- commands (supervisor.commands) --------------------------------------------------

    def acting_for(self, user: str) -> contextlib.AbstractContextManager[None]:
        """Commands sent from this thread (and threads it starts through ``contextvars``) inside
        the block carry ``user`` as ``on_behalf_of``: a gateway's way to have the agents' audit
        name the person (an OPC UA user) behind its own principal. ``user`` must be a legal name."""
        return acting_for(user)

    def _request(self, op: str, args: Mapping[str, Any] | None, timeout_s: float):
        return self._commands.request(op, args, timeout_s)

    def command(self, op: str, target: "Selection | str | Sequence[str]" = "**",
                args: Mapping[str, Any] | None = None, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Send drive command ``op`` (``schemas.messages.DRIVE_OPS``) to the selection: one
        fan-out query per planned key expression, one result per selected drive. A ``move`` with
        ``sync`` goes through the group move whatever the selectors
        (:func:`supervisor.motion.sync_move`): one group, or refused as a whole."""
        sel = self._as_selection(target)
        if op == "move" and (args or {}).get("sync"):
            return sync_move(self, sel.drives, dict(args or {}), timeout_s=timeout_s)
        return self.send(op, sel, args, timeout_s)

    def send(self, op: str, sel: Selection, args: Mapping[str, Any] | None = None,
             timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Send ``op`` as ``sel`` plans it (its queries as they are). A synchronized move comes
        here only from the group path, with the axes named per host (``targets`` or ``axes``):
        planned otherwise it would start as several groups (ValueError)."""
        return self._commands.send(op, sel, args, timeout_s)

    def enable(self, *selectors: str, timeout_s: float = DEFAULT_TIMEOUT_S,
               stages: Sequence[Sequence[str]] | None = None,
               before_phase: Callable[[str], None] | None = None):
        """Two-phase enable (see :func:`supervisor.orchestration.two_phase_enable`)."""
        return two_phase_enable(self, selectors or ("**",), timeout_s=timeout_s, stages=stages,
                                before_phase=before_phase)

    def take_down(self, stages: Sequence[Sequence[str] | str], *, op: str = "disable",
                  timeout_s: float = DEFAULT_TIMEOUT_S) -> Report:
        """Ordered take-down, last stage first, each stage with ``op`` (default ``disable``: to
        Switch on disabled). See :func:`supervisor.orchestration.ordered_shutdown`."""
        return ordered_shutdown(self, stages, op=op, timeout_s=timeout_s)

    def shutdown(self, *selectors: str, stages: Sequence[Sequence[str] | str] | None = None,
                 timeout_s: float = DEFAULT_TIMEOUT_S) -> Report:
        """The CiA 402 Shutdown command (transitions 2, 6, 8: to Ready to switch on), as ``drivectl
        shutdown``: to the selected drives, or stage by stage, last stage first. For the take-down
        to Switch on disabled use :meth:`disable` or :meth:`take_down`."""
        if any(not isinstance(s, str) for s in selectors):
            raise TypeError("Fleet.shutdown(*selectors, stages=...) sends the CiA 402 shutdown (to Ready to "
                            "switch on); for the ordered take-down to Switch on disabled use "
                            "Fleet.take_down(stages)")
        if stages:
            return ordered_shutdown(self, stages, op="shutdown", timeout_s=timeout_s)
        return single("shutdown", self.command("shutdown", selectors or "**", timeout_s=timeout_s))

    def switch_on(self, *selectors: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        return self.command("switch_on", selectors or "**", timeout_s=timeout_s)

    def disable(self, *selectors: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        return self.command("disable", selectors or "**", timeout_s=timeout_s)

    def quick_stop(self, *selectors: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Quick stop (controlword bit 2 low, transition 11) on every selected drive, default all."""
        return self.command("quick_stop", selectors or "**", timeout_s=timeout_s)

    def halt(self, *selectors: str, on: bool = True, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Halt (controlword bit 8) on or off."""
        return self.command("halt", selectors or "**", {"on": bool(on)}, timeout_s=timeout_s)

    # -- motion (docs/motion.md; the agents generate the trajectories)

    def move(self, *selectors: str, to: float | None = None, by: float | None = None,
             velocity: float | None = None, accel: float | None = None, jerk: float | None = None,
             sync: bool = False, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Move to ``to`` (absolute) or ``by`` (relative), in each axis's unit; ``velocity``,
        ``accel``, ``jerk`` default to the axis limits (above them: clamped or rejected by the
        axis). ``sync``: every selected axis, on whatever hosts, starts together and arrives
        together (one group move; a drive or host that cannot take part refuses the whole
        move, nothing moves). Done when in the position window at rest; ``timeout_s`` must
        cover the move."""
        return self.command("move", selectors or "**", move_args(to, by, velocity, accel, jerk, sync),
                            timeout_s=timeout_s)

    def jog(self, *selectors: str, velocity: float, for_s: float | None = None,
            timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Jog at ``velocity`` (signed, unit/s) for ``for_s`` (default: until ``timeout_s`` less
        the time to stop), then stop; done at rest. A halt or stop ends it (aborted)."""
        args: dict[str, Any] = {"velocity": float(velocity)}
        if for_s is not None:
            args["for_s"] = float(for_s)
        return self.command("jog", selectors or "**", args, timeout_s=timeout_s)

    def stop(self, *selectors: str, release: bool = False, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """PLCopen MC_Stop: abort motion, decelerate, and refuse motion until ``release``."""
        return self.command("stop", selectors or "**", {"release": True} if release else {}, timeout_s=timeout_s)

    def home(self, *selectors: str, method: int | None = None, timeout_s: float = 30.0) -> CommandResult:
        """Home (mode 6) with the axis's configured method, or ``method`` (0x6098)."""
        return self.command("home", selectors or "**", {} if method is None else {"method": int(method)},
                            timeout_s=timeout_s)

    def group_move(self, targets: Mapping[DriveRef | str, float], *, velocity: float | None = None,
                   accel: float | None = None, jerk: float | None = None, timeout_s: float = 30.0) -> CommandResult:
        """Synchronized move of ``{ref: absolute target}`` across any hosts: all start together
        and arrive together (see :func:`supervisor.motion.group_move`)."""
        return group_move(self, targets, velocity=velocity, accel=accel, jerk=jerk, timeout_s=timeout_s)

    def fault_reset(self, *selectors: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Fault reset (controlword bit 7 rising edge, transition 15), made by the agent."""
        return self.command("fault_reset", selectors or "**", timeout_s=timeout_s)

    def set_mode(self, mode: int, *selectors: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Modes of operation 0x6060, done on the 0x6061 echo."""
        if isinstance(mode, bool) or not isinstance(mode, int) or mode not in MODES:
            raise ValueError(f"mode {mode!r} is not one of {', '.join(map(str, MODES))}")
        return self.command("set_mode", selectors or "**", {"mode": mode}, timeout_s=timeout_s)

    def nmt(self, command: str, hosts: Sequence[str] = ("*",), axis: str | int | None = None,
            timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Network management on agents (``.../agent/cmd/nmt``): start (-> OP), stop
        (-> SAFE-OP), preop, reset_comm, reset_node (cia402.md section 5), for the slave of one
        axis (a name, or a slave position looked up in the drive status) or the whole segment.
        One result per agent (``axis`` '')."""
        return self._commands.nmt(command, hosts, axis, timeout_s)

    # ---- leases (supervisor.leases) ------------------------------------------------------

    def lease(self, *selectors: str, ttl_s: float | None = None, takeover: bool = False,
              timeout_s: float = 2.0) -> CommandResult:
        """Take (or with ``takeover`` seize) exclusive control of the selected drives.

        Leases are renewed every ttl/3 by a background thread while this Fleet is open; a drive
        whose renewal answers ``busy`` was taken over and is reported through ``lease_lost``.
        When this process dies, its liveliness token vanishes and the agents run the lease
        reaction at once (or at the latest when the ttl runs out).
        """
        return self._leases.lease(self._as_selection(selectors or "**"), float(ttl_s or self.lease_ttl_s),
                                  takeover, timeout_s)

    def leases(self) -> list[DriveRef]:
        """Drives whose lease this supervisor holds (as far as it knows)."""
        return self._leases.held()

    def release(self, *selectors: str, timeout_s: float = 2.0) -> CommandResult:
        """Give leases back (no reaction runs); default every lease held."""
        sel = self._as_selection(selectors) if selectors else self.selection_of(self.leases())
        return self._leases.release(sel, timeout_s)


__all__ = ["Fleet", "Selection", "AgentInfo", "FleetError", "NoAgentError", "SelectorError",
           "DriveRef", "DriveResult", "CommandResult", "zenoh_config", "default_name", "CONFLICT_HOLD_S",
           "DEFAULT_LEASE_TTL_S"]
