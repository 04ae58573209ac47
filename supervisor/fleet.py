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

import dataclasses
import itertools
import json
import logging
import os
import queue
import re
import socket
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

import zenoh

from bus_agent.gateway.zenoh_config import zenoh_error_text
from schemas import keys
from schemas.messages import (
    AgentStatus,
    CommandReply,
    CommandRequest,
    DriveStatus,
    MODES,
    NMT_COMMANDS,
    SchemaError,
    decode,
    encode,
)

from .fleetfile import ExpectedFleet, load as load_fleet
from .motion import group_move, move_args
from .orchestration import ordered_shutdown, two_phase_enable
from .results import CommandResult, DriveResult, Report, aggregate, single
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

DEFAULT_CONNECT = ("tcp/127.0.0.1:7447",)
#: Extra time a query waits beyond the agents' own deadline (transport and scheduling).
REPLY_MARGIN_S = 1.0
DEFAULT_TIMEOUT_S = 5.0
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


@dataclass
class _Collector:
    """Replies of one command, filled from Zenoh reply callbacks."""

    addressed: frozenset[DriveRef]
    replies: dict[DriveRef, CommandReply] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    finished: int = 0


def default_name() -> str:
    """A legal supervisor name from the host name and process id."""
    base = re.sub(r"[^A-Za-z0-9_.\-]", "_", socket.gethostname())[:40] or "host"
    return f"sup-{base.lstrip('.-') or 'host'}-{os.getpid()}"


def zenoh_config(mode: str, connect: Sequence[str], listen: Sequence[str] = (),
                 connect_timeout_ms: int = 2000, *, pki: str | None = None,
                 identity: str | None = None) -> zenoh.Config:
    """A session config for the supervisor: multicast scouting off, explicit endpoints; with
    ``pki``/``identity``, mutual TLS as that principal (``bus_agent.gateway.zenoh_config``).
    Raises ValueError on a bad mode or identity."""
    if mode not in ("client", "peer"):
        raise ValueError(f"mode {mode!r}: use 'client' or 'peer'")
    if pki is not None or identity is not None:
        from bus_agent.gateway.zenoh_config import make_zenoh_config

        return make_zenoh_config(mode, listen if mode == "peer" else (), connect,
                                 connect_timeout_ms=connect_timeout_ms, pki=pki, identity=identity)
    conf: dict[str, Any] = {
        "mode": mode,
        "connect": {"endpoints": list(connect), "timeout_ms": connect_timeout_ms},
        "scouting": {"multicast": {"enabled": False}},
    }
    if mode == "peer":
        conf["listen"] = {"endpoints": list(listen)}
    return zenoh.Config.from_json5(json.dumps(conf))


