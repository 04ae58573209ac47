"""Command queries, pure: which axes a key addresses, who asks, the payload checked; one request's replies.

No Zenoh session here: :func:`parse_command` and :func:`axes_in_key` are pure functions of the
query (tested without a network); :class:`Request` gathers one request id's replies and answers
the queries waiting for them (touched only by the gateway's command thread).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import zenoh

from bus_agent import hops
from schemas import keys
from schemas import messages as m

log = logging.getLogger("bus_agent.gateway.gateway")

MSGPACK = zenoh.Encoding("application/msgpack")
TEXT = zenoh.Encoding.TEXT_PLAIN
#: Extra time after a command's own timeout before the gateway gives up on the cycle's outcome.
OUTCOME_GRACE_S = 2.0
#: Flight recorder queries waiting to be served (beyond: refused as busy), and how long the cycle
#: may take to produce one (an explicit request waits for its window's after part too).
RECORDING_QUEUE = 4
RECORDING_TIMEOUT_S = 10.0
#: Ops the gateway answers itself; every other drive op is carried out by the cycle.
LEASE_OPS = ("lease", "release")


class RequestError(ValueError):
    """A command query refused as a whole: answered with ``reply_err``, nothing changes."""


@functools.lru_cache(maxsize=4096)
def key_expr(key: str) -> zenoh.KeyExpr:
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
    """The axes of ``host`` whose ``cmd/<op>`` key (of ``principal``, if any) intersects ``query_key``.
    Remembered per arguments: supervisors repeat the same few keys, and working it out costs
    about 6 us per axis (a key built and intersected), 0.1 ms for 16 drives on every command."""
    return _axes_in_key(str(query_key), host, tuple(axes), op, principal)


@functools.lru_cache(maxsize=1024)
def _axes_in_key(query_key: str, host: str, axes: tuple[str, ...], op: str,
                 principal: str | None) -> tuple[str, ...]:
    qke = key_expr(query_key)
    return tuple(a for a in axes if key_expr(keys.drive_cmd(host, a, op, principal)).intersects(qke))


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
        if not key_expr(keys.agent_cmd(host, req.op, principal)).intersects(key_expr(str(query_key))):
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
    if req.op == "move" and ("targets" in args or "axes" in args):
        # A group move addresses the axes it names (one query for a part of a host's axes).
        if "targets" in args and "axes" in args:
            raise RequestError("args: give targets (absolute, per axis) or axes (with to/by), not both")
        field = "targets" if "targets" in args else "axes"
        if field == "axes" and not args.get("sync"):
            raise RequestError("args.axes names the axes of a synchronized move: it needs sync true")
        named = set(args[field])
        if not named:
            raise RequestError(f"args.{field}: empty (name the axes of the group move)")
        missing = sorted(named - set(addressed))
        if missing:
            raise RequestError(f"args.{field}: {', '.join(missing)} not addressed by {query_key} on {host}")
        addressed = tuple(a for a in addressed if a in named)
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


@functools.lru_cache(maxsize=4096)
def reply_key(host: str, axis: str, op: str, principal: str | None) -> str:
    """The key a reply for ``axis`` ('' : the agent) goes on: the command key asked, the
    authenticated form included (a reply must intersect the query). Remembered: building and
    checking 64 keys took about 0.18 ms of every 64-drive command."""
    return keys.drive_cmd(host, axis, op, principal) if axis else keys.agent_cmd(host, op, principal)


class Request:
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
        self.reply_keys = {a: reply_key(host, a, req.op, self.principal) for a in self.axes}
        self.created_s = now_s
        self.received_ns = time.monotonic_ns()
        self.deadline_s = now_s + req.timeout_s + OUTCOME_GRACE_S
        self.replies: dict[str, m.CommandReply] = {}
        self.payloads: dict[str, bytes] = {}  # each reply encoded once, for every query waiting on it
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

    def add(self, reply: m.CommandReply, payload: bytes) -> None:
        """The reply for ``reply.axis`` and its encoding (the first one given stays), sent to
        every query waiting for that axis: one axis per call, so a 64-drive command's replies
        cost 64 sends, not a walk over every waiting axis per reply."""
        axis = reply.axis
        if axis in self.replies:
            return
        self.replies[axis] = reply
        self.payloads[axis] = payload
        done = False
        for query, remaining in self.waiting:
            if axis in remaining:
                remaining.discard(axis)
                self._send(query, axis)
                done = done or not remaining
        if done:
            self._finish_answered()

    def flush(self) -> None:
        """Send every waiting query the replies it still lacks; finish the answered ones."""
        for query, remaining in self.waiting:
            for axis in [a for a in remaining if a in self.replies]:
                remaining.discard(axis)
                self._send(query, axis)
        self._finish_answered()

    def _send(self, query: zenoh.Query, axis: str) -> None:
        try:
            query.reply(self.reply_keys[axis], self.payloads[axis], encoding=MSGPACK)
            hops.stamp("gw.reply")
        except Exception as exc:  # the querier may be gone; the others still get theirs
            log.warning("reply to %s (%s) failed: %s", self.reply_keys[axis], self.request_id, exc)

    def _finish_answered(self) -> None:
        still = []
        for query, remaining in self.waiting:
            if remaining:
                still.append((query, remaining))
            else:
                finish(query)
                hops.stamp("gw.finish")
        self.waiting = still


def finish(query: zenoh.Query) -> None:
    try:
        query.drop()
    except Exception as exc:
        log.debug("query drop: %s", exc)


def reply_err(query: zenoh.Query, text: str) -> None:
    try:
        query.reply_err(text.encode("utf-8"), encoding=TEXT)
    except Exception as exc:
        log.warning("reply_err failed: %s", exc)
    finish(query)


def undeclare(decl: Any) -> None:
    """Undeclare a Zenoh entity; a failure (the session already closed) is only logged."""
    try:
        decl.undeclare()
    except Exception as exc:
        log.debug("undeclare: %s", exc)
