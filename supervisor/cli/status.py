"""Verbs that look: status, watch."""

from __future__ import annotations

import argparse
import json
from typing import Callable

from rich.console import Console

from ..fleet import Fleet
from .common import EXIT_OK, open_fleet, positive_s


def _status(args: argparse.Namespace, console: Console) -> int:
    from ..watch import status_rows, status_table
    with open_fleet(args) as fleet:
        if args.selectors:
            fleet.select(*args.selectors)
        rows = status_rows(fleet, args.selectors)
        if args.json:
            print(json.dumps({"agents": agent_rows(fleet), "drives": rows, "supervisors": fleet.supervisors()},
                             indent=1))
        else:
            console.print(status_table(rows, f"{len(fleet.hosts())} agent(s), {len(rows)} drive(s)"))
    return EXIT_OK


def agent_rows(fleet: Fleet) -> dict[str, dict]:
    """One JSON-ready entry per known agent: liveliness, state, cycle figures."""
    agents = {}
    for h, a in sorted(fleet.agents().items()):
        st = a.status
        agents[h] = {"alive": a.alive, "state": st.state if st else None,
                     "backend": st.backend if st else None, "axes": list(st.axes) if st else None,
                     "groups": dict(st.groups) if st else {}, "leases": dict(st.leases) if st else {},
                     "cycle_us": st.cycle_us if st else None, "overruns": st.overruns if st else None}
    return agents


def _watch(args: argparse.Namespace, console: Console) -> int:
    from ..watch import run_watch
    with open_fleet(args) as fleet:
        if args.selectors:
            fleet.select(*args.selectors)  # bad or empty selectors: exit 2 before drawing
        return run_watch(fleet, args.selectors, console=console, duration_s=args.duration)


def register(add_verb: Callable[..., argparse.ArgumentParser]) -> None:
    """Declare this module's verbs."""
    add_verb("status", "table (or --json) of every drive", _status)
    w = add_verb("watch", "live table, redrawn on every status change", _watch)
    w.add_argument("--duration", type=positive_s, default=None, metavar="S", help="stop after S seconds")