Listener = Callable[..., None]


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
        self._lock = threading.Condition()
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
        self._collectors: list[_Collector] = []

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
                self._on_status_sample(reply.ok)
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

    def _on_status_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            st = decode(sample.payload.to_bytes(), DriveStatus)
        except SchemaError as exc:
            log.warning("supervisor %s: bad status on %s: %s", self.name, sample.key_expr, exc)
            return
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
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            st = decode(sample.payload.to_bytes(), AgentStatus)
        except SchemaError as exc:
            log.warning("supervisor %s: bad agent status on %s: %s", self.name, sample.key_expr, exc)
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

    # ---- commands ------------------------------------------------------------------------

    def _request_id(self, op: str) -> str:
        return f"{self.name}-{op}-{next(self._rid)}-{uuid.uuid4().hex[:8]}"

    def _query(self, keyexprs: Sequence[str], request: CommandRequest,
               addressed: Iterable[DriveRef], wait_s: float, agent_level: bool = False) -> CommandResult:
        """Send one query per key expression at once; collect one reply per addressed drive.

        Each query carries its own request id (``<id>.<n>`` when there are several): an agent
        treats a repeated id as the same request, so two queries reaching one agent with one id
        would be refused as a reuse for other drives.
        """
        s = self.session
        if len(keyexprs) == 1:
            payloads = [(keyexprs[0], request)]
        else:
            payloads = [(ke, dataclasses.replace(request, request_id=f"{request.request_id}.{i}"))
                        for i, ke in enumerate(keyexprs)]
        ids = {req.request_id for _, req in payloads}
        col = _Collector(frozenset(addressed))
        t0 = time.monotonic()

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                try:
                    msg = decode(reply.ok.payload.to_bytes(), CommandReply)
                except SchemaError as exc:
                    with self._lock:
                        col.errors.append(f"bad reply on {reply.ok.key_expr}: {exc}")
                    return
                if msg.request_id not in ids:
                    return
                ref = DriveRef(msg.host, "" if agent_level else msg.axis)
                with self._lock:
                    col.replies.setdefault(ref, msg)
                    self._lock.notify_all()
            else:
                text = reply.err.payload.to_string() if reply.err is not None else "?"
                if text != "Timeout":  # zenoh's own end-of-query marker, not an agent's answer
                    with self._lock:
                        col.errors.append(text)
                        self._lock.notify_all()

        def on_done() -> None:
            with self._lock:
                col.finished += 1
                self._lock.notify_all()

        for ke, req in payloads:
            s.get(ke, zenoh.handlers.Callback(on_reply, on_done), target=zenoh.QueryTarget.ALL,
                  consolidation=zenoh.ConsolidationMode.NONE, timeout=wait_s, payload=encode(req))
        deadline = t0 + wait_s + 0.2
        with self._lock:
            while True:
                alive = {h for h, a in self._agents.items() if a.alive}
                waiting = [r for r in col.addressed if r not in col.replies and r.host in alive]
                if not waiting or col.finished >= len(keyexprs):
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._lock.wait(min(left, 0.05))
            gone = {r.host for r in col.addressed} - {h for h, a in self._agents.items() if a.alive}
            replies = dict(col.replies)
            errors = list(col.errors)
        elapsed = time.monotonic() - t0
        silent = ""
        if self.identity and not replies and not errors and col.finished >= len(keyexprs) and elapsed < wait_s / 2:
            # Every query ended with no reply long before its deadline: what an ACL denial looks like.
            silent = (f"denied at once: identity {self.identity!r} may not {request.op} (router ACL), "
                      "or no agent serves authenticated commands")
        result = aggregate(request.op, request.request_id, sorted(col.addressed), replies,
                           errors=errors, gone_hosts=gone, timeout_s=wait_s, elapsed_s=elapsed,
                           denied_reason=silent)
        level = logging.INFO if result.ok else logging.WARNING
        log.log(level, "supervisor %s: %s to %d drive(s): %s in %.3f s", self.name, request.op,
                len(col.addressed), result.counts(), elapsed)
        return result

    def command(self, op: str, target: "Selection | str | Sequence[str]" = "**",
                args: Mapping[str, Any] | None = None, timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Send drive command ``op`` (``schemas.messages.DRIVE_OPS``) to the selection: one
        fan-out query per planned key expression, one result per selected drive."""
        sel = self._as_selection(target)
        req = CommandRequest(self._request_id(op), op, dict(args or {}), float(timeout_s), self.name)
        conflicts = self.conflicts()
        refused = [DriveResult(r.host, r.axis, "rejected", error=f"not sent: {conflicts[r.host]}")
                   for r in sel.drives if r.host in conflicts]
        if refused:
            log.error("supervisor %s: %s not sent to %s: host name conflict", self.name, op,
                      ", ".join(sorted({r.host for r in refused})))
            sel = self.selection_of([r for r in sel.drives if r.host not in conflicts])
        if not sel.drives:
            return CommandResult(op, req.request_id, tuple(refused))
        res = self._query(sel.plan.keyexprs(op, self.identity), req, sel.drives, timeout_s + REPLY_MARGIN_S)
        if refused:
            res = dataclasses.replace(res, results=tuple(sorted((*res.results, *refused),
                                                                key=lambda r: (r.host, r.axis))))
        return res

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
        axis). ``sync``: the selected axes of each host start in one cycle and arrive together.
        Done when in the position window at rest; ``timeout_s`` must cover the move."""
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
        if command not in NMT_COMMANDS:
            raise ValueError(f"nmt command {command!r} is not one of {', '.join(NMT_COMMANDS)}")
        conflicts = self.conflicts()
        live = [h for h in self.hosts() if h not in conflicts]
        addressed: set[str] = set()
        keyexprs: list[str] = []
        for h in hosts:
            sel = parse_selector(f"{h}/x") if "/" not in h else None
            if sel is None:
                raise SelectorError(f"host selector {h!r} may not contain '/'")
            matched = [x for x in live if sel.matches(DriveRef(x, "x"))]
            if not sel.has_wildcards:
                if h in conflicts:
                    raise SelectorError(f"host {h}: {conflicts[h]}")
                matched = [h]
            if not matched:
                raise SelectorError(f"host selector {h!r} matches no live agent")
            addressed.update(matched)
            pair = sel.zenoh_pair()
            if pair is None:
                keyexprs.extend(keys.agent_cmd(m, "nmt", self.identity) for m in matched)
            else:
                keyexprs.append(keys.agent_cmd(pair[0], "nmt", self.identity))
        args: dict[str, Any] = {"command": command}
        if axis is not None:
            args["axis"] = self._axis_of_slave(axis, addressed)
        req = CommandRequest(self._request_id("nmt"), "nmt", args, float(timeout_s), self.name)
        return self._query(sorted(set(keyexprs)), req, [DriveRef(h, "") for h in addressed],
                           timeout_s + REPLY_MARGIN_S, agent_level=True)

    def _axis_of_slave(self, axis: str | int, hosts: Iterable[str]) -> str:
        """An axis name, or the axis at slave position ``axis`` on the (single) addressed host."""
        if isinstance(axis, str) and not axis.isdigit():
            return keys.validate_name(axis, "axis")
        pos = int(axis)
        hosts = sorted(hosts)
        if len(hosts) != 1:
            raise SelectorError("a slave position needs exactly one host (--host); or give an axis name")
        found = [r.axis for r, st in self.drives().items() if r.host == hosts[0] and st.slave == pos]
        if not found:
            info = self.agents().get(hosts[0])
            axes = info.status.axes if info and info.status else []
            if 0 <= pos < len(axes):
                found = [axes[pos]]
        if not found:
            raise SelectorError(f"no drive at slave position {pos} on {hosts[0]}")
        return found[0]

    # ---- leases --------------------------------------------------------------------------

    def lease(self, *selectors: str, ttl_s: float | None = None, takeover: bool = False,
              timeout_s: float = 2.0) -> CommandResult:
        """Take (or with ``takeover`` seize) exclusive control of the selected drives.

        Leases are renewed every ttl/3 by a background thread while this Fleet is open; a drive
        whose renewal answers ``busy`` was taken over and is reported through ``lease_lost``.
        When this process dies, its liveliness token vanishes and the agents run the lease
        reaction at once (or at the latest when the ttl runs out).
        """
        ttl = float(ttl_s or self.lease_ttl_s)
        sel = self._as_selection(selectors or "**")
        res = self.command("lease", sel, {"holder": self.name, "ttl_s": ttl, "takeover": bool(takeover)},
                           timeout_s=timeout_s)
        with self._lock:
            for r in res.results:
                if r.ok:
                    self._leases[DriveRef(r.host, r.axis)] = ttl
            if sel.selectors not in self._lease_selectors:
                self._lease_selectors.append(sel.selectors)
        if self._leases and self._renewer is None:
            self._renewer = threading.Thread(target=self._renew_loop, name=f"fleet-{self.name}-lease", daemon=True)
            self._renewer.start()
        return res

    def leases(self) -> list[DriveRef]:
        """Drives whose lease this supervisor holds (as far as it knows)."""
        with self._lock:
            return sorted(self._leases)

    def release(self, *selectors: str, timeout_s: float = 2.0) -> CommandResult:
        """Give leases back (no reaction runs); default every lease held."""
        if selectors:
            sel = self._as_selection(selectors)
        else:
            sel = self.selection_of(self.leases())
        res = self.command("release", sel, {"holder": self.name}, timeout_s=timeout_s)
        with self._lock:
            for ref in sel.drives:
                self._leases.pop(ref, None)
        return res

    def _renew_loop(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                held = sorted(self._leases)
                ttl = min(self._leases.values(), default=self.lease_ttl_s)
            if self._stop.wait(ttl / 3.0):
                return
            if not held:
                continue
            try:
                res = self.command("lease", self.selection_of(held),
                                   {"holder": self.name, "ttl_s": ttl, "takeover": False},
                                   timeout_s=min(1.0, ttl / 3.0))
            except Exception:
                if self._stop.is_set():
                    return
                log.exception("supervisor %s: lease renewal failed", self.name)
                continue
            lost = [r for r in res.results if r.outcome in ("busy", "rejected")]
            with self._lock:
                for r in lost:
                    self._leases.pop(DriveRef(r.host, r.axis), None)
            for r in lost:  # listeners see leases() already without every lost drive
                log.warning("supervisor %s: lease on %s lost (%s, holder %r)", self.name, r.name,
                            r.outcome, r.lease_holder)
                self._emit("lease_lost", r)
            for r in res.results:
                if not r.ok and r not in lost:
                    log.warning("supervisor %s: lease renewal on %s: %s %s", self.name, r.name, r.outcome, r.error)


__all__ = ["Fleet", "Selection", "AgentInfo", "FleetError", "NoAgentError", "SelectorError",
           "DriveRef", "DriveResult", "CommandResult", "zenoh_config", "default_name"]
