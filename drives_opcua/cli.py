"""``drives-opcua``: the fleet as an OPC UA server (plant SCADA, UaExpert, MES).

    drives-opcua --connect EP --endpoint opc.tcp://HOST:PORT [--fleet FILE]
                 [--pki DIR [--identity NAME]] [--accept-unknown-clients]

One Zenoh session (a ``supervisor.Fleet``) feeds the address space ``Objects/Drives/<host>/<axis>``
(namespace ``urn:zenoh-drives``) and sends the drive methods' commands. Without ``--pki``: an
insecure fleet, SecurityPolicy None and anonymous read-only sessions (nobody can log in, so no
method can be called). With ``--pki DIR``: the Fleet talks TLS as ``--identity`` (default
``opcua``; issue it with ``drives-pki issue DIR opcua --role operator --role maintenance --opcua``),
whose certificate is also the server's; endpoints offer None (anonymous read-only, user tokens
encrypted with the server certificate) and Basic256Sha256 SignAndEncrypt; users log in with
a password (``drives-pki user``) or a user certificate of the CA; client application
certificates must be issued by the CA unless ``--accept-unknown-clients``.

Prints ``drives-opcua ready opc.tcp://...`` once listening. Exit codes: 0 stopped by a signal,
2 bad arguments or PKI files, 3 the fleet unreachable.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
from typing import Sequence
from urllib.parse import urlparse

from bus_agent.security.pki import PkiError
from bus_agent.security.users import UsersError, load as load_users
from supervisor.fleet import Fleet, FleetError
from supervisor.fleetfile import FleetFileError, load as load_fleet
from supervisor.session import DEFAULT_CONNECT

from .server import DrivesServer, server_files

log = logging.getLogger("drives_opcua")
DEFAULT_IDENTITY = "opcua"
DEFAULT_ENDPOINT = "opc.tcp://127.0.0.1:4840"


def _endpoint(text: str) -> str:
    url = urlparse(text)
    if url.scheme != "opc.tcp" or not url.hostname or not url.port:
        raise argparse.ArgumentTypeError(f"--endpoint {text!r}: use opc.tcp://HOST:PORT, e.g. {DEFAULT_ENDPOINT}")
    return text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drives-opcua", description="OPC UA server of a fleet of bus agents: "
                                "Objects/Drives/<host>/<axis>, drive methods for logged-in users.")
    p.add_argument("--connect", "-c", action="append", metavar="EP",
                   help=f"zenoh endpoint (repeat; default {DEFAULT_CONNECT[0]})")
    p.add_argument("--endpoint", type=_endpoint, default=DEFAULT_ENDPOINT, metavar="opc.tcp://HOST:PORT",
                   help=f"where OPC UA clients connect (default {DEFAULT_ENDPOINT})")
    p.add_argument("--fleet", metavar="FILE", help="expected fleet (TOML): absent hosts are shown offline")
    p.add_argument("--pki", metavar="DIR", help="drives-pki directory: TLS to Zenoh, the server certificate, "
                   "users (users.toml, principals.toml)")
    p.add_argument("--identity", metavar="NAME", help=f"principal of this server in DIR (default {DEFAULT_IDENTITY})")
    p.add_argument("--accept-unknown-clients", action="store_true",
                   help="accept client application certificates not issued by the CA (test beds only)")
    p.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    for name in ("drives_opcua", "supervisor"):
        logging.getLogger(name).setLevel(args.log_level)
    if args.identity and not args.pki:
        print("drives-opcua: --identity needs --pki DIR", file=sys.stderr)
        return 2
    identity = (args.identity or DEFAULT_IDENTITY) if args.pki else None
    try:
        expected = load_fleet(args.fleet) if args.fleet else None
    except (FleetFileError, OSError) as exc:
        print(f"drives-opcua: --fleet {args.fleet}: {exc}", file=sys.stderr)
        return 2
    try:
        if args.pki and identity:
            server_files(args.pki, identity)  # before the fleet: a bad file is exit 2, not a late failure
            load_users(args.pki)
    except (PkiError, UsersError, OSError) as exc:
        print(f"drives-opcua: {exc}", file=sys.stderr)
        return 2
    try:
        fleet = Fleet(connect=args.connect or DEFAULT_CONNECT, expected=expected, pki=args.pki,
                      identity=identity, name=identity).open()
    except (FleetError, ValueError) as exc:
        print(f"drives-opcua: {exc}", file=sys.stderr)
        return 3
    try:
        server = DrivesServer(fleet, args.endpoint, pki=args.pki, identity=identity,
                              accept_unknown_clients=args.accept_unknown_clients)
        return asyncio.run(_serve(server))
    except (PkiError, UsersError, OSError) as exc:
        print(f"drives-opcua: {exc}", file=sys.stderr)
        return 2
    finally:
        fleet.close()


async def _serve(server: DrivesServer) -> int:
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    assert task is not None
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, task.cancel)

    def ready() -> None:
        mode = f"secure, as {server.identity}" if server.identity else "insecure, anonymous read-only"
        print(f"drives-opcua ready {server.endpoint} ({mode})", flush=True)

    try:
        await server.serve(ready)
    except asyncio.CancelledError:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
