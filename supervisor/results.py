"""Per-drive command results and their aggregation: pure data, no I/O.

Every command the supervisor sends ends with one :class:`DriveResult` per addressed drive:
the agent's terminal outcome (``done``, ``failed``, ``timeout``, ``rejected``, ``busy``, see
``schemas.messages.OUTCOMES``) or ``missing`` when the drive did not answer at all. Nothing is
dropped: a drive addressed but silent is reported, never hidden.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Iterable, Mapping, Sequence

from schemas.messages import CommandReply

from .selectors import DriveRef

#: The outcome given to an addressed drive that sent no reply.
MISSING = "missing"
#: The outcome given to an addressed drive whose command was answered by no-one at once while
#: its agent is alive: on a secure deployment, the router's ACL refused it.
DENIED = "denied"


@dataclass(frozen=True)
class DriveResult:
    """The result of one command for one drive (or an agent, when ``axis`` is '')."""

    host: str
    axis: str
    outcome: str  # schemas.messages.OUTCOMES or MISSING
    state: str = "unknown"
    error_code: int = 0
    error: str = ""
    elapsed_s: float = 0.0
    lease_holder: str = ""
    duration_s: float = 0.0  # motion: the planned profile duration (move prepare: the minimum)

    @property
    def ok(self) -> bool:
        return self.outcome == "done"

    @property
    def name(self) -> str:
        return f"{self.host}/{self.axis}" if self.axis else self.host

    @classmethod
    def from_reply(cls, reply: CommandReply) -> "DriveResult":
        return cls(reply.host, reply.axis, reply.outcome, reply.state, reply.error_code,
                   reply.reason, reply.elapsed_s, reply.lease_holder, reply.duration_s)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class CommandResult:
    """All per-drive results of one command (one op, one request id)."""

    op: str
    request_id: str
    results: tuple[DriveResult, ...]
    #: replies from drives that were not in the selection when it was made (a new agent that
    #: matches a wildcard selector); reported so nothing acts unseen.
    unexpected: tuple[DriveResult, ...] = ()
    #: reply_err texts and transport errors, as received.
    errors: tuple[str, ...] = ()
    elapsed_s: float = 0.0

    @property
    def ok(self) -> bool:
        return all(r.ok for r in self.results) and all(r.ok for r in self.unexpected)

    @property
    def failures(self) -> list[DriveResult]:
        return [r for r in (*self.results, *self.unexpected) if not r.ok]

    @property
    def done(self) -> list[DriveResult]:
        return [r for r in self.results if r.ok]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for r in (*self.results, *self.unexpected):
            out[r.outcome] = out.get(r.outcome, 0) + 1
        return out

    def by_ref(self) -> dict[DriveRef, DriveResult]:
        return {DriveRef(r.host, r.axis): r for r in (*self.results, *self.unexpected)}

    def to_dict(self) -> dict[str, Any]:
        return {
            "op": self.op,
            "request_id": self.request_id,
            "ok": self.ok,
            "elapsed_s": round(self.elapsed_s, 6),
            "counts": self.counts(),
            "results": [r.to_dict() for r in self.results],
            "unexpected": [r.to_dict() for r in self.unexpected],
            "errors": list(self.errors),
        }


def aggregate(
    op: str,
    request_id: str,
    addressed: Sequence[DriveRef],
    replies: Mapping[DriveRef, CommandReply],
    *,
    errors: Iterable[str] = (),
    gone_hosts: Iterable[str] = (),
    timeout_s: float = 0.0,
    elapsed_s: float = 0.0,
    denied_reason: str = "",
) -> CommandResult:
    """Combine the replies received for ``addressed`` drives into a :class:`CommandResult`.

    A drive without a reply becomes ``missing`` with the reason: its agent is gone, the agent
    answered with an error, or nothing came back before the deadline; or ``denied`` with
    ``denied_reason`` when that is given (the caller saw the queries end at once, unanswered)
    and its agent is not gone.
    """
    errors = tuple(errors)
    gone = set(gone_hosts)
    addressed_set = set(addressed)
    results = []
    for ref in sorted(addressed_set):
        reply = replies.get(ref)
        if reply is not None:
            results.append(DriveResult.from_reply(reply))
            continue
        if ref.host in gone:
            why = f"no reply: agent {ref.host} is gone or offline"
        elif denied_reason:
            results.append(DriveResult(ref.host, ref.axis, DENIED, error=denied_reason, elapsed_s=elapsed_s))
            continue
        elif errors:
            why = "no reply; agent error(s): " + "; ".join(errors)
        else:
            why = f"no reply within {timeout_s:g} s (unknown drive or agent not answering)"
        results.append(DriveResult(ref.host, ref.axis, MISSING, error=why, elapsed_s=elapsed_s))
    unexpected = tuple(DriveResult.from_reply(r) for ref, r in sorted(replies.items()) if ref not in addressed_set)
    return CommandResult(op, request_id, tuple(results), unexpected, errors, elapsed_s)


@dataclass(frozen=True)
class Report:
    """The outcome of an orchestrated operation (several commands): each step, and why it
    stopped. ``final`` holds one result per selected drive: its last step's result."""

    action: str
    ok: bool
    steps: tuple[tuple[str, CommandResult], ...] = ()
    reason: str = ""
    final: tuple[DriveResult, ...] = field(default=())

    @property
    def failures(self) -> list[DriveResult]:
        return [r for r in self.final if not r.ok]

    def to_dict(self) -> dict[str, Any]:
        return {
            "action": self.action,
            "ok": self.ok,
            "reason": self.reason,
            "final": [r.to_dict() for r in self.final],
            "steps": [{"step": label, **res.to_dict()} for label, res in self.steps],
        }


def final_results(steps: Sequence[tuple[str, CommandResult]]) -> tuple[DriveResult, ...]:
    """The last result of every drive over ``steps`` (later steps override earlier ones)."""
    last: dict[DriveRef, DriveResult] = {}
    for _, res in steps:
        last.update(res.by_ref())
    return tuple(last[k] for k in sorted(last))


def single(action: str, result: CommandResult) -> Report:
    """Wrap a one-command operation as a :class:`Report`."""
    reason = "" if result.ok else f"{len(result.failures)} of {len(result.results) + len(result.unexpected)} drive(s) did not reach the goal"
    return Report(action, result.ok, ((result.op, result),), reason, final_results([(result.op, result)]))
