"""Secure by default: which listen endpoints other machines can reach (pure).

An agent or router that listens only on loopback (``127.0.0.0/8``, ``::1``, ``localhost``) is
reachable from this machine alone, as in ``make demo``; any other address (``0.0.0.0``, a
plant-network address, a host name) is exposed and needs ``--pki`` or an explicit ``--insecure``.
"""

from __future__ import annotations

import ipaddress
from typing import Iterable

LOOPBACK_NAMES = ("localhost",)


def _host_of(endpoint: str) -> str:
    _, _, addr = endpoint.partition("/")
    addr = addr.split("#", 1)[0].split("?", 1)[0]
    host, colon, _port = addr.rpartition(":")
    host = host if colon else addr
    return host.strip("[]")


def is_loopback(endpoint: str) -> bool:
    """True if ``endpoint`` (``tcp/127.0.0.1:7447``, ``tls/[::1]:7447``, ``unixsock-stream/...``)
    can only be reached from this machine."""
    proto = endpoint.partition("/")[0]
    if proto.startswith("unixsock"):
        return True
    host = _host_of(endpoint)
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def exposed_endpoints(listen: Iterable[str]) -> list[str]:
    """The listen endpoints that other machines can reach. Malformed ones (no ``proto/``) are
    left to the endpoint check, whose error says what is wrong with them."""
    return [ep for ep in listen if "/" in ep.strip("/") and not is_loopback(ep)]


def refusal(who: str, exposed: Iterable[str], how: str) -> str:
    """The message of a program that refuses to listen unsecured on ``exposed``."""
    return (f"{who}: listening on {', '.join(exposed)} exposes it to the network without authentication: "
            f"secure it with --pki DIR --identity NAME ({how}), or give --insecure to accept that")
