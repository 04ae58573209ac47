"""Verbs that look: status, watch."""

from __future__ import annotations

import argparse
import json
from typing import Callable

from rich.console import Console

from ..fleet import Fleet
from ..watch import agent_rows, agent_table, run_watch, run_watch_json, status_rows, status_table
from .common import EXIT_FAILED, EXIT_OK, known_targets, open_fleet, positive_s


def _title(fleet: Fleet, rows: list[dict]) -> str:
    title = f"{len(fleet.hosts())} agent(s), {len(rows)} drive(s)"
    absent = sorted({r.host for r in fleet.absent()} - set(fleet.hosts()))
    extra = [f"offline: {', '.join(absent)}" if absent else "",
             f"unexpected: {', '.join(fleet.unexpected_hosts())}" if fleet.unexpected_hosts() else "",
             f"HOST NAME CONFLICT: {', '.join(fleet.conflicts())}" if fleet.conflicts() else ""]
    return "; ".join([title, *[e for e in extra if e]])


def _status(args: argparse.Namespace, console: Console) -> int:
    with open_fleet(args) as fleet:
        if args.selectors:
            fleet.select(*known_targets(fleet, args.selectors))
        rows = status_rows(fleet, args.selectors)
        if args.json:
            print(json.dumps({"agents": agent_rows(fleet), "drives": rows, "supervisors": fleet.supervisors(),
                              "conflicts": fleet.conflicts(), "absent": [str(r) for r in fleet.absent()],
                              "unexpected_hosts": fleet.unexpected_hosts()}, indent=1))
        else:
            console.print(status_table(rows, _title(fleet, rows)))
            if args.verbose:
                console.print(agent_table(agent_rows(fleet)))
            for host, text in sorted(fleet.conflicts().items()):
                console.print(f"{host}: {text}", style="bold red")
        # Offline expected drives and host name conflicts are news an operator must not miss.
        return EXIT_FAILED if fleet.conflicts() or fleet.absent() else EXIT_OK


def _watch(args: argparse.Namespace, console: Console) -> int:
    with open_fleet(args) as fleet:
        if args.selectors:
            fleet.select(*known_targets(fleet, args.selectors))  # bad selectors: exit 2 before drawing
        if args.json:
            return run_watch_json(fleet, args.selectors, duration_s=args.duration)
        return run_watch(fleet, args.selectors, console=console, duration_s=args.duration)


def register(add_verb: Callable[..., argparse.ArgumentParser]) -> None:
    """Declare this module's verbs."""
    add_verb("status", "table (or --json) of every drive; exit 1 when an expected drive is offline or a "
             "host name is used by two agents", _status)
    w = add_verb("watch", "live table redrawn on every status change (--json: one line per change)", _watch)
    w.add_argument("--duration", type=positive_s, default=None, metavar="S", help="stop after S seconds")
