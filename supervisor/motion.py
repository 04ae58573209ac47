"""Motion commands of the supervisor API: move, jog, stop, home, and synchronized group moves.

The agents generate the trajectories (docs/motion.md); the supervisor only sends commands. Every
synchronized move (``Fleet.move(..., sync=True)``, ``drivectl move --sync``, ``Fleet.group_move``)
takes one path, :func:`_one_group`, whatever selected its drives: one ``<host>/drive/*`` query
per host naming its axes (the agent starts them in one cycle); across hosts two phases:
*prepare* (each agent plans, moves nothing, and answers its axes' minimum duration), then
*commit* (every host gets the largest duration and one wall-clock start time
:data:`START_MARGIN_S` ahead, sent concurrently). What cannot be one group is refused as a whole.
A host whose commit ends without its drives arriving (refused, failed, missing) while others
still move stops the others (``stop``, a defined stop they keep until released): a group move
never goes on as part of a group.
"""

from __future__ import annotations

import contextvars
import dataclasses
import logging
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from typing import TYPE_CHECKING, Any, Mapping, Sequence

from .results import CommandResult, DriveResult
from .selectors import DriveRef

if TYPE_CHECKING:
    from .orchestration import Fleet

log = logging.getLogger(__name__)

#: Wall-clock margin between the commit and the common start of a cross-host group move: covers
#: the commit's delivery to every agent (a query on a LAN: ~1 ms) and the hosts' clock offsets.
START_MARGIN_S = 0.25


def move_args(to: float | None = None, by: float | None = None, velocity: float | None = None,
              accel: float | None = None, jerk: float | None = None, sync: bool = False) -> dict[str, Any]:
    """The ``move`` arguments; exactly one of ``to``/``by`` (ValueError otherwise)."""
    if (to is None) == (by is None):
        raise ValueError("move: give exactly one of to (absolute) or by (relative)")
    args: dict[str, Any] = {"to": to} if to is not None else {"by": by}
    for k, v in (("velocity", velocity), ("accel", accel), ("jerk", jerk)):
        if v is not None:
            if not v > 0:
                raise ValueError(f"move: {k} must be > 0, got {v}")
            args[k] = float(v)
    if sync:
        args["sync"] = True
    return args


def _ref(r: DriveRef | str) -> DriveRef:
    if isinstance(r, DriveRef):
        return r
    host, sep, axis = str(r).partition("/")
    if not sep or not host or not axis or any(c in r for c in "*?[]"):
        raise ValueError(f"group_move: {r!r} is not a drive 'host/axis' (no wildcards)")
    return DriveRef(host, axis)


def group_move(fleet: "Fleet", targets: Mapping[DriveRef | str, float], *, velocity: float | None = None,
               accel: float | None = None, jerk: float | None = None, timeout_s: float = 30.0,
               margin_s: float = START_MARGIN_S) -> CommandResult:
    """Move every drive of ``targets`` (``{ref: absolute position}``) so they start together
    and arrive together. Any drive refusing refuses the whole move (nothing moves): the
    result then holds the refusals. One result per drive."""
    by_host: dict[str, dict[str, float]] = {}
    for r, t in targets.items():
        ref = _ref(r)
        by_host.setdefault(ref.host, {})[ref.axis] = float(t)
    if not by_host:
        raise ValueError("group_move: no targets")
    extra = {k: float(v) for k, v in (("velocity", velocity), ("accel", accel), ("jerk", jerk)) if v is not None}
    refs = [DriveRef(h, a) for h, axes in by_host.items() for a in axes]
    return _one_group(fleet, refs, {h: {"targets": t, "sync": True, **extra} for h, t in by_host.items()},
                      timeout_s=timeout_s, margin_s=margin_s)


def sync_move(fleet: "Fleet", refs: Sequence[DriveRef], args: Mapping[str, Any], *, timeout_s: float,
              margin_s: float = START_MARGIN_S) -> CommandResult:
    """A ``move`` with ``sync`` to ``refs``, whatever selected them (classes, lists, groups,
    several hosts): one group move, or refused as a whole (see :func:`_one_group`). ``to``
    goes out as per-axis ``targets``, ``by`` with the host's ``axes``. ``Fleet.command`` sends
    every synchronized move here."""
    if not refs:
        raise ValueError("move: no drive selected")
    by_host: dict[str, list[str]] = {}
    for r in sorted(set(refs)):
        by_host.setdefault(r.host, []).append(r.axis)
    # The addressing and the two phases are this path's own: a caller's are not passed on.
    base = {k: v for k, v in args.items()
            if k not in ("to", "by", "targets", "axes", "prepare", "duration_s", "start_at_ns")} | {"sync": True}
    if "to" in args and "by" not in args:
        per_host = {h: base | {"targets": {a: float(args["to"]) for a in axes}} for h, axes in by_host.items()}
    elif "by" in args and "to" not in args:
        per_host = {h: base | {"by": float(args["by"]), "axes": axes} for h, axes in by_host.items()}
    else:
        raise ValueError("move: give exactly one of to (absolute) or by (relative)")
    return _one_group(fleet, list(refs), per_host, timeout_s=timeout_s, margin_s=margin_s)


