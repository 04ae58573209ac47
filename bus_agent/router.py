"""``drives-router``: a standalone Zenoh router process (the PyPI wheel ships no ``zenohd``).

    drives-router                                             # listens on tcp/127.0.0.1:7447
    drives-router --config deploy/router.json5                # TLS, ACL, ... from the file
    drives-router --listen tcp/10.213.7.1:7447 --connect tcp/10.213.7.2:7447 --pki /etc/zenoh-drives/pki --identity r1
    drives-router --rt-priority 9                             # beside a real-time bus agent (see below)

One router per host: the host's bus agents and supervisors connect to it, and routers connect
to each other with explicit ``--connect`` endpoints (see docs/deployment.md). The session is
built by :func:`bus_agent.gateway.zenoh_config.make_zenoh_config` (multicast scouting off, 3 s link
lease, background reconnection). ``--listen`` / ``--connect`` replace the file's endpoint
lists when given. Once the session is open it prints one line,
``drives-router ready zid=<zid> listen=<eps> connect=<eps>``; SIGTERM or SIGINT closes the
session and exits 0.

``--rt-priority N`` puts the whole router (every zenoh runtime thread: they inherit it) under
SCHED_FIFO ``N``. On a host whose bus agent runs at real-time priority, a fault's status and the
group reflexes pass through this router; under SCHED_OTHER it waited behind the agent's
real-time threads, busy right after a fault, for about a millisecond (docs/benchmarks.md,
bench_reflex). Give it the agent's helper priority: the cycle's priority minus one.

Exit codes: 0 stopped cleanly; 2 bad command line or configuration; 3 the session did not open
(e.g. the listen address is in use or not on this host).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from typing import Sequence

import zenoh

from bus_agent.gateway.zenoh_config import ZenohConfigError, make_zenoh_config
from bus_agent.security.exposure import exposed_endpoints, refusal
from bus_agent.stop_signals import StopSignals

log = logging.getLogger("bus_agent.router")

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
EXIT_OK, EXIT_USAGE, EXIT_STARTUP = 0, 2, 3


class RouterConfigError(ValueError):
    """A router setting that cannot work (unreadable file, malformed endpoint)."""


def _file_endpoints(conf: zenoh.Config, key: str) -> list[str]:
    raw = conf.get_json(key)
    value = json.loads(raw) if raw else []
    return [str(ep) for ep in value or []]


def build_config(config_file: str | None, listen: Sequence[str] = (), connect: Sequence[str] = (), *,
                 pki: str | None = None, identity: str | None = None, insecure: bool = False) -> tuple[
        zenoh.Config, list[str], list[str]]:
    """The router's ``zenoh.Config`` and its effective listen and connect endpoints.

    The file (JSON5, e.g. deploy/router.json5) is loaded first; ``listen``/``connect`` replace
    its lists when non-empty. With neither, the router listens on :data:`DEFAULT_LISTEN`.
    ``pki``/``identity``: mutual TLS and the ACL compiled from the directory's principals.toml.
    Without them, a listen endpoint off loopback is refused unless ``insecure``.
    Raises :class:`RouterConfigError`.
    """
    base = None
    if config_file:
        try:
            base = zenoh.Config.from_file(str(config_file))
        except Exception as exc:  # zenoh raises ZError with the parser's message
            raise RouterConfigError(f"router config {config_file}: {exc}") from None
        if not listen:
            listen = _file_endpoints(base, "listen/endpoints")
        if not connect:
            connect = _file_endpoints(base, "connect/endpoints")
    listen = list(listen) or ([] if config_file else [DEFAULT_LISTEN])
    connect = list(connect)
    if not listen and not connect:
        raise RouterConfigError("a router needs at least one --listen or --connect endpoint")
    exposed = exposed_endpoints(listen)
    if exposed and not pki and not insecure:
        raise RouterConfigError(refusal("drives-router", exposed, "drives-pki init DIR; drives-pki issue DIR NAME "
                                        "--role router --san ADDRESS"))
    try:
        conf = make_zenoh_config("router", listen, connect, base=base, pki=pki, identity=identity)
    except ZenohConfigError as exc:
        raise RouterConfigError(str(exc)) from None
    return conf, listen, connect


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drives-router", description="Run a Zenoh router for the drive network "
                                "(multicast scouting off, 3 s link lease).")
    p.add_argument("--config", metavar="JSON5", help="zenoh router configuration file (see deploy/router.json5)")
    p.add_argument("--listen", action="append", default=[], metavar="EP",
                   help=f"listen endpoint (repeatable; default {DEFAULT_LISTEN} without --config)")
    p.add_argument("--connect", action="append", default=[], metavar="EP",
                   help="another router to connect to (repeatable; retried in the background)")
    p.add_argument("--pki", metavar="DIR", help="drives-pki directory: mutual TLS on every link and the ACL "
                   "compiled from DIR/principals.toml, default deny (see docs/security.md)")
    p.add_argument("--identity", metavar="NAME", help="this router's principal in --pki (role router)")
    p.add_argument("--insecure", action="store_true", help="allow a non-loopback listen endpoint without --pki")
    p.add_argument("--rt-priority", type=int, default=0, metavar="N",
                   help="SCHED_FIFO priority 1..99 of the router's threads (needs root/CAP_SYS_NICE; default 0 = "
                   "off; beside a real-time agent: its cycle priority minus one)")
    p.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    return p


def set_process_fifo(priority: int) -> None:
    """SCHED_FIFO ``priority`` for the calling thread, before zenoh starts its runtime threads
    (they inherit the policy). Raises :class:`RouterConfigError` when refused."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        raise RouterConfigError(f"--rt-priority {priority}: SCHED_FIFO refused ({exc.strerror}; needs root or "
                                "CAP_SYS_NICE)") from None


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if not 0 <= args.rt_priority <= 99:
            raise RouterConfigError(f"--rt-priority {args.rt_priority} must be 0 (off) or a SCHED_FIFO priority 1..99")
        conf, listen, connect = build_config(args.config, args.listen, args.connect, pki=args.pki,
                                             identity=args.identity, insecure=args.insecure)
        if args.rt_priority:
            set_process_fifo(args.rt_priority)
    except RouterConfigError as exc:
        print(f"drives-router: {exc}", file=sys.stderr)
        return EXIT_USAGE
    # Handlers go in before the session opens, so an early SIGTERM still closes it cleanly.
    stop = StopSignals()
    try:
        try:
            session = zenoh.open(conf)
        except Exception as exc:
            print(f"drives-router: cannot open the router session: {exc}", file=sys.stderr)
            return EXIT_STARTUP
        try:
            print(f"drives-router ready zid={session.info.zid()} listen={','.join(listen) or '-'} "
                  f"connect={','.join(connect) or '-'} identity={args.identity + ' (tls, acl)' if args.pki else '- (insecure)'}"
                  f"{f' rt_priority={args.rt_priority}' if args.rt_priority else ''}",
                  flush=True)
            log.info("router up: listen %s connect %s", listen, connect)
            stop.wait()
            log.info("router stopping")
        finally:
            session.close()
    finally:
        stop.restore()
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
