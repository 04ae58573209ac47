"""Verbs addressed to agents rather than drives: nmt."""

from __future__ import annotations

import argparse
from typing import Callable

from rich.console import Console

from schemas.messages import NMT_COMMANDS

from ..results import single
from ..selectors import parse_selector
from .common import UsageError, emit_report, open_fleet


def _nmt(args: argparse.Namespace, console: Console) -> int:
    for h in args.host:
        if "/" in h:
            raise UsageError(f"--host {h!r} is a host, not host/axis")
        parse_selector(h)
    with open_fleet(args) as fleet:
        res = fleet.nmt(args.command, args.host or ["*"], args.slave, timeout_s=args.timeout)
        return emit_report(args, console, single("nmt", res))


def register(add_verb: Callable[..., argparse.ArgumentParser]) -> None:
    """Declare this module's verbs."""
    n = add_verb("nmt", "network management on agents' segments", _nmt, selectors=False)
    n.add_argument("command", choices=NMT_COMMANDS)
    n.add_argument("--host", action="append", default=[], help="agent host (pattern; default every agent)")
    n.add_argument("--slave", help="only this slave: an axis name or a position (with one --host)")
