"""The supervisor's Zenoh session settings: the default endpoint, a supervisor's default name,
and the session configuration a :class:`supervisor.fleet.Fleet` opens with."""

from __future__ import annotations

import json
import os
import re
import socket
from typing import Any, Sequence

import zenoh

DEFAULT_CONNECT = ("tcp/127.0.0.1:7447",)


def default_name() -> str:
    """A legal supervisor name from the host name and process id."""
    base = re.sub(r"[^A-Za-z0-9_.\-]", "_", socket.gethostname())[:40] or "host"
    return f"sup-{base.lstrip('.-') or 'host'}-{os.getpid()}"


def zenoh_config(mode: str, connect: Sequence[str], listen: Sequence[str] = (),
                 connect_timeout_ms: int = 2000, *, pki: str | None = None,
                 identity: str | None = None) -> zenoh.Config:
    """A session config for the supervisor: multicast scouting off, explicit endpoints; with
    ``pki``/``identity``, mutual TLS as that principal (``bus_agent.gateway.zenoh_config``).
    Raises ValueError on a bad mode or identity."""
    if mode not in ("client", "peer"):
        raise ValueError(f"mode {mode!r}: use 'client' or 'peer'")
    if pki is not None or identity is not None:
        from bus_agent.gateway.zenoh_config import make_zenoh_config

        return make_zenoh_config(mode, listen if mode == "peer" else (), connect,
                                 connect_timeout_ms=connect_timeout_ms, pki=pki, identity=identity)
    conf: dict[str, Any] = {
        "mode": mode,
        "connect": {"endpoints": list(connect), "timeout_ms": connect_timeout_ms},
        "scouting": {"multicast": {"enabled": False}},
    }
    if mode == "peer":
        conf["listen"] = {"endpoints": list(listen)}
    return zenoh.Config.from_json5(json.dumps(conf))
