"""``drivectl sim``: fault injection into simulated drives by axis name (test beds only).

    drivectl sim fault SEL CODE        e.g. sim fault h1/axis1 0x2310
    drivectl sim unplug SEL | sim plug SEL
    drivectl sim wkc-fault on|off [SEL]      (default every drive)

``--segment NAME`` addresses an ``ecat-sim`` by its ``--name`` (default: the host name, which
is the segment of ``bus-agent --sim``).
"""

from __future__ import annotations

import argparse
import json
from typing import Any, Callable

from rich.console import Console

from ..simctl import SimControlError, inject
from .common import EXIT_FAILED, EXIT_OK, UsageError, known_targets, open_fleet


def _code(text: str) -> int:
    try:
        code = int(text, 0)
    except ValueError:
        raise UsageError(f"sim fault: error code {text!r} is not a number (e.g. 0x2310)") from None
    if not 0 < code <= 0xFFFF:
        raise UsageError(f"sim fault: error code {text!r} must be 0x0001..0xFFFF")
    return code


def _parse(action: str, rest: list[str]) -> tuple[str, list[str], dict[str, Any]]:
    """(simulator action, selectors, arguments) from ``sim ACTION ARGS...``; UsageError (exit 2)."""
    if action == "fault":
        if len(rest) != 2:
            raise UsageError("sim fault: give SELECTOR CODE, e.g. sim fault h1/axis1 0x2310")
        return "fault", [rest[0]], {"error_code": _code(rest[1])}
    if action in ("unplug", "plug"):
        if len(rest) != 1:
            raise UsageError(f"sim {action}: give one SELECTOR, e.g. sim {action} h1/axis1")
        return action, rest, {}
    if not rest or rest[0] not in ("on", "off") or len(rest) > 2:
        raise UsageError("sim wkc-fault: give on|off [SELECTOR], e.g. sim wkc-fault on h1/axis0")
    return "wkc_fault", rest[1:] or ["**"], {"on": rest[0] == "on"}


def _sim(args: argparse.Namespace, console: Console) -> int:
    action, selectors, kwargs = _parse(args.action, list(args.args))
    with open_fleet(args) as fleet:
        known_targets(fleet, selectors)
        try:
            done = inject(fleet, action, *selectors, segment=args.segment, timeout_s=args.timeout, **kwargs)
        except SimControlError as exc:
            if args.json:
                print(json.dumps({"ok": False, "error": "sim", "message": str(exc), "exit_code": EXIT_FAILED}))
            else:
                console.print(f"sim {args.action} FAILED: {exc}", style="bold red", markup=False)
            return EXIT_FAILED
    if args.json:
        print(json.dumps({"ok": True, "action": action, "results": [
            {"drive": str(t.drive), "segment": t.segment, "slave": t.slave, "detail": d} for t, d in done]}))
    else:
        for t, d in done:
            console.print(f"{t.drive} (segment {t.segment}, slave {t.slave}): {d}", markup=False)
    return EXIT_OK


def register(add_verb: Callable[..., argparse.ArgumentParser]) -> None:
    """Declare this module's verbs."""
    s = add_verb("sim", "simulator fault injection by axis name: fault SEL CODE, unplug SEL, plug SEL, "
                 "wkc-fault on|off [SEL]", _sim, selectors=False)
    s.add_argument("action", choices=("fault", "unplug", "plug", "wkc-fault"))
    s.add_argument("args", nargs="*", metavar="ARG", help="SELECTOR [CODE] (fault), on|off [SELECTOR] (wkc-fault)")
    s.add_argument("--segment", default=None, help="simulator segment name (ecat-sim --name; default the host name)")
