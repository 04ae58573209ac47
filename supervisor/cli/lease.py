"""Lease verbs: ``lease`` holds exclusive control while it runs; ``release`` gives it back.

    drivectl --name line1 lease 'h1/*' [--ttl S] [--takeover] [--duration S]
    drivectl --name line1 release 'h1/*'

``lease`` takes the lease (renewed every ttl/3), prints one line, and holds it until Ctrl-C,
SIGTERM or ``--duration``; then it releases it (no reaction runs). If the process dies, the
agents run their lease reaction. Exit 0 when held to the end, 1 when not every drive was
leased or a lease was taken over (``lease_lost``).
"""

from __future__ import annotations

import argparse
import json
from typing import Any, Callable

from rich.console import Console

from ..results import single
from .common import EXIT_FAILED, EXIT_OK, UsageError, emit_report, known_targets, open_fleet, positive_s
from bus_agent.stop_signals import StopSignals


def _selectors(args: argparse.Namespace) -> list[str]:
    if not args.selectors:
        raise UsageError(f"{args.verb}: name the drives (a selector, or '**' for every drive)")
    return list(args.selectors)


def _lease(args: argparse.Namespace, console: Console) -> int:
    lost: list[Any] = []
    # Both handled explicitly: a SIGINT that the starting shell ignored (a job started with '&'
    # from a script inherits SIGINT ignored) must still end the lease, as Ctrl-C does.
    stop = StopSignals()
    try:
        with open_fleet(args) as fleet:
            sels = known_targets(fleet, _selectors(args))
            res = fleet.lease(*sels, ttl_s=args.ttl, takeover=args.takeover, timeout_s=args.timeout)
            if not res.ok:
                return emit_report(args, console, single("lease", res))  # close() releases what was taken
            def on_lost(r: Any) -> None:
                lost.append(r)
                stop.request()

            fleet.on("lease_lost", on_lost)
            held = [str(r) for r in fleet.leases()]
            if args.json:
                print(json.dumps({"event": "leased", "holder": fleet.name, "drives": held}), flush=True)
            else:
                console.print(f"lease held by {fleet.name} on {len(held)} drive(s): {', '.join(held)}; "
                              "Ctrl-C releases it")
            stop.wait(args.duration)
            for r in lost:
                msg = f"lease on {r.name} lost: {r.outcome}, held by {r.lease_holder or '?'}"
                print(json.dumps({"event": "lease_lost", "drive": r.name, "holder": r.lease_holder})
                      if args.json else msg, flush=True)
            return EXIT_FAILED if lost else EXIT_OK
    finally:
        stop.restore()


def _release(args: argparse.Namespace, console: Console) -> int:
    with open_fleet(args) as fleet:
        res = fleet.release(*known_targets(fleet, _selectors(args)), timeout_s=args.timeout)
        return emit_report(args, console, single("release", res))


def register(add_verb: Callable[..., argparse.ArgumentParser]) -> None:
    """Declare this module's verbs."""
    le = add_verb("lease", "take exclusive control of drives and hold it until Ctrl-C (or --duration)", _lease)
    le.add_argument("--ttl", type=positive_s, default=None, metavar="S", help="lease duration, renewed every S/3 "
                    "(default 3 s)")
    le.add_argument("--takeover", action="store_true", help="take the lease even if another supervisor holds it")
    le.add_argument("--duration", type=positive_s, default=None, metavar="S", help="release after S seconds")
    add_verb("release", "give back leases held under --name (no lease reaction runs)", _release)
