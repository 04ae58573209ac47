"""``drivectl``: thin verbs over the supervisor API.

    drivectl [--connect EP]... [--json] [--timeout S] VERB [SELECTOR]...

Verbs: status, watch, enable, disable, shutdown, switch-on, quick-stop, halt [--off],
fault-reset, mode MODE, nmt COMMAND [--host H] [--slave S]. Selectors: ``h1/x``, ``h1/*``,
``h1``, ``*/x``, ``h*/axis?``, ``**``, ``@group``. enable/disable/shutdown take ``--stage`` (a
comma-separated selector list, repeated, in enable order; shutdown goes last stage first).

Exit codes: 0 every addressed drive reached its goal; 1 some did not (listed); 2 bad selectors
or arguments (reported before anything is sent); 3 no agent reachable.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import Sequence

from rich.console import Console

from schemas.messages import MODES, NMT_COMMANDS

from .fleet import DEFAULT_CONNECT, Fleet, NoAgentError
from .recordings import TRIGGER_WORDS, RecordingError, fetch_recording, write_csv
from .results import CommandResult, Report, single
from .selectors import SelectorError, parse_selector

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_NO_AGENT = 0, 1, 2, 3

#: Mode names accepted by ``drivectl mode`` (0x6060 values, CiA 402 abbreviations).
MODE_NAMES = {"pp": 1, "pv": 3, "pt": 4, "hm": 6, "ip": 7, "csp": 8, "csv": 9, "cst": 10}


class UsageError(Exception):
    """Bad arguments found after argparse (exit 2, nothing sent)."""


def _mode(text: str) -> int:
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


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0 < v <= 3600:
        raise argparse.ArgumentTypeError(f"{text!r} must be in (0, 3600] seconds")
    return v


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drivectl", description="Supervise CiA 402 drives through their Zenoh bus agents.",
                                epilog="exit codes: 0 all reached the goal, 1 some did not, 2 bad arguments, 3 no agent")
    p.add_argument("--connect", "-c", action="append", metavar="EP",
                   help=f"zenoh endpoint (repeat for fail-over; default {DEFAULT_CONNECT[0]})")
    p.add_argument("--mode", choices=("client", "peer"), default="client", help="zenoh session mode")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--timeout", type=_positive, default=5.0, metavar="S", help="per-command deadline (default 5 s)")
    p.add_argument("--discovery", type=_positive, default=1.0, metavar="S",
                   help="how long to wait for agents to answer at start (default 1 s)")
    p.add_argument("--name", help="supervisor name (default sup-<host>-<pid>)")
    p.add_argument("--group", action="append", default=[], metavar="NAME=H/A,H/A",
                   help="define a local group usable as @NAME")
    p.add_argument("-v", "--verbose", action="count", default=0)
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")

    def verb(name: str, help_: str, selectors: bool = True, stages: bool = False) -> argparse.ArgumentParser:
        sp = sub.add_parser(name, help=help_)
        if selectors:
            sp.add_argument("selectors", nargs="*", metavar="SELECTOR", help="drives (default: ** where safe)")
        if stages:
            sp.add_argument("--stage", action="append", default=[], metavar="SEL,SEL",
                            help="a stage of selectors, repeated in enable order")
        return sp

    verb("status", "table (or --json) of every drive")
    w = verb("watch", "live table, redrawn on every status change")
    w.add_argument("--duration", type=_positive, default=None, metavar="S", help="stop after S seconds")
    verb("enable", "two-phase enable: all to Switched on, then all to Operation enabled", stages=True)
    verb("disable", "disable operation, shutdown, disable voltage (-> Switch on disabled)", stages=True)
    verb("shutdown", "CiA 402 shutdown (-> Ready to switch on)", stages=True)
    verb("switch-on", "switch on (-> Switched on)")
    verb("quick-stop", "quick stop (default: every drive)")
    h = verb("halt", "set halt (controlword bit 8)")
    h.add_argument("--off", action="store_true", help="clear halt instead")
    verb("fault-reset", "fault reset (bit 7 edge, made by the agent)")
    m = sub.add_parser("mode", help="set modes of operation 0x6060 (waits for 0x6061)")
    m.add_argument("mode_value", type=_mode, metavar="MODE", help="pp, pv, pt, hm, ip, csp, csv, cst or a number")
    m.add_argument("selectors", nargs="*", metavar="SELECTOR")
    n = sub.add_parser("nmt", help="network management on agents' segments")
    n.add_argument("command", choices=NMT_COMMANDS)
    n.add_argument("--host", action="append", default=[], help="agent host (pattern; default every agent)")
    n.add_argument("--slave", help="only this slave: an axis name or a position (with one --host)")
    r = sub.add_parser("record", help="fetch a flight recording of an agent into a CSV file")
    r.add_argument("host", help="agent host name")
    what = r.add_mutually_exclusive_group()
    what.add_argument("--last", type=_positive, metavar="S", help="the last S seconds (default 10)")
    what.add_argument("--trigger", choices=tuple(TRIGGER_WORDS), help="the latest window frozen by a fault, "
                      "reflex, lost slave or request (last: any), or freeze one now")
    r.add_argument("--out", required=True, metavar="FILE.csv")
    pl = sub.add_parser("plot", help="draw a flight recording CSV as a PNG (states, statusword bits, motion)")
    pl.add_argument("file", metavar="FILE.csv")
    pl.add_argument("--out", required=True, metavar="FILE.png")
    pl.add_argument("--axis", action="append", default=[], help="only this axis (repeat; default the first 8)")
    return p


def _groups(specs: Sequence[str]) -> dict[str, list[str]]:
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


def _stages(specs: Sequence[str]) -> list[list[str]]:
    stages = []
    for spec in specs:
        stage = [s.strip() for s in spec.split(",") if s.strip()]
        if not stage:
            raise UsageError(f"--stage {spec!r} is empty")
        stages.append(stage)
    return stages


def _check_syntax(args: argparse.Namespace) -> None:
    """Every selector parses before anything connects (exit 2 otherwise)."""
    for s in getattr(args, "selectors", None) or []:
        parse_selector(s)
    for stage in _stages(getattr(args, "stage", None) or []):
        for s in stage:
            parse_selector(s)
    if getattr(args, "stage", None) and getattr(args, "selectors", None):
        raise UsageError("give either selectors or --stage, not both")
    for h in getattr(args, "host", None) or []:
        if "/" in h:
            raise UsageError(f"--host {h!r} is a host, not host/axis")
        parse_selector(h)


_REQUIRED = {"enable", "disable", "shutdown", "switch-on", "halt", "mode", "fault-reset"}


def _targets(args: argparse.Namespace) -> list[str]:
    sels = list(getattr(args, "selectors", None) or [])
    if not sels and args.verb in _REQUIRED and not getattr(args, "stage", None):
        # Commands that move drives need an explicit target; '**' is there for "all".
        raise UsageError(f"{args.verb}: name the drives (a selector, or '**' for every drive)")
    return sels or ["**"]


def run(args: argparse.Namespace, console: Console) -> int:
    _check_syntax(args)
    groups = _groups(args.group)
    with Fleet(connect=args.connect or DEFAULT_CONNECT, name=args.name, mode=args.mode, groups=groups,
               discovery_timeout_s=args.discovery) as fleet:
        if not fleet.hosts():
            # Agents may be reachable an instant after the router: wait for the discovery window.
            fleet.wait_for_agents(1, timeout_s=args.discovery)
        if not fleet.hosts():
            raise NoAgentError(f"no bus agent answered through {', '.join(fleet.connect)}")
        verb = args.verb
        if verb == "record":
            return _record(fleet, args, console)
        if verb == "status":
            return _status(fleet, args, console)
        if verb == "watch":
            if args.selectors:
                fleet.select(*args.selectors)  # bad or empty selectors: exit 2 before drawing
            from .watch import run_watch
            return run_watch(fleet, args.selectors, console=console, duration_s=args.duration)
        t = args.timeout
        report: Report | CommandResult
        if verb == "enable":
            stages = _stages(args.stage)
            report = fleet.enable(*_targets(args), timeout_s=t, stages=stages or None)
        elif verb in ("disable", "shutdown"):
            op = verb
            if args.stage:
                report = fleet.shutdown(_stages(args.stage), op=op, timeout_s=t)
            else:
                report = single(op, fleet.command(op, fleet.select(*_targets(args)), timeout_s=t))
        elif verb == "nmt":
            report = single("nmt", fleet.nmt(args.command, args.host or ["*"], args.slave, timeout_s=t))
        else:
            sel = fleet.select(*_targets(args))
            if verb == "switch-on":
                res = fleet.command("switch_on", sel, timeout_s=t)
            elif verb == "quick-stop":
                res = fleet.command("quick_stop", sel, timeout_s=t)
            elif verb == "halt":
                res = fleet.command("halt", sel, {"on": not args.off}, timeout_s=t)
            elif verb == "fault-reset":
                res = fleet.command("fault_reset", sel, timeout_s=t)
            elif verb == "mode":
                res = fleet.command("set_mode", sel, {"mode": args.mode_value}, timeout_s=t)
            else:  # pragma: no cover - argparse only offers the verbs above
                raise UsageError(f"unknown verb {verb}")
            report = single(verb, res)
        if isinstance(report, Report) and not report.final and not report.ok and args.json is False:
            console.print(f"{report.action} FAILED: {report.reason}", style="bold red")
            return EXIT_FAILED
        if args.json:
            print(json.dumps(report.to_dict(), indent=1))
        else:
            from .watch import print_report
            print_report(console, report)
        return EXIT_OK if report.ok else EXIT_FAILED


def _record(fleet: Fleet, args: argparse.Namespace, console: Console) -> int:
    what = TRIGGER_WORDS[args.trigger] if args.trigger else "last"
    try:
        rec = fetch_recording(fleet.session, args.host, what, args.last or 10.0, timeout_s=max(args.timeout, 20.0))
    except RecordingError as exc:
        console.print(f"record {args.host} FAILED: {exc}", style="bold red", markup=False, highlight=False)
        return EXIT_FAILED
    rows = write_csv(rec, args.out)
    summary = {"host": rec.host, "reason": rec.reason, "axis": rec.axis, "detail": rec.detail,
               "trigger_cycle": rec.trigger_cycle, "first_cycle": rec.first_cycle, "cycles": rec.n_cycles,
               "seconds": rec.n_cycles * rec.cycle_us / 1e6, "axes": rec.axes, "rows": rows, "out": args.out}
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        console.print(f"{rec.host}: {rec.n_cycles} cycles ({summary['seconds']:g} s) of {len(rec.axes)} drive(s), "
                      f"{rec.reason}{' ' + rec.axis if rec.axis else ''}{': ' + rec.detail if rec.detail else ''}"
                      f" -> {args.out}", markup=False, highlight=False)
    return EXIT_OK


def _plot(args: argparse.Namespace, console: Console) -> int:
    from .plot import plot_file
    try:
        drawn = plot_file(args.file, args.out, args.axis)
    except (OSError, ValueError) as exc:
        raise UsageError(f"plot {args.file}: {exc}") from None
    console.print(f"{args.file}: {', '.join(drawn)} -> {args.out}", markup=False, highlight=False)
    return EXIT_OK


def _status(fleet: Fleet, args: argparse.Namespace, console: Console) -> int:
    from .watch import status_rows, status_table
    if args.selectors:
        fleet.select(*args.selectors)
    rows = status_rows(fleet, args.selectors)
    if args.json:
        agents = {}
        for h, a in sorted(fleet.agents().items()):
            st = a.status
            agents[h] = {"alive": a.alive, "state": st.state if st else None,
                         "backend": st.backend if st else None, "axes": list(st.axes) if st else None,
                         "groups": dict(st.groups) if st else {}, "leases": dict(st.leases) if st else {},
                         "cycle_us": st.cycle_us if st else None, "overruns": st.overruns if st else None}
        print(json.dumps({"agents": agents, "drives": rows, "supervisors": fleet.supervisors()}, indent=1))
    else:
        console.print(status_table(rows, f"{len(fleet.hosts())} agent(s), {len(rows)} drive(s)"))
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # exits 2 on bad arguments
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if args.verbose == 0:
        logging.getLogger("supervisor").setLevel(logging.ERROR)  # the report says it all
    console = Console(stderr=False)
    err = Console(stderr=True, soft_wrap=True)
    try:
        if args.verb == "plot":  # a file to a file: no agent involved
            return _plot(args, console)
        return run(args, console)
    except (SelectorError, UsageError, ValueError) as exc:
        err.print(f"drivectl: {exc}", style="bold red", markup=False, highlight=False)
        return EXIT_USAGE
    except NoAgentError as exc:
        err.print(f"drivectl: no agent reachable: {exc}", style="bold red", markup=False, highlight=False)
        return EXIT_NO_AGENT
    except KeyboardInterrupt:
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
