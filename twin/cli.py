"""``drives-twin``: a simulated twin of a fleet file in one command.

    drives-twin --fleet fleet.toml                        # router on a free loopback port
    drives-twin --fleet fleet.toml --listen tcp/127.0.0.1:7447 --backend ecat   # root
    drives-twin --fleet fleet.toml --pki DIR [--identity alice]   # mTLS + ACL with DIR's CA
    drives-twin --cleanup                                 # what twins killed with SIGKILL left

Starts a router and one bus agent per host of the fleet file with exactly its host, axis and
group names (``twin.Twin``), waits until every expected drive answers and prints one line::

    drives-twin ready endpoint=tcp/127.0.0.1:7447 backend=sim hosts=c1,c2 drives=3 ready_s=1.72

Then it reads commands, one per line, on standard input (a pipe, a terminal), answering each
with one line ``ok <detail>`` or ``error <reason>``::

    fault REF [CODE]          drive REF = host/axis faults (0x603F CODE, default 0x5530)
    unplug REF | plug REF     the drive's slave stops answering / is back, power-cycled
    sim REF ACTION [K=V ...]  any simulator action (wkc_fault on=true, drop_frames count=10, ...)
    cut HOST | restore HOST   pull / plug HOST's network cable (noticed after the 3 s link lease)
    kill-agent HOST | restart-agent HOST | kill-router | restart-router
    status                    every drive's state
    stop                      stop the twin (like SIGTERM)

SIGINT or SIGTERM stops everything cleanly (agents' ordered shutdown first; no process, veth or
namespace left). If a child exits unasked, the twin says which on stderr, stops everything and
exits 1. SIGKILL cannot be handled: the children die with the twin all the same (parent-death
signal), and the next start or ``drives-twin --cleanup`` removes the work directory and the ecat
backend's namespaces it left. Exit codes: 0 stopped on request; 1 a child died; 2 bad command
line or fleet file (``--cleanup``: something could not be removed); 3 start-up failed (a child
did not start or a drive did not answer in time).
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import sys
import threading
from typing import Callable, Sequence

from bus_agent.stop_signals import StopSignals
from supervisor.fleetfile import FleetFileError

from .plan import BACKENDS, PlanError
from .stale import clean_stale
from .twin import READY_TIMEOUT_S, Twin, TwinError

EXIT_OK, EXIT_CHILD_DIED, EXIT_USAGE, EXIT_STARTUP = 0, 1, 2, 3


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drives-twin", description="Run a simulated twin of a fleet file: a Zenoh "
                                "router and one bus agent per host, with fault injection on standard input.")
    p.add_argument("--fleet", metavar="TOML", help="the fleet file ([hosts.NAME] axes = [...], [groups])")
    p.add_argument("--cleanup", action="store_true",
                   help="only remove what twins killed with SIGKILL left (work directories; namespaces and "
                        "veth pairs of the ecat backend, as root) and exit; every start does this too")
    p.add_argument("--listen", metavar="EP", help="the router's endpoint for supervisors (default: a free loopback port)")
    p.add_argument("--backend", choices=BACKENDS, default="sim",
                   help="sim: in-process drive models (no root); ecat: pysoem against ecat-sim per host namespace (root)")
    p.add_argument("--ready-timeout", type=float, default=READY_TIMEOUT_S, metavar="S",
                   help=f"how long to wait for every drive to answer (default {READY_TIMEOUT_S:.0f})")
    p.add_argument("--pki", metavar="DIR", help="a drives-pki directory (with its CA key): mutual TLS on every "
                   "link and the router's ACL; the twin issues its own certificates into a copy of DIR")
    p.add_argument("--identity", metavar="NAME", help="with --pki: the principal of DIR the twin's own supervisor "
                   "uses (default: twin-operator, issued with role operator)")
    p.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    return p


def _value(text: str) -> object:
    """A command argument: JSON where it parses (numbers, true/false), else the text; 0x.. hex."""
    if text.lower().startswith("0x"):
        return int(text, 16)
    try:
        return json.loads(text)
    except ValueError:
        return text


def run_command(twin: Twin, line: str) -> str:
    """Perform one command line on ``twin``; returns its detail. Raises ValueError/TwinError/PlanError."""
    words = shlex.split(line)
    if not words:
        return ""
    verb, args = words[0], words[1:]

    def need(n: int, usage: str) -> None:
        if len(args) != n:
            raise ValueError(f"usage: {usage}")

    if verb == "fault":
        if len(args) not in (1, 2):
            raise ValueError("usage: fault HOST/AXIS [CODE]")
        return twin.fault(args[0], *([int(str(_value(args[1])))] if len(args) == 2 else []))
    if verb in ("unplug", "plug"):
        need(1, f"{verb} HOST/AXIS")
        return twin.unplug(args[0]) if verb == "unplug" else twin.plug(args[0])
    if verb == "sim":
        if len(args) < 2:
            raise ValueError("usage: sim HOST/AXIS ACTION [KEY=VALUE ...]")
        kv = {}
        for a in args[2:]:
            k, sep, v = a.partition("=")
            if not sep:
                raise ValueError(f"argument {a!r} is not KEY=VALUE")
            kv[k] = _value(v)
        return twin.inject(args[0], args[1], **kv)
    if verb in ("cut", "restore", "kill-agent", "restart-agent"):
        need(1, f"{verb} HOST")
        actions: dict[str, Callable[[str], None]] = {"cut": twin.cut, "restore": twin.restore,
                                                     "kill-agent": twin.kill_agent,
                                                     "restart-agent": twin.restart_agent}
        actions[verb](args[0])
        return f"{verb} {args[0]}"
    if verb in ("kill-router", "restart-router"):
        need(0, verb)
        if verb == "kill-router":
            twin.kill_router()
        else:
            twin.restart_router()
        return verb
    if verb == "status":
        need(0, "status")
        return " ".join(f"{r}={st.state}{'(lost)' if st.lost else ''}" for r, st in sorted(twin.fleet.drives().items()))
    raise ValueError(f"unknown command {verb!r} (fault, unplug, plug, sim, cut, restore, kill-agent, "
                     "restart-agent, kill-router, restart-router, status, stop)")


def _serve_stdin(twin: Twin, stop: StopSignals) -> None:
    for line in sys.stdin:
        if stop.stopped:
            return
        if line.strip() == "stop":
            print("ok stopping", flush=True)
            stop.request()
            return
        try:
            detail = run_command(twin, line)
        except (ValueError, TwinError, PlanError) as exc:
            print(f"error {exc}", flush=True)
            continue
        if detail:
            print(f"ok {detail}", flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.cleanup:
        done = clean_stale()
        print("\n".join(done) or "drives-twin cleanup: nothing left by a dead twin", flush=True)
        return EXIT_USAGE if any(line.startswith(("kept", "could not")) for line in done) else EXIT_OK
    if not args.fleet:
        parser.error("--fleet is required (or --cleanup)")
    died: list[str] = []
    # Handlers first: a signal during start-up still stops what was started.
    stop = StopSignals()

    def on_exit(msg: str) -> None:
        died.append(msg)
        stop.request()

    try:
        twin = Twin(args.fleet, backend=args.backend, listen=args.listen, ready_timeout_s=args.ready_timeout,
                    on_unexpected_exit=on_exit, log_level=args.log_level, pki=args.pki, identity=args.identity)
    except (FleetFileError, PlanError) as exc:
        print(f"drives-twin: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        twin.start()
    except (TwinError, PlanError, OSError) as exc:
        print(f"drives-twin: {exc}", file=sys.stderr)
        return EXIT_USAGE if isinstance(exc, PlanError) else EXIT_STARTUP
    try:
        refs = twin.expected.refs()
        print(f"drives-twin ready endpoint={twin.endpoint} backend={twin.backend} "
              f"hosts={','.join(twin.expected.hosts)} drives={len(refs)} ready_s={twin.ready_s:.2f}"
              f"{f' identity={twin.fleet.identity}' if twin.pki else ''}", flush=True)
        threading.Thread(target=_serve_stdin, args=(twin, stop), name="twin-stdin", daemon=True).start()
        stop.wait()
    finally:
        twin.stop()
    if died:
        print(f"drives-twin: stopped because {died[0]}", file=sys.stderr)
        return EXIT_CHILD_DIED
    print("drives-twin stopped", flush=True)
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
