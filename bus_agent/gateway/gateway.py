"""The gateway: the agent's Zenoh side (status publishers, command queryables, liveliness, leases).

It never blocks the cycle. The cycle hands over one :class:`~bus_agent.runtime.CycleSnapshot`
per cycle through :meth:`Gateway.on_snapshot` (an attribute store, a deque extend and an event
set) and one :class:`~bus_agent.runtime.Outcome` per addressed axis through each command's
``on_outcome`` (a queue put). Everything else runs on the gateway's two threads:

- ``gw-publish`` turns snapshots into ``DriveStatus`` puts (on change of a discrete field,
  within one cycle; motion fields at most every ``motion_period_s``; everything every
  ``heartbeat_s``), ``Event`` puts (cycle events and command outcomes) and ``AgentStatus``;
- ``gw-command`` owns every piece of mutable command state (pending requests, the request-id
  memory, the lease table, remote group members). Zenoh callbacks only enqueue to it.

Command path (one query): find which of this host's axes the query key intersects (none: not
for us, finish silently); decode and validate the payload (``schemas.messages``); any problem
-> ``reply_err`` with a text naming it, nothing changes. Otherwise one DriveCommand for all the
addressed axes (the cycle applies it in one cycle) and, as the outcomes arrive, one
``CommandReply`` per axis on ``drives/@v1/<host>/drive/<axis>/cmd/<op>``; the query is finished
when every axis has answered. A repeated request id attaches to the first request's outcomes.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Protocol, Sequence

import zenoh

from bus_agent import runtime as rt
from bus_agent.gateway.hostclaim import ConflictTracker, check_host_free, new_instance
from bus_agent.gateway.leases import EndedLease, LeaseDecision, LeaseResult, LeaseTable
from schemas import keys
from schemas import messages as m
from schemas.error_codes import describe

log = logging.getLogger(__name__)

MSGPACK = zenoh.Encoding("application/msgpack")
TEXT = zenoh.Encoding.TEXT_PLAIN

#: Ops the gateway answers itself; every other drive op is carried out by the cycle.
LEASE_OPS = ("lease", "release")
#: Lease loss reactions (``DrivePolicy.lease_reaction``) -> drive ops run one after the other.
LEASE_REACTION_OPS: dict[str, tuple[str, ...]] = {
    "quick_stop_then_disable": ("quick_stop", "disable"),
    "quick_stop": ("quick_stop",),
    "disable": ("disable",),
    "none": (),
}
#: Drive status fields whose change is news and is published within one cycle. Position,
#: velocity and torque change every cycle in motion: they go out at most every
#: ``motion_period_s`` and with every heartbeat.
CHANGE_FIELDS = ("state", "statusword", "controlword", "goal", "halt", "mode", "mode_display",
                 "error_code", "error_text", "al_state", "lost", "axis_state", "homed", "motion_request_id")
MOTION_FIELDS = ("position", "velocity", "torque", "target_position", "following_error", "objects")
#: Remote group member states that trigger the group here.
BAD_STATES = ("fault", "fault_reaction_active")

#: Ops an agent refuses while another agent uses its host name (lowering ops still work).
CONFLICT_REFUSED_OPS = frozenset({"enable", "switch_on", "fault_reset", "set_mode", "nmt"})
#: Request-id memory: size and time to live of finished requests.
DEDUP_SIZE = 1024
DEDUP_TTL_S = 300.0
#: Extra time after a command's own timeout before the gateway gives up on the cycle's outcome.
OUTCOME_GRACE_S = 2.0
#: Identity of commands the agent issues itself (lease loss reactions).
AGENT_SUPERVISOR = ""
#: How long one publish pass may wait, in all, for the command thread to finish its work (see
#: ``Gateway._commands_first``).
COMMANDS_FIRST_MAX_S = 0.005
#: Flight recorder queries waiting to be served (beyond: refused as busy), and how long the cycle
#: may take to produce one (an explicit request waits for its window's after part too).
RECORDING_QUEUE = 4
RECORDING_TIMEOUT_S = 10.0


class RequestError(ValueError):
    """A command query refused as a whole: answered with ``reply_err``, nothing changes."""


class CycleLike(Protocol):
    """What the gateway needs from the cycle (``bus_agent.cycle.cycle.Cycle``)."""

    snapshot_sink: Callable[[rt.CycleSnapshot], None] | None

    @property
    def latest(self) -> rt.CycleSnapshot | None: ...

    def submit(self, cmd: rt.DriveCommand | rt.AgentCommand) -> bool: ...

    def trigger_group(self, group: str, reason: str) -> None: ...


@functools.lru_cache(maxsize=4096)
def _ke(key: str) -> zenoh.KeyExpr:
    return zenoh.KeyExpr(key)


# ---- pure command validation --------------------------------------------------------------


@dataclass(frozen=True)
class ParsedCommand:
    """A validated command query: the request, its normalised args, the addressed axes
    (empty for agent commands)."""

    request: m.CommandRequest
    args: Mapping[str, Any]
    axes: tuple[str, ...]
    principal: str | None = None  # from the key (authenticated), None on an unauthenticated key


def axes_in_key(query_key: str, host: str, axes: Iterable[str], op: str = "*",
                principal: str | None = None) -> tuple[str, ...]:
    """The axes of ``host`` whose ``cmd/<op>`` key (of ``principal``, if any) intersects ``query_key``."""
    qke = _ke(str(query_key))
    return tuple(a for a in axes if _ke(keys.drive_cmd(host, a, op, principal)).intersects(qke))


def requester(query_key: str, claimed: str, *, secure: bool) -> str:
    """Who is asking: the principal the key names (``.../cmd/<op>/@sup/<principal>``, which the
    router's ACL admits only from that principal), else, on an insecure agent, the payload's
    ``supervisor`` (a claim nobody checked). The one place the gateway decides it.
    Raises :class:`RequestError` when the payload names someone else than the key, or when a
    secure agent gets a key without a principal."""
    try:
        principal = keys.command_principal(query_key)
    except keys.InvalidKey as exc:
        raise RequestError(str(exc)) from None
    if principal is None:
        if secure:
            raise RequestError("this agent takes commands only on .../cmd/<op>/@sup/<principal> keys (--pki)")
        return claimed
    if claimed and claimed != principal:
        raise RequestError(f"supervisor {claimed!r} in the payload is not the requester {principal!r} "
                           "authenticated by the key")
    return principal


def parse_command(payload: Any, query_key: str, host: str, axes: Sequence[str], *, agent: bool = False,
                  secure: bool = False) -> ParsedCommand:
    """Decode and validate one command query; raise :class:`RequestError` naming the problem.

    ``payload``: the query payload (bytes or zenoh ZBytes, None if absent). ``agent``: the
    query came to ``.../agent/cmd/*`` (op ``nmt``) rather than ``.../drive/*/cmd/*``.
    The payload's op must be the key's op (checked as: the concrete key of that op intersects
    the query key, which also admits ``cmd/*`` selectors). The request's ``supervisor`` is
    replaced by :func:`requester` (``secure``: only authenticated keys are accepted).
    """
    if payload is None:
        raise RequestError("no payload: a command query carries a msgpack command_request (schemas.messages)")
    try:
        req = m.decode(payload, m.CommandRequest)
    except m.SchemaError as exc:
        raise RequestError(f"invalid command_request: {exc}") from None
    req = dataclasses.replace(req, supervisor=requester(query_key, req.supervisor, secure=secure))
    principal = keys.command_principal(query_key)  # valid: requester() checked it
    if agent:
        if req.op not in m.AGENT_OPS:
            raise RequestError(f"op {req.op!r} is not an agent op (agent ops: {', '.join(m.AGENT_OPS)})")
        if not _ke(keys.agent_cmd(host, req.op, principal)).intersects(_ke(str(query_key))):
            raise RequestError(f"op {req.op!r} in the payload does not match the key {query_key}")
        args = m.validate_args(req.op, req.args)
        if args.get("axis") and args["axis"] not in axes:
            raise RequestError(f"args.axis: {args['axis']!r} is not an axis of {host} ({', '.join(axes)})")
        return ParsedCommand(req, args, (), principal)
    if req.op not in m.DRIVE_OPS:
        raise RequestError(f"op {req.op!r} is not a drive op (drive ops: {', '.join(m.DRIVE_OPS)})")
    addressed = axes_in_key(query_key, host, axes, req.op, principal)
    if not addressed:
        raise RequestError(f"op {req.op!r} in the payload does not match the key {query_key} "
                           "(the key's last chunk is the op)")
    args = m.validate_args(req.op, req.args)
    if req.op == "move" and "targets" in args:
        # A group move addresses the axes it names (one query for a part of a host's axes).
        missing = sorted(set(args["targets"]) - set(addressed))
        if missing:
            raise RequestError(f"args.targets: {', '.join(missing)} not addressed by {query_key} on {host}")
        addressed = tuple(a for a in addressed if a in args["targets"])
    if req.op in LEASE_OPS and req.supervisor and args["holder"] != req.supervisor:
        raise RequestError(f"args.holder {args['holder']!r} differs from supervisor {req.supervisor!r}")
    return ParsedCommand(req, args, addressed, principal)


def recording_message(host: str, data: Any) -> m.Recording:
    """The ``recording`` reply for a ``bus_agent.cycle.recorder.RecordingData``."""
    return m.Recording(host=host, reason=data.reason, cycle_us=data.cycle_us, first_cycle=data.first_cycle,
                       n_cycles=data.n_cycles, time_origin_ns=data.time_origin_ns, axes=list(data.axes),
                       channels=data.channels, axis=data.axis, detail=data.detail,
                       trigger_cycle=data.trigger_cycle)


# ---- pending requests ----------------------------------------------------------------------


class _Request:
    """One request id: its axes, the replies gathered so far, the queries waiting for them.
    Touched only by the command thread."""

    def __init__(self, parsed: ParsedCommand, host: str, now_s: float) -> None:
        req = parsed.request
        self.request_id = req.request_id
        self.op = req.op
        self.axes: tuple[str, ...] = parsed.axes or ("",)
        self.supervisor = req.supervisor
        # Replies go on the key asked, authenticated form included (a reply must intersect the query).
        self.principal = parsed.principal
        self.reply_keys = {a: (keys.drive_cmd(host, a, req.op, self.principal) if a else
                               keys.agent_cmd(host, req.op, self.principal)) for a in self.axes}
        self.created_s = now_s
        self.received_ns = time.monotonic_ns()
        self.deadline_s = now_s + req.timeout_s + OUTCOME_GRACE_S
        self.replies: dict[str, m.CommandReply] = {}
        self.waiting: list[tuple[zenoh.Query, set[str]]] = []
        self.requester = "anonymous"

    @property
    def done(self) -> bool:
        return len(self.replies) == len(self.axes)

    def same_command(self, parsed: ParsedCommand) -> bool:
        return (parsed.request.op == self.op and (parsed.axes or ("",)) == self.axes
                and parsed.request.supervisor == self.supervisor and parsed.principal == self.principal)

    def attach(self, query: zenoh.Query) -> None:
        self.waiting.append((query, set(self.axes)))
        self.flush()

    def add(self, reply: m.CommandReply) -> None:
        self.replies.setdefault(reply.axis, reply)
        self.flush()

    def flush(self) -> None:
        still = []
        for query, remaining in self.waiting:
            for axis in [a for a in remaining if a in self.replies]:
                remaining.discard(axis)
                try:
                    query.reply(self.reply_keys[axis], m.encode(self.replies[axis]), encoding=MSGPACK)
                except Exception as exc:  # the querier may be gone; the others still get theirs
                    log.warning("reply to %s (%s) failed: %s", self.reply_keys[axis], self.request_id, exc)
            if remaining:
                still.append((query, remaining))
            else:
                _finish(query)
        self.waiting = still


def _finish(query: zenoh.Query) -> None:
    try:
        query.drop()
    except Exception as exc:
        log.debug("query drop: %s", exc)


def _reply_err(query: zenoh.Query, text: str) -> None:
    try:
        query.reply_err(text.encode("utf-8"), encoding=TEXT)
    except Exception as exc:
        log.warning("reply_err failed: %s", exc)
    _finish(query)


# ---- the gateway ----------------------------------------------------------------------------


@dataclass(frozen=True)
class GatewaySettings:
    host: str
    axes: tuple[str, ...]                      # in slave order
    heartbeat_s: float = 1.0
    agent_period_s: float = 1.0
    motion_period_s: float = 0.1
    backend: str = "sim"
    cycle_us: int = 1000
    groups: Mapping[str, Sequence[str]] = field(default_factory=dict)   # name -> "host/axis"
    lease_reaction: Mapping[str, str] = field(default_factory=dict)     # axis -> LEASE_REACTION_OPS key
    lease_ttl_s: Mapping[str, float] = field(default_factory=dict)      # axis -> default ttl
    instance: str = ""              # this agent process' id ('' = a new random one)
    check_host: bool = True         # refuse to start while another agent holds the host name
    has_connect: bool = False       # the session has connect endpoints (wait for a link first)
    secure: bool = False  # --pki: serve only authenticated command keys (requester from the key)


@dataclass
class _Remote:
    """A group member on another host, as seen through its status and its agent's token."""

    group: str
    host: str
    axis: str
    bad: bool = False
    seen: bool = False


class Gateway:
    """Zenoh I/O of one bus agent. ``start`` declares everything; ``stop_commands`` stops
    accepting commands (shutdown begins); ``close`` publishes the last snapshot and undeclares.
    """

    def __init__(self, session: zenoh.Session, cycle: CycleLike, settings: GatewaySettings) -> None:
        self.session = session
        self.cycle = cycle
        self.s = settings
        self.host = settings.host
        self.axes = tuple(settings.axes)
        self.agent_state_override: str | None = None
        self.instance = settings.instance or new_instance()
        # Other agents under our host name; a conflict ends after three silent status periods.
        self._conflicts = ConflictTracker(self.host, self.instance, max(1.0, 3 * settings.agent_period_s))
        self._conflict_text = ""
        # cycle -> publisher
        self._latest: rt.CycleSnapshot | None = None
        self._events: collections.deque[tuple[rt.CycleEvent, int, int]] = collections.deque(maxlen=8192)
        self._wake = threading.Event()
        # command thread state
        self._inbox: queue.SimpleQueue[tuple[Callable[..., None], tuple]] = queue.SimpleQueue()
        self._requests: collections.OrderedDict[str, _Request] = collections.OrderedDict()
        self._pending: set[_Request] = set()
        self.leases = LeaseTable()
        self._lease_holders: dict[str, str] = {}   # published copy, replaced whole
        self._remotes: list[_Remote] = []
        for group, members in settings.groups.items():
            for member in members:
                host, _, axis = member.partition("/")
                if host != self.host:
                    self._remotes.append(_Remote(group, host, axis))
        self._internal_seq = 0
        # publisher thread state
        self._status_seq: dict[str, int] = {a: 0 for a in self.axes}
        self._event_seq: dict[str, int] = {a: 0 for a in self.axes}
        self._agent_seq = 0
        self._last_fields: dict[str, tuple] = {}
        self._last_motion: dict[str, tuple] = {}
        self._last_motion_pub_s: dict[str, float] = {}
        self._published: dict[str, m.DriveStatus] = {}
        self._next_heartbeat_s = 0.0
        self._next_agent_s = 0.0
        # zenoh entities
        self._status_pubs: dict[str, zenoh.Publisher] = {}
        self._event_pubs: dict[str, zenoh.Publisher] = {}
        self._agent_pub: zenoh.Publisher | None = None
        self._cmd_queryables: list[Any] = []
        self._other_decls: list[Any] = []
        self._token: Any = None
        self._stop = threading.Event()
        self._accepting = False
        self._threads: list[threading.Thread] = []
        self._pub_lock = threading.Lock()  # publish_once from close() vs the thread
        # Set while the command thread has nothing to do; the publish thread waits for it (bounded).
        self._commands_idle = threading.Event()
        self._commands_idle.set()
        # Flight recorder queries: served one at a time on their own thread (copies take a while).
        self._recordings: queue.Queue[zenoh.Query] = queue.Queue(maxsize=RECORDING_QUEUE)
        #: 'op.outcome' -> replies given (published in AgentStatus.commands, for metrics).
        self._command_counts: dict[str, int] = {}

    # ---- called from the cycle thread: enqueue only --------------------------------------

    def on_snapshot(self, snap: rt.CycleSnapshot) -> None:
        """Snapshot sink of the cycle. Cycle-safe: no I/O, no locks held for long."""
        self._latest = snap
        if snap.events:
            self._events.extend((ev, snap.cycle, snap.time_ns) for ev in snap.events)
        self._wake.set()

    def on_events(self, items: Iterable[tuple[rt.CycleEvent, int, int]]) -> None:
        """Event sink of a cycle in another process (``bridge.CycleProxy.event_sink``): events
        with the cycle number and wall time of the snapshot they came in, in order."""
        self._events.extend(items)
        self._wake.set()

    # ---- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Check that the host name is free (:class:`~bus_agent.gateway.hostclaim.HostNameTaken`
        otherwise, nothing declared), then declare everything, commands last."""
        s = self.session
        if self.s.check_host:
            check_host_free(s, self.host, has_connect=self.s.has_connect)
        # A cycle already running (behind the process bridge) has a snapshot: drive status goes
        # out in the first publish pass, before the agent status that lists the axes.
        self._latest = self._latest or getattr(self.cycle, "latest", None)
        for axis in self.axes:
            # BLOCK: a watcher must see every publication (seq without gaps); a slow subscriber
            # slows only this publishing thread, which coalesces to the latest snapshot, never the cycle.
            self._status_pubs[axis] = s.declare_publisher(keys.drive_status(self.host, axis), encoding=MSGPACK,
                                                          express=True,
                                                          congestion_control=zenoh.CongestionControl.BLOCK)
            self._event_pubs[axis] = s.declare_publisher(keys.drive_event(self.host, axis), encoding=MSGPACK,
                                                         congestion_control=zenoh.CongestionControl.BLOCK)
        self._agent_pub = s.declare_publisher(keys.agent_status(self.host), encoding=MSGPACK)
        enqueue = self._inbox.put
        self._other_decls.append(s.declare_queryable(
            keys.drive_status(self.host, "*"), lambda q: enqueue((self._on_status_query, (q,)))))
        self._other_decls.append(s.declare_queryable(
            keys.agent_status(self.host), lambda q: enqueue((self._on_agent_query, (q,)))))
        self._other_decls.append(s.liveliness().declare_subscriber(
            keys.ALL_SUPERVISORS, lambda smp: enqueue((self._on_supervisor_token, (smp,))), history=True))
        self._other_decls.append(s.declare_subscriber(
            keys.agent_status(self.host), lambda smp: enqueue((self._on_own_host_status, (smp,)))))
        remote_hosts = sorted({r.host for r in self._remotes})
        for host in remote_hosts:
            self._other_decls.append(s.declare_subscriber(
                keys.drive_status(host, "*"), lambda smp: enqueue((self._on_remote_status, (smp,)))))
            self._other_decls.append(s.liveliness().declare_subscriber(
                keys.alive(host), lambda smp: enqueue((self._on_remote_token, (smp,))), history=True))
        self._other_decls.append(s.declare_queryable(keys.agent_recording(self.host), self._on_recording_query))
        self._threads = [threading.Thread(target=self._publish_loop, name="gw-publish", daemon=True),
                         threading.Thread(target=self._command_loop, name="gw-command", daemon=True),
                         threading.Thread(target=self._recording_loop, name="gw-record", daemon=True)]
        for t in self._threads:
            t.start()
        if hasattr(self.cycle, "event_sink"):  # a cycle behind the process bridge forwards events apart
            self.cycle.event_sink = self.on_events
        self.cycle.snapshot_sink = self.on_snapshot
        # Commands last: by now status flows and the lease/group subscribers are in place.
        self._accepting = True
        # Authenticated keys always; the unauthenticated ones (the v1 contract's) only without --pki.
        for principal in ("*",) if self.s.secure else ("*", None):
            self._cmd_queryables.append(s.declare_queryable(
                keys.drive_cmd(self.host, "*", "*", principal), lambda q: enqueue((self._on_drive_cmd, (q,)))))
            self._cmd_queryables.append(s.declare_queryable(
                keys.agent_cmd(self.host, "*", principal), lambda q: enqueue((self._on_agent_cmd, (q,)))))
        self._token = s.liveliness().declare_token(keys.alive(self.host))
        log.info("gateway %s: %d drive(s), %d remote group member(s)", self.host, len(self.axes), len(self._remotes))

    def stop_commands(self) -> None:
        """Stop taking new commands (queries already accepted still get their outcomes)."""
        self._accepting = False
        for q in self._cmd_queryables:
            _undeclare(q)
        self._cmd_queryables.clear()

    def close(self, timeout_s: float = 2.0) -> None:
        """Publish what the cycle last reported, answer what is pending, undeclare everything.
        Call after the cycle stopped. Idempotent."""
        self.stop_commands()
        if self._stop.is_set():
            return
        # Outcomes the cycle gave during its ordered stop are in the inbox: let them through.
        done = threading.Event()
        self._inbox.put((lambda: done.set(), ()))
        done.wait(timeout_s)
        self._stop.set()
        self._wake.set()
        self._inbox.put((lambda: None, ()))
        for t in self._threads:
            t.join(timeout_s)
        self.agent_state_override = "stopped"
        self._publish_once(final=True)
        for req in list(self._pending):
            for axis in req.axes:
                if axis not in req.replies:
                    req.add(self._reply(req, rt.Outcome(axis, "failed", reason="agent stopped before the outcome")))
        self._pending.clear()
        for decl in self._other_decls:
            _undeclare(decl)
        self._other_decls.clear()
        if self._token is not None:
            _undeclare(self._token)
            self._token = None
        for pub in [*self._status_pubs.values(), *self._event_pubs.values(), self._agent_pub]:
            if pub is not None:
                _undeclare(pub)
        self._status_pubs.clear()
        self._event_pubs.clear()
        self._agent_pub = None

    # ---- publisher thread -----------------------------------------------------------------

    def _publish_loop(self) -> None:
        while not self._stop.is_set():
            now = time.monotonic()
            wait = max(0.0, min(self._next_heartbeat_s, self._next_agent_s) - now)
            self._wake.wait(wait)
            self._wake.clear()
            if self._stop.is_set():
                break
            try:
                self._publish_once()
            except Exception:  # keep publishing; the log says what broke
                log.exception("gateway %s: publish failed", self.host)

    def _commands_first(self, until_s: float) -> None:
        """Let the command thread finish what it is doing (replies, a query's validation) before
        the next put, until ``until_s`` at most. Both threads need the GIL, and a put or a reply
        gives it up while zenoh works: a publish pass (a put per changed drive and per event, all
        16 drives in every cycle of an enable) took it back each time and held a 16-drive reply
        batch up by milliseconds. Waiting on an event sleeps without the GIL."""
        if not self._commands_idle.is_set() and not self._stop.is_set():
            self._commands_idle.wait(max(0.0, until_s - time.monotonic()))

    def _publish_once(self, final: bool = False) -> None:
        with self._pub_lock:
            snap = self._latest
            now = time.monotonic()
            until_s = now + (0.0 if final else COMMANDS_FIRST_MAX_S)
            heartbeat = final or now >= self._next_heartbeat_s
            if heartbeat:
                self._next_heartbeat_s = now + self.s.heartbeat_s
            holders = self._lease_holders
            if snap is not None:
                for d in snap.drives:
                    self._commands_first(until_s)
                    self._maybe_publish_status(snap, d, holders.get(d.axis, ""), now, heartbeat)
            while self._events:
                self._commands_first(until_s)
                ev, cycle, time_ns = self._events.popleft()
                self._publish_event(ev, cycle, time_ns)
            if final or now >= self._next_agent_s:
                self._next_agent_s = now + self.s.agent_period_s
                if self._agent_pub is not None:
                    self._agent_seq += 1
                    self._agent_pub.put(m.encode(self._agent_status(self._agent_seq)))

    def _maybe_publish_status(self, snap: rt.CycleSnapshot, d: rt.DriveSnapshot, holder: str, now: float,
                              heartbeat: bool) -> None:
        axis = d.axis
        pub = self._status_pubs.get(axis)
        if pub is None:
            return
        fields = tuple(getattr(d, f) for f in CHANGE_FIELDS) + (holder,)
        motion = tuple(getattr(d, f) for f in MOTION_FIELDS)
        changed = fields != self._last_fields.get(axis)
        moved = (motion != self._last_motion.get(axis)
                 and now - self._last_motion_pub_s.get(axis, 0.0) >= self.s.motion_period_s)
        if not (changed or moved or heartbeat):
            return
        self._status_seq[axis] = self._status_seq.get(axis, 0) + 1
        msg = self._status_msg(snap, d, holder, self._status_seq[axis])
        try:
            payload = m.encode(msg)
        except m.SchemaError as exc:
            log.error("drive %s/%s: status not publishable: %s", self.host, axis, exc)
            return
        pub.put(payload)
        self._published[axis] = msg
        self._last_fields[axis] = fields
        self._last_motion[axis] = motion
        self._last_motion_pub_s[axis] = now

    def _status_msg(self, snap: rt.CycleSnapshot, d: rt.DriveSnapshot, holder: str, seq: int) -> m.DriveStatus:
        return m.DriveStatus(
            host=self.host, axis=d.axis, seq=seq, time_ns=snap.time_ns, cycle=snap.cycle,
            state=d.state if d.state in m.DRIVE_STATES else "unknown", statusword=d.statusword,
            controlword=d.controlword, goal=d.goal, halt=d.halt, mode=d.mode, mode_display=d.mode_display,
            position=d.position, velocity=d.velocity, torque=d.torque, error_code=d.error_code,
            error_text=(d.error_text or describe(d.error_code))[:200], al_state=d.al_state, lost=d.lost, lease_holder=holder, slave=d.slave,
            axis_state=d.axis_state, homed=d.homed, target_position=d.target_position,
            following_error=max(-2**31, min(2**31 - 1, d.following_error)), motion_request_id=d.motion_request_id[:128],
            absent=list(d.absent), objects=dict(zip(d.object_names, d.objects)),
        )

    def _publish_event(self, ev: rt.CycleEvent, cycle: int, time_ns: int) -> None:
        if not ev.axis:
            # An agent-wide event (e.g. an NMT outcome) concerns every drive: one copy each.
            for axis in self.axes:
                self._publish_event(dataclasses.replace(ev, axis=axis), cycle, time_ns)
            return
        pub = self._event_pubs.get(ev.axis)
        if pub is None:
            log.debug("event for unknown axis %r dropped: %s", ev.axis, ev)
            return
        self._event_seq[ev.axis] = self._event_seq.get(ev.axis, 0) + 1
        detail = ev.detail
        if ev.kind == "fault" and ev.error_code and describe(ev.error_code) not in detail:
            detail = f"{detail}: {describe(ev.error_code)}" if detail else describe(ev.error_code)
        try:
            msg = m.Event(
                host=self.host, axis=ev.axis, seq=self._event_seq[ev.axis], time_ns=time_ns, cycle=cycle,
                kind=ev.kind, detail=detail[:400],
                from_state=ev.from_state if ev.from_state in m.DRIVE_STATES else "unknown",
                to_state=ev.to_state if ev.to_state in m.DRIVE_STATES else "unknown",
                error_code=ev.error_code, request_id=ev.request_id[:128], requester=ev.requester[:128],
            )
            pub.put(m.encode(msg))
        except m.SchemaError as exc:
            log.error("drive %s/%s: event not publishable: %s", self.host, ev.axis, exc)

    def _agent_status(self, seq: int) -> m.AgentStatus:
        snap = self._latest
        st = snap.stats if snap else rt.CycleStats(cycle_us=self.s.cycle_us)
        state = self.agent_state_override or (snap.agent_state if snap else "starting")
        return m.AgentStatus(
            host=self.host, seq=seq, time_ns=snap.time_ns if snap else time.time_ns(),
            state=state if state in m.AGENT_STATES else "error", backend=self.s.backend,
            cycle_us=st.cycle_us or self.s.cycle_us, cycles=st.cycles,
            period_p50_us=st.period_p50_us, period_p99_us=st.period_p99_us, period_max_us=st.period_max_us,
            overruns=st.overruns, wkc_errors=st.wkc_errors, expected_wkc=st.expected_wkc,
            axes=list(self.axes), al_states={d.axis: d.al_state for d in snap.drives} if snap else {},
            leases=dict(self._lease_holders), groups={g: list(ms) for g, ms in self.s.groups.items()},
            instance=self.instance, conflict=self._conflict_text[:400], commands=dict(self._command_counts),
            dc={d.axis: d.dc for d in snap.drives} if snap else {},
            dc_offset_p50_us=st.dc_offset_p50_us, dc_offset_p99_us=st.dc_offset_p99_us,
        )

    # ---- command thread ---------------------------------------------------------------------

    def _command_loop(self) -> None:
        while True:
            timeout = self._next_timer_s() - time.monotonic()
            try:
                fn, args = self._inbox.get(timeout=max(0.001, timeout))
            except queue.Empty:
                fn, args = None, ()
            if self._stop.is_set():
                break
            if fn is not None:
                self._commands_idle.clear()
            try:
                if fn is not None:
                    fn(*args)
                self._timers(time.monotonic())
            except Exception:
                log.exception("gateway %s: command thread", self.host)
            if self._inbox.empty():
                self._commands_idle.set()

    def _next_timer_s(self) -> float:
        t = time.monotonic() + 0.2
        nxt = self.leases.next_expiry_s()
        if nxt is not None:
            t = min(t, nxt)
        return t

    def _timers(self, now: float) -> None:
        if self._conflicts.expire(now):
            self._conflict_changed()
        ended = self.leases.expire(now)
        if ended:
            self._leases_ended(ended)
        for req in [r for r in self._pending if now >= r.deadline_s]:
            for axis in req.axes:
                if axis not in req.replies:
                    self._outcome(req, rt.Outcome(axis, "timeout", reason="no outcome from the cycle in time"))

    # -- status/agent gets

    def _on_status_query(self, query: zenoh.Query) -> None:
        with query:
            snap = self._latest
            if snap is None:
                return
            qke = query.key_expr
            holders = self._lease_holders
            for d in snap.drives:
                key = keys.drive_status(self.host, d.axis)
                if _ke(key).intersects(qke):
                    seq = self._status_seq.get(d.axis, 0)
                    query.reply(key, m.encode(self._status_msg(snap, d, holders.get(d.axis, ""), seq)),
                                encoding=MSGPACK)

    def _on_agent_query(self, query: zenoh.Query) -> None:
        with query:
            query.reply(keys.agent_status(self.host), m.encode(self._agent_status(self._agent_seq)),
                        encoding=MSGPACK)

    # -- flight recorder

    def _on_recording_query(self, query: zenoh.Query) -> None:
        try:
            self._recordings.put_nowait(query)
        except queue.Full:
            _reply_err(query, f"{self.host}: flight recorder busy: {RECORDING_QUEUE} requests are waiting")

    def _recording_loop(self) -> None:
        while not self._stop.is_set():
            try:
                query = self._recordings.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._serve_recording(query)
            except Exception as exc:  # keep serving; the querier gets the reason
                log.exception("gateway %s: recording query failed", self.host)
                _reply_err(query, f"{self.host}: recording failed: {exc}")

    def _serve_recording(self, query: zenoh.Query) -> None:
        try:
            payload: Any = query.payload
            req = m.RecordingRequest() if payload is None else m.decode(payload, m.RecordingRequest)
        except m.SchemaError as exc:
            _reply_err(query, f"{self.host}: invalid recording_request: {exc}")
            return
        fetch = getattr(self.cycle, "recording", None)
        if fetch is None:
            _reply_err(query, f"{self.host}: this agent has no flight recorder")
            return
        try:
            data = fetch(req.what, req.last_s, RECORDING_TIMEOUT_S)
        except LookupError as exc:
            _reply_err(query, f"{self.host}: {exc}")
            return
        query.reply(keys.agent_recording(self.host), m.encode(recording_message(self.host, data)), encoding=MSGPACK)
        _finish(query)

    # -- commands

    def _on_drive_cmd(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        if not (axes_in_key(key, self.host, self.axes) or axes_in_key(key, self.host, self.axes, principal="*")):
            _finish(query)  # a selector for other drives or hosts: not ours to answer
            return
        self._command(query, key, agent=False)

    def _on_agent_cmd(self, query: zenoh.Query) -> None:
        self._command(query, str(query.key_expr), agent=True)

    def _requester(self, key: str, request: m.CommandRequest | None) -> str:
        """Who is asking, for the audit trail: the requester :func:`requester` decided for a parsed
        request (the key's authenticated principal, else the declared ``supervisor``); for a
        refused one, the key's principal if it names one; '' -> anonymous."""
        if request is not None:
            return request.supervisor or "anonymous"
        try:
            return keys.command_principal(key) or "anonymous"
        except keys.InvalidKey:
            return "anonymous"

    def _audit(self, key: str, request: m.CommandRequest | None, axes: Sequence[str], requester: str,
               outcome: str, reason: str = "") -> None:
        """Log (INFO) and publish (event kind ``command``) one accepted or refused command."""
        rid = request.request_id if request is not None else ""
        op = request.op if request is not None else key.split("/cmd/", 1)[-1].split("/", 1)[0]
        log.info("agent %s: command %s op %s axes %s from %s: %s%s", self.host, rid or "-", op,
                 ",".join(axes) or "-", requester, outcome, f": {reason}" if reason else "")
        detail = f"{op} {outcome} from {requester}" + (f": {reason}" if reason else "")
        for axis in axes or ("",):
            self._emit(rt.CycleEvent(axis, "command", detail=detail, request_id=rid, requester=requester))

    def _command(self, query: zenoh.Query, key: str, agent: bool) -> None:
        key_axes = () if agent else (axes_in_key(key, self.host, self.axes)
                                     or axes_in_key(key, self.host, self.axes, principal="*"))
        if not self._accepting:
            self._audit(key, None, key_axes, self._requester(key, None), "refused", "shutting down")
            _reply_err(query, f"agent {self.host} is shutting down: no new commands")
            return
        try:
            parsed = parse_command(query.payload, key, self.host, self.axes, agent=agent, secure=self.s.secure)
        except RequestError as exc:
            self._audit(key, None, key_axes, self._requester(key, None), "refused", str(exc))
            _reply_err(query, f"{self.host}: {exc}")
            return
        requester = self._requester(key, parsed.request)
        now = time.monotonic()
        self._forget_old(now)
        rid = parsed.request.request_id
        first = self._requests.get(rid)
        if first is not None:
            if not first.same_command(parsed):
                reason = (f"request_id {rid!r} was already used for op {first.op} on "
                          f"{', '.join(first.axes) or 'the agent'}: use a new request_id")
                self._audit(key, parsed.request, parsed.axes, requester, "refused", reason)
                _reply_err(query, f"{self.host}: {reason}")
                return
            first.attach(query)  # the first outcome(s), now or when they come: no second action
            return
        self._audit(key, parsed.request, parsed.axes, requester, "accepted")
        req = _Request(parsed, self.host, now)
        req.requester = requester
        self._requests[rid] = req
        self._pending.add(req)
        req.attach(query)
        if parsed.request.op in LEASE_OPS:
            self._lease_command(req, parsed)
        else:
            self._submit(req, parsed)

    def _submit(self, req: _Request, parsed: ParsedCommand) -> None:
        r = parsed.request
        if self._conflict_text and r.op in CONFLICT_REFUSED_OPS:
            # Another agent may obey the same command: nothing that raises power or clears a fault.
            for axis in parsed.axes or ("",):
                self._outcome(req, rt.Outcome(axis, "rejected", state=self._state(axis), reason=self._conflict_text))
            return
        on_outcome = functools.partial(self._outcome_from_cycle, req)
        if not parsed.axes:  # agent command
            blocked = self._blocking_leases(r.supervisor, [parsed.args["axis"]] if parsed.args.get("axis") else self.axes)
            if blocked:
                self._outcome(req, rt.Outcome("", "busy", reason=f"leased: {blocked}"))
                return
            cmd: rt.DriveCommand | rt.AgentCommand = rt.AgentCommand(
                request_id=r.request_id, op=r.op, args=dict(parsed.args), timeout_s=r.timeout_s,
                supervisor=r.supervisor, received_ns=req.received_ns, on_outcome=on_outcome)
            if not self.cycle.submit(cmd):
                self._outcome(req, rt.Outcome("", "busy", reason=self._refused()))
            return
        free = []
        for axis in parsed.axes:
            holder = self.leases.check(axis, r.supervisor)
            if holder:
                self._outcome(req, rt.Outcome(axis, "busy", state=self._state(axis),
                                              reason=f"drive {self.host}/{axis} is leased by {holder}"))
            else:
                free.append(axis)
        if not free:
            return
        cmd = rt.DriveCommand(request_id=r.request_id, op=r.op, axes=tuple(free), args=dict(parsed.args),
                              timeout_s=r.timeout_s, supervisor=r.supervisor, received_ns=req.received_ns,
                              on_outcome=on_outcome)
        if not self.cycle.submit(cmd):
            reason = self._refused()
            for axis in free:
                self._outcome(req, rt.Outcome(axis, "busy", state=self._state(axis), reason=reason))

    def _refused(self) -> str:
        """Why ``cycle.submit`` said no."""
        state = getattr(self.cycle, "state", "running")
        if state != "running":
            return f"agent {self.host} is {state}: command not taken"
        return "command inbox full: retry"

    def _blocking_leases(self, supervisor: str, axes: Iterable[str]) -> str:
        blocked = [f"{a} by {h}" for a in axes if (h := self.leases.check(a, supervisor))]
        return ", ".join(blocked)

    def _outcome_from_cycle(self, req: _Request, outcome: rt.Outcome) -> None:
        """Called from the cycle thread: enqueue only. (The cycle publishes its own outcome event.)"""
        self._inbox.put((self._outcome, (req, outcome, False)))

    def _outcome(self, req: _Request, outcome: rt.Outcome, event: bool = True) -> None:
        """Record one axis' terminal outcome and answer the waiting queries. ``event``: also
        publish an ``outcome`` event (for outcomes the gateway decided itself)."""
        if outcome.axis in req.replies or outcome.axis not in req.axes:
            return
        reply = self._reply(req, outcome)
        req.add(reply)
        if event and outcome.axis:
            detail = f"{req.op} {reply.outcome}" + (f": {reply.reason}" if reply.reason else "")
            self._emit(rt.CycleEvent(outcome.axis, "outcome", detail=detail, to_state=reply.state,
                                     error_code=reply.error_code, request_id=req.request_id))
        if req.done:
            self._pending.discard(req)
            log.info("agent %s: command %s op %s from %s finished: %s", self.host, req.request_id, req.op,
                     req.requester, ", ".join(f"{a or 'agent'}={r.outcome}" for a, r in sorted(req.replies.items())))

    def _reply(self, req: _Request, o: rt.Outcome) -> m.CommandReply:
        outcome = o.outcome if o.outcome in m.OUTCOMES else "failed"
        key = f"{req.op}.{outcome}"
        self._command_counts[key] = self._command_counts.get(key, 0) + 1
        return m.CommandReply(
            request_id=req.request_id, host=self.host, op=req.op,
            outcome=outcome, axis=o.axis,
            state=o.state if o.state in m.DRIVE_STATES else "unknown", error_code=o.error_code & 0xFFFF,
            reason=o.reason[:400], elapsed_s=o.elapsed_s or (time.monotonic_ns() - req.received_ns) / 1e9,
            cycles=o.cycles, lease_holder=self.leases.holder(o.axis) if o.axis else "",
            duration_s=min(max(o.duration_s, 0.0), 1e6),
        )

    def _emit(self, ev: rt.CycleEvent) -> None:
        snap = self._latest
        self._events.append((ev, snap.cycle if snap else 0, time.time_ns()))
        self._wake.set()

    def _state(self, axis: str) -> str:
        snap = self._latest
        if snap is not None:
            for d in snap.drives:
                if d.axis == axis:
                    return d.state
        return "unknown"

    def _forget_old(self, now: float) -> None:
        while self._requests:
            rid, req = next(iter(self._requests.items()))
            if len(self._requests) > DEDUP_SIZE or (req.done and now - req.created_s > DEDUP_TTL_S):
                self._requests.popitem(last=False)
            else:
                break

    # -- leases

    def _lease_command(self, req: _Request, parsed: ParsedCommand) -> None:
        args, r = parsed.args, parsed.request
        holder = args["holder"]
        now = time.monotonic()
        if r.op == "lease":
            ttl = args["ttl_s"] if "ttl_s" in r.args else self.s.lease_ttl_s.get(parsed.axes[0], args["ttl_s"])
            decisions = self.leases.acquire(parsed.axes, holder, ttl, args["takeover"], now)
        else:
            decisions = self.leases.release(parsed.axes, holder)
        self._lease_holders = self.leases.holders()
        self._wake.set()
        for dec in decisions:
            self._lease_outcome(req, dec)

    def _lease_outcome(self, req: _Request, dec: LeaseDecision) -> None:
        where = f"drive {self.host}/{dec.axis}"
        if dec.result is LeaseResult.BUSY:
            reason = f"{where} is leased by {dec.previous}" if dec.previous == dec.holder else \
                     f"lease refused: another addressed drive is leased by {dec.previous}"
            self._outcome(req, rt.Outcome(dec.axis, "busy", state=self._state(dec.axis), reason=reason))
            return
        if dec.result is LeaseResult.TAKEN_OVER:
            self._emit(rt.CycleEvent(dec.axis, "lease", detail=f"lease taken over by {dec.holder} from {dec.previous}",
                                     request_id=req.request_id))
        elif dec.result in (LeaseResult.GRANTED, LeaseResult.RELEASED):
            who = dec.holder or dec.previous
            self._emit(rt.CycleEvent(dec.axis, "lease", detail=f"lease {dec.result.value} ({who})",
                                     request_id=req.request_id))
        self._outcome(req, rt.Outcome(dec.axis, "done", state=self._state(dec.axis), reason=dec.result.value))

    def _on_supervisor_token(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.DELETE:
            return
        try:
            name = keys.parse(str(sample.key_expr)).name
        except keys.InvalidKey:
            return
        if name:
            ended = self.leases.holder_lost(name)
            if ended:
                self._leases_ended(ended)

    def _leases_ended(self, ended: list[EndedLease]) -> None:
        """Lease expired or holder lost: run the configured reaction on those drives."""
        self._lease_holders = self.leases.holders()
        self._wake.set()
        by_reaction: dict[tuple[str, ...], list[str]] = {}
        for e in ended:
            why = "expired" if e.why.value == "expired" else "holder's liveliness token disappeared"
            reaction = self.s.lease_reaction.get(e.lease.axis, "quick_stop_then_disable")
            ops = LEASE_REACTION_OPS.get(reaction, LEASE_REACTION_OPS["quick_stop_then_disable"])
            log.warning("drive %s/%s: lease of %s %s: %s", self.host, e.lease.axis, e.lease.holder, why,
                        " then ".join(ops) or "no reaction")
            self._emit(rt.CycleEvent(e.lease.axis, "lease",
                                     detail=f"lease of {e.lease.holder} ended ({why}): {', then '.join(ops) or 'no reaction'}"))
            if ops:
                by_reaction.setdefault(ops, []).append(e.lease.axis)
        for ops, axes in by_reaction.items():
            self._run_internal(ops, tuple(axes), "lease")

    def _run_internal(self, ops: tuple[str, ...], axes: tuple[str, ...], why: str) -> None:
        """Issue ``ops[0]`` for ``axes`` as the agent itself; each next op after every axis answered."""
        if not ops:
            return
        self._internal_seq += 1
        rid = f"@{self.host}-{why}-{self._internal_seq}"
        remaining = set(axes)

        def on_outcome(o: rt.Outcome) -> None:  # cycle thread
            self._inbox.put((step_done, (o,)))

        def step_done(o: rt.Outcome) -> None:
            remaining.discard(o.axis)
            if not remaining:
                self._run_internal(ops[1:], axes, why)

        cmd = rt.DriveCommand(request_id=rid, op=ops[0], axes=axes, timeout_s=5.0, supervisor=AGENT_SUPERVISOR,
                              received_ns=time.monotonic_ns(), on_outcome=on_outcome)
        if not self.cycle.submit(cmd):
            log.error("agent %s: %s reaction %s for %s could not be queued (inbox full); retrying",
                      self.host, why, ops[0], ", ".join(axes))
            threading.Timer(0.01, lambda: self._inbox.put((self._run_internal, (ops, axes, why)))).start()

    # -- one agent per host name

    def _on_own_host_status(self, sample: zenoh.Sample) -> None:
        try:
            st = m.decode(sample.payload.to_bytes(), m.AgentStatus)
        except m.SchemaError:
            return
        if self._conflicts.seen(st.instance, time.monotonic()):
            self._conflict_changed()

    def _conflict_changed(self) -> None:
        self._conflict_text = self._conflicts.text
        if self._conflict_text:
            log.error("agent %s: %s", self.host, self._conflict_text)
        else:
            log.warning("agent %s: host name conflict over (no other instance for %.0f s)", self.host,
                        self._conflicts.hold_s)
        self._emit(rt.CycleEvent("", "conflict", detail=self._conflict_text or "host name conflict over"))
        self._next_agent_s = 0.0  # say it in the agent status now

    # -- cross-host groups

    def _on_remote_status(self, sample: zenoh.Sample) -> None:
        try:
            st = m.decode(sample.payload.to_bytes(), m.DriveStatus)
        except m.SchemaError as exc:
            log.warning("remote status on %s undecodable: %s", sample.key_expr, exc)
            return
        bad = st.lost or st.state in BAD_STATES
        reason = f"{st.host}/{st.axis} {'lost' if st.lost else st.state}"
        for r in self._remotes:
            if r.host == st.host and r.axis == st.axis:
                if not r.seen:
                    r.seen = True
                    log.info("agent %s: group %s member %s/%s seen: %s", self.host, r.group, r.host, r.axis,
                             "lost" if st.lost else st.state)
                self._remote_member(r, bad, reason)

    def _on_remote_token(self, sample: zenoh.Sample) -> None:
        try:
            host = keys.parse(str(sample.key_expr)).host
        except keys.InvalidKey:
            return
        if sample.kind == zenoh.SampleKind.DELETE:
            for r in self._remotes:
                if r.host == host:
                    self._remote_member(r, True, f"agent {host} lost (liveliness)")

    def _remote_member(self, r: _Remote, bad: bool, reason: str) -> None:
        if bad and not r.bad:
            log.warning("agent %s: group %s member %s/%s: %s -> trigger", self.host, r.group, r.host, r.axis, reason)
            self.cycle.trigger_group(r.group, reason)
        r.bad = bad


def _undeclare(decl: Any) -> None:
    try:
        decl.undeclare()
    except Exception as exc:
        log.debug("undeclare: %s", exc)
