"""The supervisor's Python API: discover agents and drives, select, command, lease, watch.

``Fleet`` is the imperative shell around the pure parts (``selectors``, ``results``): one Zenoh
session (multicast scouting off), agent discovery through liveliness tokens
(``drives/@v1/<host>/alive``, history replayed), a fleet snapshot kept current by subscribing to
every drive and agent status (plus one get at start), commands as fan-out queries
(target ALL, consolidation NONE) collected until every addressed drive answered, its agent is
gone, or the deadline passed, and leases held by a background renewal thread while the
supervisor's own liveliness token (``drives/@v1/@sup/<name>``) is alive.

Threading: Zenoh callbacks only decode, update state under one lock and enqueue; user callbacks
(arrival, departure, status, lease lost) run on the Fleet's own dispatcher thread, so they may
call back into the Fleet (never on a Zenoh thread, where that could deadlock).
"""

from __future__ import annotations

import itertools
import logging
import os
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping, Sequence, TypeVar

import zenoh

from bus_agent.gateway.zenoh_config import zenoh_error_text
from schemas import keys
from schemas.messages import (
    AgentStatus,
    DriveStatus,
    SchemaError,
    decode,
)

from .fleetfile import ExpectedFleet, load as load_fleet
from .session import DEFAULT_CONNECT, default_name, zenoh_config  # the session settings (re-exported)
from .commands import FleetCommands
from .results import CommandResult, DriveResult
from .selectors import (
    DriveRef,
    QueryPlan,
    Selector,
    SelectorError,
    parse_selector,
    plan_queries,
    resolve,
    unknown_selector_problems,
)

log = logging.getLogger(__name__)

T = TypeVar("T")

DEFAULT_LEASE_TTL_S = 3.0
#: Two agent instances seen under one host name within this window are a conflict (agents
#: publish their status every second).
CONFLICT_HOLD_S = 3.5
#: Depth of the status subscriber's FIFO (samples): a few status bursts of a 1024-drive fleet.
STATUS_FIFO = 65536


class FleetError(RuntimeError):
    """The fleet could not be reached or a command could not be sent."""


class NoAgentError(FleetError):
    """No router/agent answered: nothing to supervise."""


@dataclass
class AgentInfo:
    """What the supervisor knows about one agent (host)."""

    host: str
    alive: bool
    status: AgentStatus | None = None
    seen_monotonic: float = 0.0
    gone_monotonic: float | None = None


@dataclass(frozen=True)
class Selection:
    """Drives chosen by selectors at one moment, and the queries that address exactly them."""

    selectors: tuple[str, ...]
    drives: tuple[DriveRef, ...]
    plan: QueryPlan

    def __len__(self) -> int:
        return len(self.drives)


Listener = Callable[..., None]


