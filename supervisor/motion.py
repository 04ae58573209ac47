"""Motion commands of the supervisor API: move, jog, stop, home, and synchronized group moves.

The agents generate the trajectories (docs/motion.md); the supervisor only sends commands. A
group move whose axes live on one host is one query (the agent starts them in one cycle); across
hosts it is two phases: *prepare* (each agent plans, moves nothing, and answers its axes'
minimum duration), then *commit* (every host gets the largest duration and one wall-clock start
time :data:`START_MARGIN_S` ahead, sent concurrently).
"""

from __future__ import annotations

import contextvars
import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Mapping, Sequence

from .results import CommandResult, DriveResult
from .selectors import DriveRef

if TYPE_CHECKING:
    from .orchestration import Fleet

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

    def send(host: str, args: dict[str, Any]) -> CommandResult:
        # One query per host (``drive/*``): the agent addresses the axes ``targets`` names and
        # starts them in one cycle.
        sel = fleet.selection_of((DriveRef(host, a) for a in by_host[host]), per_host=True)
        return fleet.command("move", sel, {"targets": by_host[host], "sync": True, **extra, **args},
                             timeout_s=timeout_s)

    if len(by_host) == 1:
        return send(next(iter(by_host)), {})
    with ThreadPoolExecutor(max_workers=len(by_host)) as pool:
        # Each host's query in the caller's context (the user it acts for, supervisor.commands.ACTING_FOR).
        ctx = contextvars.copy_context()
        prepared = list(pool.map(lambda h: ctx.copy().run(send, h, {"prepare": True}), by_host))
        merged = _merge("move", prepared)
        if not merged.ok:
            # Nothing moved: the drives whose host prepared fine are refused with the others' reasons.
            why = "group move refused: " + "; ".join(f"{r.name}: {r.outcome} {r.error}".strip()
                                                      for r in merged.failures)
            return dataclasses.replace(merged, results=tuple(
                r if not r.ok else dataclasses.replace(r, outcome="rejected", error=why[:400]) for r in merged.results))
        duration = max(r.duration_s for r in merged.results)
        start_at_ns = time.time_ns() + int(margin_s * 1e9)
        committed = list(pool.map(lambda h: ctx.copy().run(send, h, {"duration_s": duration, "start_at_ns": start_at_ns}),
                                  by_host))
    return _merge("move", committed)


def _merge(op: str, parts: Sequence[CommandResult]) -> CommandResult:
    """One result of several per-host queries of one logical command."""
    results: list[DriveResult] = sorted((r for p in parts for r in p.results), key=lambda r: (r.host, r.axis))
    return CommandResult(op=op, request_id=",".join(p.request_id for p in parts), results=tuple(results),
                         unexpected=tuple(r for p in parts for r in p.unexpected),
                         errors=tuple(e for p in parts for e in p.errors),
                         elapsed_s=max((p.elapsed_s for p in parts), default=0.0))


__all__ = ["START_MARGIN_S", "move_args", "group_move"]
