"""Verbs that command drives: enable, disable, shutdown, switch-on, quick-stop, halt, fault-reset,
mode."""

from __future__ import annotations

import argparse
from typing import Callable

from rich.console import Console

from schemas.messages import MODES

from ..fleet import Fleet
from ..results import CommandResult, Report, single
from .common import MODE_NAMES, UsageError, emit_report, known_targets, open_fleet, stages_of

#: Verbs that move drives need an explicit target; ``**`` is there for "all".
_REQUIRED = {"enable", "disable", "shutdown", "switch-on", "halt", "mode", "fault-reset"}


def mode_value(text: str) -> int:
    """A mode of operation (0x6060) by abbreviation or number."""
    value = MODE_NAMES.get(text.lower())
    if value is None:
        try:
            value = int(text, 0)
        except ValueError:
            value = -1
    if value not in MODES:
        raise argparse.ArgumentTypeError(
            f"mode {text!r}: use one of {', '.join(f'{k}={v}' for k, v in MODE_NAMES.items())}")
    return value


def targets(args: argparse.Namespace, fleet: Fleet | None = None) -> list[str]:
    """The verb's selectors (each naming a live or expected drive when ``fleet`` is given: exit 2
    with hints otherwise); ``**`` for verbs that may default to every drive."""
    sels = list(getattr(args, "selectors", None) or [])
    if not sels and args.verb in _REQUIRED and not getattr(args, "stage", None):
        raise UsageError(f"{args.verb}: name the drives (a selector, or '**' for every drive)")
    sels = sels or ["**"]
    return known_targets(fleet, sels) if fleet is not None else sels


def _enable(fleet: Fleet, args: argparse.Namespace) -> Report | CommandResult:
    for stage in stages_of(args.stage):
        known_targets(fleet, stage)
    return fleet.enable(*targets(args, fleet), timeout_s=args.timeout, stages=stages_of(args.stage) or None)


def _down(op: str) -> Callable[[Fleet, argparse.Namespace], Report | CommandResult]:
    def run(fleet: Fleet, args: argparse.Namespace) -> Report | CommandResult:
        if args.stage:
            stages = stages_of(args.stage)
            for stage in stages:
                known_targets(fleet, stage)
            return fleet.take_down(stages, op=op, timeout_s=args.timeout)
        return single(op, fleet.command(op, fleet.select(*targets(args, fleet)), timeout_s=args.timeout))
    return run


def _simple(op: str, args_of: Callable[[argparse.Namespace], dict] = lambda a: {}
            ) -> Callable[[Fleet, argparse.Namespace], Report | CommandResult]:
    def run(fleet: Fleet, args: argparse.Namespace) -> Report | CommandResult:
        res = fleet.command(op, fleet.select(*targets(args, fleet)), args_of(args), timeout_s=args.timeout)
        return single(args.verb, res)
    return run


def _handler(fn: Callable[[Fleet, argparse.Namespace], Report | CommandResult]) -> Callable[..., int]:
    def handle(args: argparse.Namespace, console: Console) -> int:
        with open_fleet(args) as fleet:
            return emit_report(args, console, fn(fleet, args))
    return handle


def register(add_verb: Callable[..., argparse.ArgumentParser]) -> None:
    """Declare this module's verbs (``add_verb(name, help, handler, selectors=, stages=)``)."""
    add_verb("enable", "two-phase enable: all to Switched on, then all to Operation enabled", _handler(_enable),
             stages=True)
    add_verb("disable", "disable operation, shutdown, disable voltage (-> Switch on disabled)",
             _handler(_down("disable")), stages=True)
    add_verb("shutdown", "CiA 402 shutdown (transitions 2, 6, 8 -> Ready to switch on), as Fleet.shutdown",
             _handler(_down("shutdown")), stages=True)
    add_verb("switch-on", "switch on (-> Switched on)", _handler(_simple("switch_on")))
    add_verb("quick-stop", "quick stop (default: every drive)", _handler(_simple("quick_stop")))
    h = add_verb("halt", "set halt (controlword bit 8)", _handler(_simple("halt", lambda a: {"on": not a.off})))
    h.add_argument("--off", action="store_true", help="clear halt instead")
    m = add_verb("mode", "set modes of operation 0x6060 (waits for 0x6061)",
                 _handler(_simple("set_mode", lambda a: {"mode": a.mode_value})), selectors=False)
    m.add_argument("mode_value", type=mode_value, metavar="MODE", help="pp, pv, pt, hm, ip, csp, csv, cst or a number")
    m.add_argument("selectors", nargs="*", metavar="SELECTOR")
    add_verb("fault-reset", "fault reset (bit 7 edge, made by the agent)", _handler(_simple("fault_reset")))
