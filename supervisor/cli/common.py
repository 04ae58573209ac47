"""What every ``drivectl`` verb shares: exit codes, global options, argument types, the Fleet.

Global options are accepted before or after the verb (``drivectl --json status`` and ``drivectl
status --json`` are the same): :func:`add_globals` declares them on the top-level parser with
their defaults and on every verb's parser without defaults; :func:`merge_globals` folds the
second set into the first after parsing.
"""

from __future__ import annotations

import argparse
import json
import os
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

from rich.console import Console

from ..fleet import Fleet, NoAgentError
from ..session import DEFAULT_CONNECT
from ..fleetfile import FLEET_ENV, load as load_fleet
from ..results import CommandResult, Report
from ..selectors import SelectorError, parse_selector

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_NO_AGENT = 0, 1, 2, 3
EXIT_TEXT = "exit codes: 0 every addressed drive reached its goal, 1 some did not (listed), " \
            "2 bad arguments or selectors (nothing sent), 3 no router or agent reachable"

#: Mode names accepted by ``drivectl mode`` (0x6060 values, CiA 402 abbreviations).
MODE_NAMES = {"pp": 1, "pv": 3, "pt": 4, "hm": 6, "ip": 7, "csp": 8, "csv": 9, "cst": 10}

#: A verb handler: parsed arguments and the console in, an exit code out.
Handler = Callable[[argparse.Namespace, Console], int]


class UsageError(Exception):
    """Bad arguments found after argparse (exit 2, nothing sent)."""


def positive_s(text: str) -> float:
    """A duration in (0, 3600] seconds."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0 < v <= 3600:
        raise argparse.ArgumentTypeError(f"{text!r} must be in (0, 3600] seconds")
    return v


def endpoint(text: str) -> str:
    """A zenoh endpoint ``proto/address`` (e.g. ``tcp/127.0.0.1:7447``); exit 2 otherwise."""
    proto, sep, addr = text.partition("/")
    if not sep or proto not in ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream") or not addr:
        raise argparse.ArgumentTypeError(f"endpoint {text!r}: use PROTO/ADDRESS, e.g. tcp/127.0.0.1:7447")
    if proto in ("tcp", "udp", "tls", "quic", "ws"):
        host, colon, port = addr.rpartition(":")
        if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise argparse.ArgumentTypeError(f"endpoint {text!r}: {proto} needs HOST:PORT with a port 1..65535")
    return text


# name, argparse keyword arguments (defaults apply only on the top-level parser)
_GLOBALS: tuple[tuple[tuple[str, ...], dict[str, Any]], ...] = (
    (("--connect", "-c"), dict(action="append", type=endpoint, metavar="EP",
                               help=f"zenoh endpoint (repeat for fail-over; default {DEFAULT_CONNECT[0]})")),
    (("--mode",), dict(choices=("client", "peer"), default="client", help="zenoh session mode (default client)")),
    (("--json",), dict(action="store_true", default=False, help="machine-readable output (errors too)")),
    (("--timeout",), dict(type=positive_s, default=5.0, metavar="S", help="per-command deadline (default 5 s)")),
    (("--discovery",), dict(type=positive_s, default=1.0, metavar="S",
                            help="how long to wait for agents to answer at start (default 1 s)")),
    (("--name",), dict(default=None, help="supervisor name (default sup-<host>-<pid>)")),
    (("--group",), dict(action="append", default=[], metavar="NAME=H/A,H/A",
                        help="define a local group usable as @NAME")),
    (("--fleet",), dict(default=None, metavar="FILE",
                        help="expected fleet (TOML; default $DRIVES_FLEET): absent drives show as offline "
                             "and are reported missing")),
    (("-v", "--verbose"), dict(action="count", default=0, help="more detail (agent cycle figures; -vv logs)")),
    (("--pki",), dict(default=None, metavar="DIR",
                      help="drives-pki directory: mutual TLS, commands as --identity (default $DRIVES_PKI)")),
    (("--identity",), dict(default=None, metavar="NAME",
                           help="your principal in --pki (default $DRIVES_IDENTITY)")),
)
_POST = "post_"


def _dest(flags: Sequence[str]) -> str:
    return next(f for f in flags if f.startswith("--"))[2:].replace("-", "_")


def add_globals(parser: argparse.ArgumentParser, *, after_verb: bool) -> None:
    """Declare the global options on ``parser``: with defaults on the top-level parser, without
    (and under another name) on a verb's parser, so that a value given before the verb survives."""
    for flags, kw in _GLOBALS:
        kw = dict(kw)
        if after_verb:
            kw["default"] = argparse.SUPPRESS
            kw["dest"] = _POST + _dest(flags)
        parser.add_argument(*flags, **kw)


def merge_globals(args: argparse.Namespace) -> argparse.Namespace:
    """Fold the options given after the verb into those given before it (lists append, counts add)."""
    for flags, kw in _GLOBALS:
        dest = _dest(flags)
        post = _POST + dest
        if not hasattr(args, post):
            continue
        value = getattr(args, post)
        delattr(args, post)
        if kw.get("action") == "append":
            setattr(args, dest, (getattr(args, dest) or []) + value)
        elif kw.get("action") == "count":
            setattr(args, dest, (getattr(args, dest) or 0) + value)
        else:
            setattr(args, dest, value)
    return args