class Fleet(FleetCommands):
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
        self._lock = threading.Condition()
        self._collectors: set[Any] = set()   # commands waiting for replies (FleetCommands._query)
        self._agents: dict[str, AgentInfo] = {}
        self._drives: dict[DriveRef, DriveStatus] = {}
        self._missed: dict[DriveRef, int] = {}
        # host -> agent instance id -> (last seen monotonic, the agent's own conflict text)
        self._instances: dict[str, dict[str, tuple[float, str]]] = {}
        self._status_count = 0
        self._supervisors: set[str] = set()
        self._listeners: dict[str, list[Listener]] = {}
        self._events: queue.SimpleQueue[tuple[str, tuple[Any, ...]] | None] = queue.SimpleQueue()
        self._session: zenoh.Session | None = None
        self._decls: list[Any] = []
        self._token: Any = None
        self._dispatcher: threading.Thread | None = None
        self._drainer: threading.Thread | None = None
        self._renewer: threading.Thread | None = None
        self._stop = threading.Event()
        self._leases: dict[DriveRef, float] = {}  # drive -> ttl_s, leases this supervisor holds
        self._lease_selectors: list[tuple[str, ...]] = []
        self._rid = itertools.count(1)

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
        try:
            self._session = zenoh.open(zenoh_config(self.mode, self.connect, self.listen,
                                                    int(self.connect_timeout_s * 1000), pki=self.pki,
                                                    identity=self.identity))
        except zenoh.ZError as exc:
            raise NoAgentError(f"cannot reach {', '.join(self.connect)} ({zenoh_error_text(exc)}); check that "
                               "a router or bus agent is running and listening there (bus-agent --sim listens "
                               f"on {DEFAULT_CONNECT[0]}), or give --connect"
                               + (f"; as {self.identity}: check that the router trusts the CA of {self.pki} and "
                                  "that its certificate names the address dialled" if self.identity else
                                  "; a secure router (tls/) needs --pki DIR --identity NAME")) from None
        s = self._session
        self._dispatcher = threading.Thread(target=self._dispatch, name=f"fleet-{self.name}-events", daemon=True)
        self._dispatcher.start()
        self._token = s.liveliness().declare_token(keys.supervisor_alive(self.name))
        self._decls.append(s.liveliness().declare_subscriber(keys.ALL_ALIVE, self._on_alive, history=True))
        self._decls.append(s.liveliness().declare_subscriber(keys.ALL_SUPERVISORS, self._on_supervisor, history=True))
        # Status goes through a deep FIFO drained by our own thread: a burst (every drive of a
        # large fleet changing at once) is absorbed here instead of backing up into the router,
        # which drops samples published with congestion control DROP towards a slow subscriber.
        status_sub = s.declare_subscriber(keys.ALL_DRIVE_STATUS, zenoh.handlers.FifoChannel(STATUS_FIFO))
        self._decls.append(status_sub)
        self._drainer = threading.Thread(target=self._drain, args=(status_sub,), name=f"fleet-{self.name}-status",
                                         daemon=True)
        self._drainer.start()
        self._decls.append(s.declare_subscriber(keys.ALL_AGENT_STATUS, self._on_agent_sample))
        self.refresh(self.discovery_timeout_s)
        log.info("supervisor %s: %d agent(s), %d drive(s)", self.name, len(self.hosts()), len(self.roster()))
        return self

    def close(self) -> None:
        """Release held leases (a clean exit runs no lease reaction), then close everything."""
        if self._session is None:
            return
        try:
            if self._leases:
                self.release()
        except Exception:  # closing must finish; the token's loss then triggers the reaction
            log.exception("supervisor %s: releasing leases on close failed", self.name)
        self._stop.set()
        if self._renewer is not None:
            self._renewer.join(timeout=5)
        for d in self._decls:
            try:
                d.undeclare()
            except Exception:
                pass
        self._decls.clear()
        if self._drainer is not None:
            self._drainer.join(timeout=5)
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        self._session.close()
        self._session = None
        self._events.put(None)
        if self._dispatcher is not None:
            self._dispatcher.join(timeout=5)

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise FleetError("fleet is not open")
        return self._session

    def refresh(self, timeout_s: float = 1.0) -> None:
        """Query liveliness tokens, drive status and agent status once (a synchronous snapshot)."""
        s = self.session
        for reply in s.liveliness().get(keys.ALL_ALIVE, timeout=timeout_s):
            if reply.ok is not None:
                self._host_alive(str(reply.ok.key_expr), True)
        for selector, handler in ((keys.ALL_DRIVE_STATUS, self._on_status_sample),
                                  (keys.ALL_AGENT_STATUS, self._on_agent_sample)):
            for reply in s.get(selector, target=zenoh.QueryTarget.ALL,
                               consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
                if reply.ok is not None:
                    handler(reply.ok)

    def fetch_status(self, target: "Selection | str | Sequence[str]", timeout_s: float = 2.0) -> dict[DriveRef, DriveStatus]:
        """Ask the agents for the current status of the selected drives (one get per planned key
        expression), merge it into the snapshot and return it. Decisions that depend on a
        drive's state use this, not the snapshot alone: published status may lag or be dropped."""
        sel = self._as_selection(target)
        wanted = set(sel.drives)
        out: dict[DriveRef, DriveStatus] = {}
        for host, axis in sel.plan.pairs:
            for reply in self.session.get(keys.drive_status(host, axis), target=zenoh.QueryTarget.ALL,
                                          consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
                if reply.ok is None:
                    continue
                try:
                    st = decode(reply.ok.payload.to_bytes(), DriveStatus)
                except SchemaError as exc:
                    log.warning("supervisor %s: bad status on %s: %s", self.name, reply.ok.key_expr, exc)
                    continue
                ref = DriveRef(st.host, st.axis)
                if ref in wanted:
                    out[ref] = st
                self._apply_status(st)  # decoded once
        return out

    # ---- events --------------------------------------------------------------------------

    def on(self, event: str, fn: Listener) -> None:
        """Register ``fn`` for ``arrival``, ``departure``, ``status``, ``agent`` or ``lease_lost``."""
        if event not in ("arrival", "departure", "status", "agent", "lease_lost"):
            raise ValueError(f"unknown event {event!r}")
        with self._lock:
            self._listeners.setdefault(event, []).append(fn)

    def _emit(self, event: str, *args: Any) -> None:
        if self._listeners.get(event):
            self._events.put((event, args))

    def _dispatch(self) -> None:
        while True:
            item = self._events.get()
            if item is None:
                return
            event, args = item
            for fn in list(self._listeners.get(event, ())):
                try:
                    fn(*args)
                except Exception:
                    log.exception("supervisor %s: %s listener failed", self.name, event)

    # ---- zenoh callbacks (decode, update under the lock, enqueue; nothing blocking) ------

    def _host_alive(self, key: str, alive: bool) -> None:
        try:
            parsed = keys.parse(key)
        except keys.InvalidKey:
            log.warning("supervisor %s: ignoring liveliness key %s", self.name, key)
            return
        if parsed.kind is not keys.KeyKind.ALIVE or parsed.host is None:
            return
        host = parsed.host
        now = time.monotonic()
        with self._lock:
            info = self._agents.get(host)
            was = info.alive if info else False
            if info is None:
                info = self._agents[host] = AgentInfo(host, alive, seen_monotonic=now)
            info.alive = alive
            if alive and not was:
                info.seen_monotonic, info.gone_monotonic = now, None
                # An agent that comes back starts its sequence numbers anew.
                for ref in [r for r in self._drives if r.host == host]:
                    self._missed.pop(ref, None)
            elif not alive and was:
                info.gone_monotonic = now
                self._instances.pop(host, None)  # a restarted agent is not a second one
                for col in self._collectors:  # a command waiting for this agent stops waiting
                    with col.cv:
                        col.cv.notify_all()
            self._lock.notify_all()
        if alive and not was:
            log.info("agent %s arrived", host)
            self._emit("arrival", host)
        elif was and not alive:
            log.warning("agent %s is gone", host)
            self._emit("departure", host)

    def _drain(self, sub: Any) -> None:
        for sample in sub:  # ends when the subscriber is undeclared
            try:
                self._on_status_sample(sample)
            except Exception:
                log.exception("supervisor %s: status handling failed", self.name)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        self._host_alive(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    def _on_supervisor(self, sample: zenoh.Sample) -> None:
        try:
            parsed = keys.parse(str(sample.key_expr))
        except keys.InvalidKey:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._supervisors.add(parsed.name or "")
            else:
                self._supervisors.discard(parsed.name or "")

    def _decoded(self, sample: zenoh.Sample, cls: type[T], what: str) -> T | None:
        """A put's message, or None (a delete, or a payload that is not a valid ``cls``: logged)."""
        if sample.kind != zenoh.SampleKind.PUT:
            return None
        try:
            return decode(sample.payload.to_bytes(), cls)
        except SchemaError as exc:
            log.warning("supervisor %s: bad %s on %s: %s", self.name, what, sample.key_expr, exc)
            return None

    def _on_status_sample(self, sample: zenoh.Sample) -> None:
        st = self._decoded(sample, DriveStatus, "status")
        if st is not None:
            self._apply_status(st)

    def _apply_status(self, st: DriveStatus) -> None:
        """Take a drive's status into the view (unless older than what is there) and emit it."""
        ref = DriveRef(st.host, st.axis)
        with self._lock:
            old = self._drives.get(ref)
            restarted = ref not in self._missed
            if old is not None and not restarted and st.seq <= old.seq:
                return  # a get reply older than, or equal to, what the subscription brought
            if old is not None and not restarted and st.seq > old.seq + 1:
                self._missed[ref] = self._missed.get(ref, 0) + (st.seq - old.seq - 1)
            else:
                self._missed.setdefault(ref, 0)
            self._drives[ref] = st
            self._status_count += 1
            self._lock.notify_all()
        self._emit("status", st)

    def _on_agent_sample(self, sample: zenoh.Sample) -> None:
        st = self._decoded(sample, AgentStatus, "agent status")
        if st is None:
            return
        with self._lock:
            if st.instance:
                self._instances.setdefault(st.host, {})[st.instance] = (time.monotonic(), st.conflict)
            info = self._agents.get(st.host)
            if info is None:
                # Status before the liveliness token: known, not yet counted alive.
                info = self._agents[st.host] = AgentInfo(st.host, False, seen_monotonic=time.monotonic())
            if info.status is not None and 0 < st.seq <= info.status.seq and info.alive:
                return
            info.status = st
            self._lock.notify_all()
        self._emit("agent", st)

    # ---- snapshot ------------------------------------------------------------------------

    def hosts(self) -> list[str]:
        """Hosts whose agent is alive now."""
        with self._lock:
            return sorted(h for h, a in self._agents.items() if a.alive)

    def agents(self) -> dict[str, AgentInfo]:
        with self._lock:
            return {h: AgentInfo(a.host, a.alive, a.status, a.seen_monotonic, a.gone_monotonic)
                    for h, a in self._agents.items()}

    def drives(self) -> dict[DriveRef, DriveStatus]:
        """Last status of every drive seen (including those of agents now gone)."""
        with self._lock:
            return dict(self._drives)

    def status(self, ref: DriveRef | str) -> DriveStatus | None:
        ref = ref if isinstance(ref, DriveRef) else DriveRef.parse(ref)
        with self._lock:
            return self._drives.get(ref)

    def missed(self) -> dict[DriveRef, int]:
        """Status publications lost per drive (gaps in sequence numbers)."""
        with self._lock:
            return dict(self._missed)

    @property
    def status_count(self) -> int:
        with self._lock:
            return self._status_count

    def supervisors(self) -> list[str]:
        with self._lock:
            return sorted(self._supervisors)

    def host_axes(self) -> dict[str, list[str]]:
        """Each live agent's own complete axis list (AgentStatus.axes), where known."""
        with self._lock:
            return {h: list(a.status.axes) for h, a in self._agents.items()
                    if a.alive and a.status is not None and a.status.axes}

    def roster(self) -> list[DriveRef]:
        """Drives of live agents: from their status publications and their agent status."""
        with self._lock:
            alive = {h for h, a in self._agents.items() if a.alive}
            refs = {r for r in self._drives if r.host in alive}
            for h in alive:
                st = self._agents[h].status
                if st is not None:
                    refs.update(DriveRef(h, ax) for ax in st.axes)
            return sorted(refs)

    def conflicts(self) -> dict[str, str]:
        """Hosts whose name two agents use (two instance ids within :data:`CONFLICT_HOLD_S`, or an
        agent saying so), with what is known. Commands to them are refused (``rejected``)."""
        now = time.monotonic()
        out: dict[str, str] = {}
        with self._lock:
            for host, seen in self._instances.items():
                if not (host in self._agents and self._agents[host].alive):
                    continue  # a departed host (its last status may still come in) commands nothing
                recent = {i: c for i, (t, c) in seen.items() if now - t < CONFLICT_HOLD_S}
                said = [c for c in recent.values() if c]
                if len(recent) > 1:
                    out[host] = (f"host name {host} is used by {len(recent)} agents (instances "
                                 f"{', '.join(sorted(recent))}): not commanded until one stops")
                elif said:
                    out[host] = said[0]
        return out

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
        with self._lock:
            for a in self._agents.values():
                if a.alive and a.status is not None:
                    for g, members in a.status.groups.items():
                        out.setdefault(g, [])
                        out[g].extend(m for m in members if m not in out[g])
        out.update(self.local_groups)
        return out

    def wait_until(self, predicate: Callable[["Fleet"], bool], timeout_s: float) -> bool:
        """Wait until ``predicate(fleet)`` holds (re-checked on every update) or the deadline."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while True:
                # Predicates call back into the Fleet, which takes the (reentrant) lock again.
                if predicate(self):
                    return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._lock.wait(min(left, 0.1))

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
        refs = sorted(set(refs))
        sels = [Selector(str(r), pattern=str(r)) for r in refs]
        if per_host:
            hosts = sorted({r.host for r in refs})
            return Selection(tuple(s.text for s in sels), tuple(refs), QueryPlan(tuple((h, "*") for h in hosts)))
        # Concrete names are each expressible; group them per host to save queries.
        by_host: dict[str, list[str]] = {}
        for r in refs:
            by_host.setdefault(r.host, []).append(r.axis)
        axes = self.host_axes()
        pairs: list[tuple[str, str]] = []
        for h, ax in sorted(by_host.items()):
            if axes.get(h) and set(ax) >= set(axes[h]):
                pairs.append((h, "*"))
            else:
                pairs.extend((h, a) for a in sorted(ax))
        return Selection(tuple(s.text for s in sels), tuple(refs), QueryPlan(tuple(pairs)))

    def _as_selection(self, target: "Selection | str | Sequence[str]") -> Selection:
        if isinstance(target, Selection):
            return target
        if isinstance(target, str):
            return self.select(target)
        return self.select(*target)


__all__ = ["Fleet", "Selection", "AgentInfo", "FleetError", "NoAgentError", "SelectorError",
           "DriveRef", "DriveResult", "CommandResult", "zenoh_config", "default_name"]
