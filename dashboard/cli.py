"""``drives-dashboard``: one Zenoh session (a ``supervisor.Fleet``) serving the fleet on HTTP.

    drives-dashboard [--connect EP]... [--fleet FILE] [--http HOST:PORT] [--commands]
                     [--pki DIR --identity NAME]

Read-only unless ``--commands``, which needs an identity (``--pki DIR --identity NAME``): commands
then go out under that principal (mutual TLS; the router's ACL and the agents' audit name it),
and the page offers command buttons, each confirmed before it is sent. ``--http`` defaults to loopback. Prints ``drives-dashboard ready http://...``.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any, Sequence

import zenoh

from schemas import keys
from schemas.messages import Event, SchemaError, decode
from supervisor.fleet import Fleet, FleetError
from supervisor.session import DEFAULT_CONNECT
from supervisor.fleetfile import FleetFileError, load as load_fleet
from supervisor.recordings import fetch_recording

from .app import build_app
from .view import FleetView

log = logging.getLogger(__name__)
DEFAULT_HTTP = "127.0.0.1:8402"
#: After a stop request, responses still open this long are cancelled (a backstop: live streams
#: end on their own at the stop, see ``build_app(stopping=...)``).
GRACEFUL_SHUTDOWN_S = 1  # whole seconds (uvicorn's type)
#: How often host-name conflicts are looked up (``Fleet.conflicts()``).
CONFLICT_POLL_S = 0.5


def _http(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 < int(port) < 65536 or not host:
        raise argparse.ArgumentTypeError(f"--http {text!r}: use HOST:PORT, e.g. {DEFAULT_HTTP}")
    return host.strip("[]"), int(port)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drives-dashboard", description="Web dashboard and Prometheus metrics of a "
                                "fleet of bus agents (read-only unless --commands).")
    p.add_argument("--connect", "-c", action="append", metavar="EP",
                   help=f"zenoh endpoint (repeat; default {DEFAULT_CONNECT[0]})")
    p.add_argument("--mode", choices=("client", "peer"), default="client")
    p.add_argument("--fleet", metavar="FILE", help="expected fleet (TOML): absent hosts are shown offline")
    p.add_argument("--http", type=_http, default=_http(DEFAULT_HTTP), metavar="HOST:PORT",
                   help=f"where to serve (default {DEFAULT_HTTP}, loopback)")
    p.add_argument("--commands", action="store_true", help="allow commands from the page, under the dashboard's "
                   "identity (needs --pki and --identity)")
    p.add_argument("--pki", metavar="DIR", help="drives-pki directory (with --identity: a viewer principal, an "
                   "operator's for --commands)")
    p.add_argument("--identity", metavar="NAME")
    p.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    return p


def attach(fleet: Fleet, view: FleetView) -> Any:
    """Feed ``view`` from ``fleet``'s listeners and a drive event subscriber; returns the subscriber."""
    fleet.on("status", view.on_status)
    fleet.on("agent", view.on_agent)
    fleet.on("arrival", lambda h: view.on_alive(h, True))
    fleet.on("departure", lambda h: view.on_alive(h, False))
    for h in fleet.hosts():
        view.on_alive(h, True)
    for info in fleet.agents().values():
        if info.status is not None:
            view.on_agent(info.status)
    for st in fleet.drives().values():
        view.on_status(st)

    def on_event(sample: zenoh.Sample) -> None:
        try:
            view.on_event(decode(sample.payload.to_bytes(), Event))
        except SchemaError as exc:
            log.warning("dashboard: bad event on %s: %s", sample.key_expr, exc)

    return fleet.session.declare_subscriber(keys.ALL_DRIVE_EVENTS, on_event)


def poll_conflicts(fleet: Fleet, view: FleetView, done: threading.Event) -> None:
    """Feed ``view`` the fleet's host-name conflicts until ``done`` (they age out with time, so
    they are polled, not pushed)."""
    while not done.wait(CONFLICT_POLL_S):
        view.on_conflicts(fleet.conflicts())


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.commands and not args.identity:
        parser.error("--commands needs an identity (--pki DIR --identity NAME): a command names who sent it")
    logging.basicConfig(level=args.log_level, stream=sys.stderr, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        expected = load_fleet(args.fleet) if args.fleet else None
    except (FleetFileError, OSError) as exc:
        print(f"drives-dashboard: --fleet {args.fleet}: {exc}", file=sys.stderr)
        return 2
    import uvicorn

    view = FleetView({h: list(e.axes) for h, e in expected.hosts.items()} if expected else None)
    try:
        fleet = Fleet(connect=args.connect or DEFAULT_CONNECT, mode=args.mode, expected=expected,
                      pki=args.pki, identity=args.identity).open()
    except (FleetError, ValueError) as exc:
        print(f"drives-dashboard: {exc}", file=sys.stderr)
        return 3
    sub = attach(fleet, view)
    done = threading.Event()
    threading.Thread(target=poll_conflicts, args=(fleet, view, done), name="dashboard-conflicts", daemon=True).start()

    def run_command(op: str, selector: str, cmd_args: dict) -> dict:
        return fleet.command(op, fleet.select(selector), cmd_args or None).to_dict()

    server: uvicorn.Server | None = None
    app = build_app(view, fetch_recording=lambda h, w, s: fetch_recording(fleet.session, h, w, s),
                    run_command=run_command if args.commands else None, identity=args.identity or "",
                    stopping=lambda: server is not None and server.should_exit)
    host, port = args.http
    server = uvicorn.Server(uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False,
                                           lifespan="off", timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S))
    started = threading.Event()

    def announce() -> None:
        while not server.started and not server.should_exit:
            started.wait(0.05)
        if server.started:
            print(f"drives-dashboard ready http://{host}:{port}/ ({'commands enabled' if args.commands else 'read-only'})",
                  flush=True)

    threading.Thread(target=announce, daemon=True).start()
    # uvicorn captures SIGTERM/SIGINT while it runs (a plain flag, no lock) and raises them again
    # after its shutdown: this handler takes a SIGTERM before (and that re-raise) as a stop.
    signal.signal(signal.SIGTERM, lambda *_: setattr(server, "should_exit", True))
    try:
        server.run()
    finally:
        done.set()
        sub.undeclare()
        fleet.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