def stages_of(specs: Sequence[str]) -> list[list[str]]:
    """``--stage a,b --stage c`` -> ``[[a, b], [c]]``."""
    stages = []
    for spec in specs:
        stage = [s.strip() for s in spec.split(",") if s.strip()]
        if not stage:
            raise UsageError(f"--stage {spec!r} is empty")
        stages.append(stage)
    return stages


def local_groups(specs: Sequence[str]) -> dict[str, list[str]]:
    """``--group NAME=h/a,h/a`` options as a group table."""
    out: dict[str, list[str]] = {}
    for spec in specs:
        name, sep, members = spec.partition("=")
        if not sep or not members:
            raise UsageError(f"--group {spec!r}: use NAME=host/axis,host/axis")
        parse_selector("@" + name)
        out[name] = [m.strip() for m in members.split(",") if m.strip()]
        for m in out[name]:
            sel = parse_selector(m)
            if sel.group is not None or sel.has_wildcards:
                raise UsageError(f"--group {name}: member {m!r} must be a concrete host/axis")
    return out


def check_syntax(args: argparse.Namespace) -> None:
    """Every selector parses before anything connects (exit 2 otherwise)."""
    for s in getattr(args, "selectors", None) or []:
        parse_selector(s)
    for stage in stages_of(getattr(args, "stage", None) or []):
        for s in stage:
            parse_selector(s)
    if getattr(args, "stage", None) and getattr(args, "selectors", None):
        raise UsageError("give either selectors or --stage, not both")
    local_groups(args.group)


def security_of(args: argparse.Namespace) -> tuple[str | None, str | None]:
    """``--pki``/``--identity``, else ``$DRIVES_PKI``/``$DRIVES_IDENTITY``; both or neither."""
    pki = args.pki or os.environ.get("DRIVES_PKI") or None
    identity = args.identity or os.environ.get("DRIVES_IDENTITY") or None
    if (pki is None) != (identity is None):
        raise UsageError("--pki and --identity go together (or $DRIVES_PKI and $DRIVES_IDENTITY): "
                         f"got pki {pki!r}, identity {identity!r}")
    return pki, identity


def identity_text(args: argparse.Namespace) -> str:
    """Who drivectl acted as, for its reports."""
    pki, identity = security_of(args)
    return f"{identity} (tls, {pki})" if identity else "anonymous (insecure)"


@contextmanager
def open_fleet(args: argparse.Namespace) -> Iterator[Fleet]:
    """The Fleet of the global options, with at least one agent alive (else NoAgentError, exit 3)."""
    connect = args.connect or list(DEFAULT_CONNECT)
    fleet_file = args.fleet or os.environ.get(FLEET_ENV) or None
    expected = load_fleet(fleet_file) if fleet_file else None  # FleetFileError: exit 2
    pki, identity = security_of(args)
    with Fleet(connect=connect, name=args.name, mode=args.mode, groups=local_groups(args.group),
               discovery_timeout_s=args.discovery, pki=pki, identity=identity, expected=expected) as fleet:
        if not fleet.hosts():
            # Agents may be reachable an instant after the router: wait for the discovery window.
            fleet.wait_for_agents(1, timeout_s=args.discovery)
        if not fleet.hosts() and expected is None:
            raise NoAgentError(f"no bus agent answered through {', '.join(fleet.connect)} within "
                               f"{args.discovery:g} s; check that the agents run and reach that router")
        if fleet.hosts() or args.verb in ("status", "watch"):
            yield fleet  # with an expected fleet, status shows every host offline
        else:
            raise NoAgentError(f"no bus agent answered through {', '.join(fleet.connect)} within "
                               f"{args.discovery:g} s (expected: {', '.join(expected.hosts) if expected else '-'})")


def known_targets(fleet: Fleet, selectors: Sequence[str]) -> list[str]:
    """``selectors`` when each names a live or expected drive; else exit 2 with hints (and a
    word about the shell when a selector is the name of a file here: an unquoted ``*``)."""
    try:
        fleet.check_known(*selectors)
    except SelectorError as exc:
        files = [s for s in selectors if os.path.exists(s)]
        if files:
            raise SelectorError(f"{exc}; {', '.join(files[:3])} {'is a file' if len(files) == 1 else 'are files'} "
                                "here: did the shell expand an unquoted '**' or '*'? Quote selectors: '**'") from None
        raise
    return list(selectors)


def emit_report(args: argparse.Namespace, console: Console, report: Report | CommandResult) -> int:
    """Print a result (table or JSON) and return its exit code."""
    if isinstance(report, Report) and not report.final and not report.ok and not args.json:
        console.print(f"{report.action} FAILED: {report.reason} (as {identity_text(args)})", style="bold red")
        return EXIT_FAILED
    if args.json:
        print(json.dumps({**report.to_dict(), "identity": security_of(args)[1]}, indent=1))
    else:
        from ..watch import print_report
        print_report(console, report)
        if not report.ok:
            console.print(f"as {identity_text(args)}", style="dim")
    return EXIT_OK if report.ok else EXIT_FAILED