def _refused(op: str, refs: Sequence[DriveRef], why: str) -> CommandResult:
    """Every drive of a group refused with one reason (nothing sent)."""
    return CommandResult(op, "", tuple(DriveResult(r.host, r.axis, "rejected", error=why[:400])
                                       for r in sorted(set(refs))))


def _one_group(fleet: "Fleet", refs: Sequence[DriveRef], per_host: Mapping[str, dict[str, Any]], *,
               timeout_s: float, margin_s: float) -> CommandResult:
    """The one path of a synchronized move: one ``<host>/drive/*`` query per host whose args name
    its axes (the agent starts them in one cycle); across hosts, prepare on every host, then
    commit the longest duration and one start time. A drive no live agent reports, or a host in a
    name conflict, refuses the whole group before anything is sent; any refusal at prepare
    refuses it too (nothing moves)."""
    live = set(fleet.roster())
    conflicts = fleet.conflicts()
    problems = [f"{h}: {conflicts[h]}" for h in sorted(per_host) if h in conflicts]
    problems += [f"{r}: no live agent reports this drive" for r in sorted(set(refs)) if r not in live]
    if problems:
        why = "group move refused (nothing sent): " + "; ".join(problems)
        return _refused("move", refs, why)
    by_host = {h: sorted({r.axis for r in refs if r.host == h}) for h in per_host}

    def send(host: str, args: dict[str, Any]) -> CommandResult:
        # One query per host (``drive/*``): the agent addresses the axes the args name.
        sel = fleet.selection_of((DriveRef(host, a) for a in by_host[host]), per_host=True)
        return fleet.send("move", sel, {**per_host[host], **args}, timeout_s=timeout_s)

    if len(per_host) == 1:
        return send(next(iter(per_host)), {})
    with ThreadPoolExecutor(max_workers=len(per_host)) as pool:
        # Each host's query in the caller's context (the user it acts for, supervisor.commands.ACTING_FOR).
        ctx = contextvars.copy_context()
        prepared = list(pool.map(lambda h: ctx.copy().run(send, h, {"prepare": True}), per_host))
        merged = _merge("move", prepared)
        if not merged.ok:
            # Nothing moved: the drives whose host prepared fine are refused with the others' reasons.
            why = "group move refused: " + _failures_text(merged.failures)
            return dataclasses.replace(merged, results=tuple(
                r if not r.ok else dataclasses.replace(r, outcome="rejected", error=why[:400]) for r in merged.results))
        duration = max(r.duration_s for r in merged.results)
        start_at_ns = time.time_ns() + int(margin_s * 1e9)
        futures = {pool.submit(ctx.copy().run, send, h, {"duration_s": duration, "start_at_ns": start_at_ns}): h
                   for h in per_host}
        committed = _commit(fleet, futures, by_host, timeout_s)
    return _merge("move", committed)


#: Deadline of the ``stop`` sent to the rest of a group move whose commit failed on some host.
GROUP_STOP_TIMEOUT_S = 5.0


def _commit(fleet: "Fleet", futures: Mapping["Future[CommandResult]", str], by_host: Mapping[str, Sequence[str]],
            timeout_s: float) -> list[CommandResult]:
    """Wait for every host's commit. The first that ends without all its drives done (or raises)
    while others still run has those others stopped (one ``stop`` to their axes, sent in the
    caller's context), so the group never moves on in part; their moves then end ``aborted``
    naming the stop. A commit that raised is raised again once the others have answered."""
    results: list[CommandResult] = []
    error: BaseException | None = None
    pending = set(futures)
    stopped = False
    while pending:
        done, pending = wait(pending, return_when=FIRST_COMPLETED)
        failed: list[str] = []
        for f in done:
            try:
                results.append(f.result())
            except Exception as e:
                error = error or e
                failed.append(f"{futures[f]}: {e}")
        failed += [_failures_text(r.failures) for r in results if not r.ok]
        if pending and not stopped and failed:
            stopped = True
            rest = [DriveRef(futures[f], a) for f in pending for a in by_host[futures[f]]]
            log.warning("group move: %s; stopping the rest of the group (%s)", "; ".join(failed)[:400],
                        ", ".join(str(r) for r in rest))
            stop = fleet.send("stop", fleet.selection_of(rest), {}, min(timeout_s, GROUP_STOP_TIMEOUT_S))
            if not stop.ok:
                log.error("group move: the stop of the rest of the group did not complete: %s",
                          _failures_text(stop.failures)[:400])
    if error is not None:
        raise error
    return results


def _failures_text(failures: Sequence[DriveResult]) -> str:
    """``drive: outcome error`` of each failed drive, joined by ``; ``."""
    return "; ".join(f"{r.name}: {r.outcome} {r.error}".strip() for r in failures)


def _merge(op: str, parts: Sequence[CommandResult]) -> CommandResult:
    """One result of several per-host queries of one logical command."""
    results: list[DriveResult] = sorted((r for p in parts for r in p.results), key=lambda r: (r.host, r.axis))
    return CommandResult(op=op, request_id=",".join(p.request_id for p in parts), results=tuple(results),
                         unexpected=tuple(r for p in parts for r in p.unexpected),
                         errors=tuple(e for p in parts for e in p.errors),
                         elapsed_s=max((p.elapsed_s for p in parts), default=0.0))


__all__ = ["START_MARGIN_S", "GROUP_STOP_TIMEOUT_S", "move_args", "group_move", "sync_move"]
