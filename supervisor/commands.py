"""The Fleet's commands: requests, fan-out queries, one result per addressed drive.

The :class:`FleetCommands` part of :class:`supervisor.fleet.Fleet`: every verb of the Fleet ends
in :meth:`FleetCommands.send`, which sends the queries a selection plans
(``selectors.plan_queries``) with this supervisor's identity and gathers exactly one
:class:`~supervisor.results.DriveResult` per addressed drive (``missing`` for a drive that
never answered), or in :meth:`FleetCommands.nmt` (one result per agent).
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
from schemas.messages import CommandReply, CommandRequest, NMT_COMMANDS, SchemaError, decode, encode

from .results import CommandResult, DriveResult, aggregate
from .selectors import DriveRef, Selection, SelectorError, parse_selector

if TYPE_CHECKING:
    from .view import FleetView

log = logging.getLogger("supervisor.fleet")

#: Extra time a query waits beyond the agents' own deadline (transport and scheduling).
REPLY_MARGIN_S = 1.0
DEFAULT_TIMEOUT_S = 5.0

#: The user a gateway (drives-opcua) sends the current thread's commands for: carried in every
#: request (``on_behalf_of``) so the agents' audit names them. Set with :func:`acting_for`.
ACTING_FOR: contextvars.ContextVar[str] = contextvars.ContextVar("fleet_acting_for", default="")


@contextlib.contextmanager
def acting_for(user: str) -> Iterator[None]:
    """Commands sent from this thread (and threads it starts through ``contextvars``) inside the
    block carry ``user`` as ``on_behalf_of`` (see ``Fleet.acting_for``)."""
    token = ACTING_FOR.set(keys.validate_name(user, "user"))
    try:
        yield
    finally:
        ACTING_FOR.reset(token)


@dataclass(eq=False)  # identity: a set member of FleetCommands while it waits
class _Collector:
    """Replies of one command, filled from Zenoh reply callbacks under its own condition ``cv``.

    Not under the view's lock: that one is notified for every status sample (about 200 per
    phase of a 64-drive enable), and each notification woke the waiting caller to walk every
    addressed drive, competing for the GIL with the reply callbacks it waited for."""

    addressed: frozenset[DriveRef]
    replies: dict[DriveRef, CommandReply] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    finished: int = 0
    #: Addressed drives per host still without a reply.
    left: dict[str, int] = field(default_factory=dict)
    #: Guards the fields above; notified on progress (a host complete, an error, a query's end)
    #: and by :meth:`FleetCommands.departed` when an agent departs.
    cv: threading.Condition = field(default_factory=threading.Condition)

    def __post_init__(self) -> None:
        for ref in self.addressed:
            self.left[ref.host] = self.left.get(ref.host, 0) + 1

    def add(self, ref: DriveRef, reply: CommandReply) -> bool:
        """Keep the first reply per drive; True when it was the last one its host owed. The
        waiting caller is woken then (once per host), not for every one of 64 replies: each
        wake-up walks every addressed drive and asks the view for the live hosts, under the
        lock the status callbacks need too."""
        if ref in self.replies:
            return False
        self.replies[ref] = reply
        if ref not in self.addressed:
            return False
        self.left[ref.host] -= 1
        return self.left[ref.host] == 0


class FleetCommands:
    """Requests and their replies for a Fleet named ``name`` (authenticated as ``identity``, or
    None): given the session (``session()``), the view (live hosts, conflicts, drives) and
    ``selection_of`` (a selection of exactly some drives); owns the commands waiting for replies."""

    def __init__(self, name: str, identity: str | None, session: Callable[[], zenoh.Session], view: "FleetView",
                 selection_of: Callable[[Iterable[DriveRef]], Selection]) -> None:
        self.name = name
        self.identity = identity
        self._session = session
        self._view = view
        self._selection_of = selection_of
        self._lock = threading.Lock()
        self.collectors: set[_Collector] = set()   # commands waiting for replies
        self._rid = itertools.count(1)

    def departed(self, host: str) -> None:
        """An agent is gone: every command waiting wakes up to stop waiting for it."""
        with self._lock:
            waiting = list(self.collectors)
        for col in waiting:
            with col.cv:
                col.cv.notify_all()

    def _request_id(self, op: str) -> str:
        return f"{self.name}-{op}-{next(self._rid)}-{uuid.uuid4().hex[:8]}"

    def request(self, op: str, args: Mapping[str, Any] | None, timeout_s: float) -> CommandRequest:
        """The request of every command this Fleet sends: its id, this supervisor, and the user
        it acts for (:func:`acting_for`), if any."""
        return CommandRequest(self._request_id(op), op, dict(args or {}), float(timeout_s), self.name,
                              ACTING_FOR.get())

    def query(self, keyexprs: Sequence[str], request: CommandRequest,
               addressed: Iterable[DriveRef], wait_s: float, agent_level: bool = False) -> CommandResult:
        """Send one query per key expression at once; collect one reply per addressed drive.

        Each query carries its own request id (``<id>.<n>`` when there are several): an agent
        treats a repeated id as the same request, so two queries reaching one agent with one id
        would be refused as a reuse for other drives.
        """
        s = self._session()
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
            self.collectors.add(col)  # woken when an agent departs (departed)
        try:
            for ke, req in payloads:
                s.get(ke, zenoh.handlers.Callback(on_reply, on_done), target=zenoh.QueryTarget.ALL,
                      consolidation=zenoh.ConsolidationMode.NONE, timeout=wait_s, payload=encode(req))
            while True:
                alive = self._view.alive()  # not under col.cv: the view's lock is taken alone
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
                self.collectors.discard(col)
            gone = {r.host for r in col.addressed} - self._view.alive()
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

    def send(self, op: str, sel: "Selection", args: Mapping[str, Any] | None = None,
             timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Send ``op`` as ``sel`` plans it (its queries as they are). A synchronized move comes
        here only from the group path, with the axes named per host (``targets`` or ``axes``):
        planned otherwise it would start as several groups (ValueError)."""
        args = dict(args or {})
        if op == "move" and args.get("sync") and not ("targets" in args or "axes" in args):
            raise ValueError("a synchronized move goes through Fleet.command or Fleet.group_move (one group)")
        req = self.request(op, args, timeout_s)
        conflicts = self._view.conflicts()
        refused = [DriveResult(r.host, r.axis, "rejected", error=f"not sent: {conflicts[r.host]}")
                   for r in sel.drives if r.host in conflicts]
        if refused:
            log.error("supervisor %s: %s not sent to %s: host name conflict", self.name, op,
                      ", ".join(sorted({r.host for r in refused})))
            sel = self._selection_of([r for r in sel.drives if r.host not in conflicts])
        if not sel.drives:
            return CommandResult(op, req.request_id, tuple(refused))
        res = self.query(sel.plan.keyexprs(op, self.identity), req, sel.drives, timeout_s + REPLY_MARGIN_S)
        if refused:
            res = dataclasses.replace(res, results=tuple(sorted((*res.results, *refused),
                                                                key=lambda r: (r.host, r.axis))))
        return res

    def nmt(self, command: str, hosts: Sequence[str] = ("*",), axis: str | int | None = None,
            timeout_s: float = DEFAULT_TIMEOUT_S) -> CommandResult:
        """Network management on agents (``.../agent/cmd/nmt``): start (-> OP), stop
        (-> SAFE-OP), preop, reset_comm, reset_node (cia402.md section 5), for the slave of one
        axis (a name, or a slave position looked up in the drive status) or the whole segment.
        One result per agent (``axis`` '')."""
        if command not in NMT_COMMANDS:
            raise ValueError(f"nmt command {command!r} is not one of {', '.join(NMT_COMMANDS)}")
        conflicts = self._view.conflicts()
        live = [h for h in self._view.hosts() if h not in conflicts]
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
        req = self.request("nmt", args, timeout_s)
        return self.query(sorted(set(keyexprs)), req, [DriveRef(h, "") for h in addressed],
                           timeout_s + REPLY_MARGIN_S, agent_level=True)

    def _axis_of_slave(self, axis: str | int, hosts: Iterable[str]) -> str:
        """An axis name, or the axis at slave position ``axis`` on the (single) addressed host."""
        if isinstance(axis, str) and not axis.isdigit():
            return keys.validate_name(axis, "axis")
        pos = int(axis)
        hosts = sorted(hosts)
        if len(hosts) != 1:
            raise SelectorError("a slave position needs exactly one host (--host); or give an axis name")
        found = [r.axis for r, st in self._view.drives().items() if r.host == hosts[0] and st.slave == pos]
        if not found:
            info = self._view.agents().get(hosts[0])
            axes = info.status.axes if info and info.status else []
            if 0 <= pos < len(axes):
                found = [axes[pos]]
        if not found:
            raise SelectorError(f"no drive at slave position {pos} on {hosts[0]}")
        return found[0]


__all__ = ["ACTING_FOR", "DEFAULT_TIMEOUT_S", "FleetCommands", "REPLY_MARGIN_S", "acting_for"]
