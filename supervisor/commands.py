"""The Fleet's commands: one query per host plan, one result per addressed drive; the verbs; leases.

The :class:`FleetCommands` part of :class:`supervisor.fleet.Fleet` (the view -- discovery,
status, selection -- stays in :mod:`supervisor.fleet`). Every verb goes through
:meth:`FleetCommands.command`, which plans the queries (``selectors.plan_queries``), sends them
with this supervisor's identity, and gathers exactly one :class:`~supervisor.results.DriveResult`
per addressed drive (``missing`` for a drive that never answered).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import itertools
import logging
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator, Mapping, Sequence

import zenoh

from bus_agent import hops
from schemas import keys
from schemas.messages import (
    CommandReply,
    CommandRequest,
    DriveStatus,
    MODES,
    NMT_COMMANDS,
    SchemaError,
    decode,
    encode,
)

from .motion import group_move, move_args, sync_move
from .orchestration import ordered_shutdown, two_phase_enable
from .results import CommandResult, DriveResult, Report, aggregate, single
from .selectors import DriveRef, SelectorError, parse_selector

if TYPE_CHECKING:
    from .fleet import AgentInfo, Selection

log = logging.getLogger("supervisor.fleet")

#: Extra time a query waits beyond the agents' own deadline (transport and scheduling).
REPLY_MARGIN_S = 1.0
DEFAULT_TIMEOUT_S = 5.0

#: The user a gateway (drives-opcua) sends the current thread's commands for: carried in every
#: request (``on_behalf_of``) so the agents' audit names them. Set with :meth:`FleetCommands.acting_for`.
ACTING_FOR: contextvars.ContextVar[str] = contextvars.ContextVar("fleet_acting_for", default="")


@dataclass(eq=False)  # identity: a set member of the Fleet while it waits
class _Collector:
    """Replies of one command, filled from Zenoh reply callbacks under its own condition ``cv``.

    Not under the Fleet's lock: that one is notified for every status sample (about 200 per
    phase of a 64-drive enable), and each notification woke the waiting caller to walk every
    addressed drive, competing for the GIL with the reply callbacks it waited for."""

    addressed: frozenset[DriveRef]
    replies: dict[DriveRef, CommandReply] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    finished: int = 0
    #: Addressed drives per host still without a reply.
    left: dict[str, int] = field(default_factory=dict)
    #: Guards the fields above; notified on progress (a host complete, an error, a query's end)
    #: and by the Fleet when an agent departs.
    cv: threading.Condition = field(default_factory=threading.Condition)

    def __post_init__(self) -> None:
        for ref in self.addressed:
            self.left[ref.host] = self.left.get(ref.host, 0) + 1

    def add(self, ref: DriveRef, reply: CommandReply) -> bool:
        """Keep the first reply per drive; True when it was the last one its host owed. The
        waiting caller is woken then (once per host), not for every one of 64 replies: each
        wake-up walks every addressed drive under the Fleet's lock, which the status callbacks
        need too."""
        if ref in self.replies:
            return False
        self.replies[ref] = reply
        if ref not in self.addressed:
            return False
        self.left[ref.host] -= 1
        return self.left[ref.host] == 0


class FleetCommands:
    """Commands, verbs and leases of a :class:`~supervisor.fleet.Fleet`."""

    if TYPE_CHECKING:  # the Fleet state and view these commands use
        name: str
        identity: str | None
        lease_ttl_s: float
        _lock: threading.Condition
        _collectors: set[_Collector]
        _agents: dict[str, AgentInfo]
        _leases: dict[DriveRef, float]
        _lease_selectors: list[tuple[str, ...]]
        _renewer: threading.Thread | None
        _rid: itertools.count
        _stop: threading.Event

        @property
        def session(self) -> zenoh.Session: ...

        def _emit(self, event: str, *args: Any) -> None: ...

        def _as_selection(self, target: "Selection | str | Sequence[str]") -> Selection: ...

        def selection_of(self, refs: Iterable[DriveRef], *, per_host: bool = False) -> Selection: ...

        def agents(self) -> dict[str, AgentInfo]: ...

        def conflicts(self) -> dict[str, str]: ...

        def drives(self) -> dict[DriveRef, DriveStatus]: ...

        def hosts(self) -> list[str]: ...

        def select(self, *selectors: str, allow_empty: bool = False) -> Selection: ...

        def roster(self) -> list[DriveRef]: ...

        def fetch_status(self, target: "Selection | str | Sequence[str]",
                         timeout_s: float = 2.0) -> dict[DriveRef, DriveStatus]: ...

    # ---- commands ------------------------------------------------------------------------

    def _request_id(self, op: str) -> str:
        return f"{self.name}-{op}-{next(self._rid)}-{uuid.uuid4().hex[:8]}"

    def _request(self, op: str, args: Mapping[str, Any] | None, timeout_s: float) -> CommandRequest:
        """The request of every command this Fleet sends: its id, this supervisor, and the user
        it acts for (:meth:`acting_for`), if any."""
        return CommandRequest(self._request_id(op), op, dict(args or {}), float(timeout_s), self.name,
                              ACTING_FOR.get())

    @contextlib.contextmanager
    def acting_for(self, user: str) -> Iterator[None]:
        """Commands sent from this thread (and threads it starts through ``contextvars``) inside
        the block carry ``user`` as ``on_behalf_of``: a gateway's way to have the agents' audit
        name the person (an OPC UA user) behind its own principal. ``user`` must be a legal name."""
        token = ACTING_FOR.set(keys.validate_name(user, "user"))
        try:
            yield
        finally:
            ACTING_FOR.reset(token)

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
            hops.stamp("sup.reply")
            if reply.ok is not None:
                try:
                    msg = decode(reply.ok.payload.to_bytes(), CommandReply)
                except SchemaError as exc:
                    with col.cv:
                        col.errors.append(f"bad reply on {reply.ok.key_expr}: {exc}")
                    return
                if msg.request_id not in ids:
                    return
                ref = DriveRef(msg.host, "" if agent_level else msg.axis)
                with col.cv:
                    if col.add(ref, msg):
                        col.cv.notify_all()
            else:
                text = reply.err.payload.to_string() if reply.err is not None else "?"
                if text != "Timeout":  # zenoh's own end-of-query marker, not an agent's answer
                    with col.cv:
                        col.errors.append(text)
                        col.cv.notify_all()

        def on_done() -> None:
            with col.cv:
                col.finished += 1
                col.cv.notify_all()

        hops.stamp(f"sup.send.{request.op}")
        deadline = t0 + wait_s + 0.2
        with self._lock:
            self._collectors.add(col)  # woken when an agent departs
        try:
            for ke, req in payloads:
                s.get(ke, zenoh.handlers.Callback(on_reply, on_done), target=zenoh.QueryTarget.ALL,
                      consolidation=zenoh.ConsolidationMode.NONE, timeout=wait_s, payload=encode(req))
            while True:
                with self._lock:  # not nested in col.cv: the Fleet takes col.cv inside its lock
                    alive = {h for h, a in self._agents.items() if a.alive}
                with col.cv:
                    waiting = [r for r in col.addressed if r not in col.replies and r.host in alive]
                    if not waiting or col.finished >= len(keyexprs):
                        break
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    col.cv.wait(min(left, 0.05))
        finally:
            with self._lock:
                self._collectors.discard(col)
                gone = {r.host for r in col.addressed} - {h for h, a in self._agents.items() if a.alive}
        with col.cv:
            replies = dict(col.replies)
            errors = list(col.errors)
        elapsed = time.monotonic() - t0
        hops.stamp(f"sup.done.{request.op}")
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
        fan-out query per planned key expression, one result per selected drive. A ``move`` with
        ``sync`` goes through the group move whatever the selectors
        (:func:`supervisor.motion.sync_move`): one group, or refused as a whole."""
        sel = self._as_selection(target)
        if op == "move" and (args or {}).get("sync"):
            return sync_move(self, sel.drives, dict(args or {}), timeout_s=timeout_s)
        return self.send(op, sel, args, timeout_s)

    def send(self, op: str, sel: "Selection", args: Mapping[str, Any] | None = None,
             timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Send ``op`` as ``sel`` plans it (its queries as they are). A synchronized move comes
        here only from the group path, with the axes named per host (``targets`` or ``axes``):
        planned otherwise it would start as several groups (ValueError)."""
        args = dict(args or {})
        if op == "move" and args.get("sync") and not ("targets" in args or "axes" in args):
            raise ValueError("a synchronized move goes through Fleet.command or Fleet.group_move (one group)")
        req = self._request(op, args, timeout_s)
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
        req = self._request("nmt", args, timeout_s)
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
