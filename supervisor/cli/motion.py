"""Verbs that move drives (docs/motion.md): home, move, jog, stop. Each needs explicit selectors."""

from __future__ import annotations

import argparse
from typing import Any, Callable

from ..fleet import Fleet
from ..motion import move_args
from ..results import CommandResult, Report, single
from .common import UsageError, known_targets
from .drives import _handler


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if v != v or v in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return v


def _positive(text: str) -> float:
    v = _number(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return v


def _targets(fleet: Fleet, args: argparse.Namespace) -> list[str]:
    if not args.selectors:
        raise UsageError(f"{args.verb}: name the drives (a selector, or '**' for every drive)")
    return known_targets(fleet, list(args.selectors))


def _run(op: str, args_of: Callable[[argparse.Namespace], dict[str, Any]]
         ) -> Callable[[Fleet, argparse.Namespace], Report | CommandResult]:
    def run(fleet: Fleet, args: argparse.Namespace) -> Report | CommandResult:
        cmd_args = args_of(args)
        return single(args.verb, fleet.command(op, fleet.select(*_targets(fleet, args)), cmd_args,
                                               timeout_s=args.timeout))
    return run


def _move_args(a: argparse.Namespace) -> dict[str, Any]:
    try:
        return move_args(a.to, a.by, a.velocity, a.accel, a.jerk, a.sync)
    except ValueError as e:
        raise UsageError(str(e)) from None


def _jog_args(a: argparse.Namespace) -> dict[str, Any]:
    return {"velocity": a.velocity, **({"for_s": a.for_s} if a.for_s is not None else {})}


def register(add_verb: Callable[..., argparse.ArgumentParser]) -> None:
    """Declare this module's verbs."""
    h = add_verb("home", "home (mode 6) with the axis's configured method; --timeout covers the run",
                 _handler(_run("home", lambda a: {} if a.method is None else {"method": a.method})))
    h.add_argument("--method", type=int, default=None, metavar="N", help="0x6098 homing method (e.g. 37, 35, 19)")
    m = add_verb("move", "move to a position (--to) or by a distance (--by), in the axis unit; "
                         "done in the position window at rest (--timeout must cover the move)",
                 _handler(_run("move", _move_args)))
    where = m.add_mutually_exclusive_group(required=True)
    where.add_argument("--to", type=_number, default=None, metavar="P", help="absolute target")
    where.add_argument("--by", type=_number, default=None, metavar="D", help="relative distance")
    m.add_argument("--velocity", type=_positive, default=None, metavar="V", help="max velocity (default: axis limit)")
    m.add_argument("--accel", type=_positive, default=None, metavar="A", help="max acceleration (default: axis limit)")
    m.add_argument("--jerk", type=_positive, default=None, metavar="J", help="max jerk (default: axis limit)")
    m.add_argument("--sync", action="store_true", help="one group move: every selected axis, on any host, starts together and arrives "
                   "together, or the whole move is refused (nothing moves)")
    j = add_verb("jog", "jog at a velocity until --for elapses (default: the timeout), then stop",
                 _handler(_run("jog", _jog_args)))
    j.add_argument("--velocity", type=_number, required=True, metavar="V", help="velocity (signed, unit/s)")
    j.add_argument("--for", dest="for_s", type=_positive, default=None, metavar="S", help="run this long")
    s = add_verb("stop", "stop motion and refuse motion until --release (PLCopen MC_Stop)",
                 _handler(_run("stop", lambda a: {"release": True} if a.release else {})))
    s.add_argument("--release", action="store_true", help="release a stop: motion is accepted again")
