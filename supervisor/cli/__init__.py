"""``drivectl``: thin verbs over the supervisor API.

    drivectl [GLOBAL OPTIONS] VERB [SELECTOR]... [GLOBAL OPTIONS]

Global options (before or after the verb): ``--connect EP`` (repeatable), ``--json``,
``--timeout S``, ``--fleet FILE``, ``--discovery S``, ``--name``, ``--group``, ``-v``.
Selectors: ``h1/x``, ``h1/*``, ``h1``, ``*/x``, ``h*/axis?``, ``**``, ``@group``.

One module per verb group; each has ``register(add_verb)`` and is listed once in
:data:`VERB_MODULES`, so a new verb group is one new module and one line here.

Exit codes: 0 every addressed drive reached its goal; 1 some did not (listed); 2 bad selectors
or arguments (reported before anything is sent); 3 no agent reachable.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from types import ModuleType
from typing import NoReturn, Sequence

from rich.console import Console

from ..fleet import NoAgentError
from ..selectors import SelectorError
from . import agents, drives, lease, motion, recorder, sim, status
from .common import (EXIT_FAILED, EXIT_NO_AGENT, EXIT_OK, EXIT_TEXT, EXIT_USAGE, Handler, UsageError,
                     add_globals, check_syntax, merge_globals)

#: The verb groups, in the order ``--help`` lists them.
VERB_MODULES: tuple[ModuleType, ...] = (status, drives, motion, agents, lease, sim, recorder)


def build_parser() -> argparse.ArgumentParser:
    """The whole command line: global options, then one sub-parser per verb."""
    p = _Parser(prog="drivectl", description="Supervise CiA 402 drives through their Zenoh bus agents.",
                                epilog=EXIT_TEXT)
    add_globals(p, after_verb=False)
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB", parser_class=_Parser)

    def add_verb(name: str, help_: str, handler: Handler, *, selectors: bool = True,
                 stages: bool = False) -> argparse.ArgumentParser:
        sp = sub.add_parser(name, help=help_, description=help_, epilog=EXIT_TEXT)
        add_globals(sp, after_verb=True)
        sp.set_defaults(func=handler)
        if selectors:
            sp.add_argument("selectors", nargs="*", metavar="SELECTOR", help="drives (default: ** where safe)")
        if stages:
            sp.add_argument("--stage", action="append", default=[], metavar="SEL,SEL",
                            help="a stage of selectors, repeated in enable order")
        return sp

    for module in VERB_MODULES:
        module.register(add_verb)
    return p


def run(args: argparse.Namespace, console: Console) -> int:
    """Check the arguments, then run the verb's handler."""
    check_syntax(args)
    return int(args.func(args, console))


class _Parser(argparse.ArgumentParser):
    """argparse, but an argument error raises :class:`UsageError` (so ``--json`` can make it JSON)."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(f"{self.prog}: {message}")


def _fail(json_mode: bool, code: int, message: str) -> int:
    """Report an error on stderr (or as one JSON object on stdout with ``--json``) and return ``code``."""
    if json_mode:
        kind = {EXIT_USAGE: "usage", EXIT_NO_AGENT: "no_agent"}.get(code, "failed")
        print(json.dumps({"ok": False, "error": kind, "message": message, "exit_code": code}))
    else:
        Console(stderr=True, soft_wrap=True).print(f"drivectl: {message}", style="bold red", markup=False,
                                                   highlight=False)
    return code


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    json_mode = "--json" in argv
    try:
        args = merge_globals(build_parser().parse_args(argv))
    except UsageError as exc:
        if not json_mode:
            build_parser().print_usage(sys.stderr)
        return _fail(json_mode, EXIT_USAGE, str(exc).removeprefix("drivectl: "))
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if args.verbose < 2:
        logging.getLogger("supervisor").setLevel(logging.ERROR)  # the report says it all
        logging.getLogger("zenoh").setLevel(logging.ERROR)
    # Piped output (scripts, logs) keeps whole texts instead of wrapping them at 80 columns.
    console = Console(stderr=False, width=None if sys.stdout.isatty() else 240)
    try:
        return run(args, console)
    except (SelectorError, UsageError, ValueError) as exc:
        return _fail(args.json, EXIT_USAGE, str(exc))
    except NoAgentError as exc:
        return _fail(args.json, EXIT_NO_AGENT, f"no agent reachable: {exc}")
    except KeyboardInterrupt:
        return EXIT_FAILED


__all__ = ["main", "build_parser", "run", "VERB_MODULES", "EXIT_OK", "EXIT_FAILED", "EXIT_USAGE", "EXIT_NO_AGENT"]
