"""One place that turns the project's few Zenoh settings into a ``zenoh.Config``.

Used by the bus agent, the supervisor and the tests, so every session of the project has the
same defaults (docs/deployment.md):

- multicast scouting off (it only works on one L2 segment and leaks between test runs);
- a short link lease (``transport/link/tx/lease``, default 10 s in zenoh) so a cut network is
  noticed in about :data:`DEFAULT_LINK_LEASE_MS` and liveliness tokens of the far side vanish;
- peers and routers retry their ``connect`` endpoints in the background (``timeout_ms`` -1:
  ``open`` returns at once and the link comes up when the router does); clients wait at most
  :data:`DEFAULT_CLIENT_CONNECT_TIMEOUT_MS` in ``open`` and fail with a clear error otherwise.

- with ``pki``/``identity`` (a ``drives-pki`` directory and a principal in it): every link is
  ``tls/`` with mutual TLS against the directory's CA (``tcp/`` endpoints are rewritten to
  ``tls/``; clients check the server certificate's name), and sessions that accept links (routers,
  and any session with listen endpoints) load the ACL compiled from ``principals.toml``, default
  deny (``bus_agent.security.roles``).

``make_zenoh_config(mode, listen, connect)`` is a stable signature: other packages import it.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path
from typing import Any, Iterable, Mapping

import zenoh

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")
#: Link lease: a silent link is declared dead after this long (zenoh default 10000 ms).
DEFAULT_LINK_LEASE_MS = 3000
#: Keep-alive messages per lease period (zenoh's default ratio).
DEFAULT_KEEP_ALIVE = 4
#: How long a client's ``open`` waits for a router before it raises.
DEFAULT_CLIENT_CONNECT_TIMEOUT_MS = 5000
#: Background reconnection back-off of peers and routers.
CONNECT_RETRY = {"period_init_ms": 100, "period_max_ms": 2000, "period_increase_factor": 2}


def zenoh_error_text(exc: object) -> str:
    """A zenoh error without the library's source locations (``... at /root/.cargo/...rs:61.``)."""
    return re.sub(r"\s+at\s+\S+\.rs:\d+\.?", "", str(exc)).strip()


class ZenohConfigError(ValueError):
    """A Zenoh setting that cannot work (unknown mode, malformed endpoint)."""


def _check_endpoint(ep: str) -> str:
    # Zenoh's own error for a malformed locator comes late (at open) and is cryptic.
    if not isinstance(ep, str) or "/" not in ep or ep.startswith("/") or ep.endswith("/"):
        raise ZenohConfigError(
            f"endpoint {ep!r} is not a zenoh locator: expected <protocol>/<address>, e.g. tcp/127.0.0.1:7447"
        )
    return ep


def _secure_endpoint(ep: str) -> str:
    proto, _, addr = ep.partition("/")
    if proto == "tls":
        return ep
    if proto == "tcp":
        return f"tls/{addr}"
    raise ZenohConfigError(f"endpoint {ep!r}: with --pki every link is tls/ (or tcp/, made tls/), not {proto}/")


def secure_settings(pki: str | Path, identity: str, *, acl: bool) -> dict[str, Any]:
    """TLS (mutual, against ``pki``'s CA) as ``identity``, and with ``acl`` the access control
    compiled from ``pki``/principals.toml. Raises :class:`ZenohConfigError` naming the file or
    principal at fault (missing, expired, not in principals.toml, key readable by others)."""
    from bus_agent.security import pki as pki_mod
    from bus_agent.security import principals, roles

    try:
        files = pki_mod.check_identity(pki, identity)
        known, revoked = principals.load_all(pki)
    except (pki_mod.PkiError, principals.PrincipalsError) as exc:
        raise ZenohConfigError(f"--pki {pki} --identity {identity}: {exc}") from None
    if identity in revoked:
        raise ZenohConfigError(f"--identity {identity!r} was revoked ({revoked[identity].revoked_at}): every router "
                               "that loaded this principals.toml denies it; issue a certificate under a new name")
    if identity not in known:
        raise ZenohConfigError(f"--identity {identity!r} is not in {Path(pki) / principals.FILE_NAME} "
                               f"(issue it with `drives-pki issue {pki} {identity} --role ROLE`)")
    settings: dict[str, Any] = {"transport/link/tls": {
        "root_ca_certificate": str(files.ca),
        "listen_certificate": str(files.cert), "listen_private_key": str(files.key),
        "connect_certificate": str(files.cert), "connect_private_key": str(files.key),
        "enable_mtls": True, "verify_name_on_connect": True,
        # A link ends when the peer's certificate expires, not at the next reconnection.
        "close_link_on_expiration": True,
    }}
    if acl:
        settings["access_control"] = roles.compile_acl(known.values(), revoked)
    return settings


def make_zenoh_config(
    mode: str = "peer",
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    *,
    multicast_scouting: bool = False,
    link_lease_ms: int = DEFAULT_LINK_LEASE_MS,
    connect_timeout_ms: int | None = None,
    extra: Mapping[str, Any] | None = None,
    base: zenoh.Config | None = None,
    pki: str | Path | None = None,
    identity: str | None = None,
    acl: bool | None = None,
) -> zenoh.Config:
    """Build a ``zenoh.Config``.

    ``mode``: 'peer', 'client' or 'router'. ``listen``/``connect``: endpoint lists
    (``tcp/127.0.0.1:7447``). ``connect_timeout_ms``: None picks -1 (retry in the background)
    for peers and routers and :data:`DEFAULT_CLIENT_CONNECT_TIMEOUT_MS` for clients.
    ``extra``: further settings as ``{"path/to/key": json-serialisable value}`` (TLS, ACL, auth).
    ``base``: a config (e.g. loaded from a JSON5 file) to apply these settings on top of.
    ``pki``/``identity``: secure the session (see the module docstring); ``acl`` None loads the
    ACL in routers and in sessions that listen.
    Raises :class:`ZenohConfigError` on an unknown mode, a malformed endpoint or a bad identity.
    """
    if mode not in MODES:
        raise ZenohConfigError(f"zenoh mode {mode!r} is not one of {', '.join(MODES)}")
    listen = [_check_endpoint(ep) for ep in listen]
    connect = [_check_endpoint(ep) for ep in connect]
    secure: dict[str, Any] = {}
    if pki is not None or identity is not None:
        if pki is None or not identity:
            raise ZenohConfigError("--pki and --identity go together (a PKI directory and a principal in it)")
        listen = [_secure_endpoint(ep) for ep in listen]
        connect = [_secure_endpoint(ep) for ep in connect]
        secure = secure_settings(pki, identity, acl=(mode == "router" or bool(listen)) if acl is None else acl)
    if link_lease_ms < 100:
        raise ZenohConfigError(f"link lease {link_lease_ms} ms is too short (at least 100 ms)")
    if connect_timeout_ms is None:
        connect_timeout_ms = DEFAULT_CLIENT_CONNECT_TIMEOUT_MS if mode == "client" else -1
    settings: dict[str, Any] = {
        "mode": mode,
        "connect/endpoints": connect,
        "connect/timeout_ms": connect_timeout_ms,
        "connect/exit_on_failure": mode == "client",
        "connect/retry": CONNECT_RETRY,
        "scouting/multicast/enabled": bool(multicast_scouting),
        "transport/link/tx/lease": int(link_lease_ms),
        "transport/link/tx/keep_alive": DEFAULT_KEEP_ALIVE,
    }
    if listen or mode != "client":
        # An empty list keeps a peer from listening on a random port of every interface.
        settings["listen/endpoints"] = listen
    settings.update(secure)
    settings.update(extra or {})
    return _apply(zenoh.Config() if base is None else base, settings)


def _apply(conf: zenoh.Config, settings: Mapping[str, Any]) -> zenoh.Config:
    for key, value in settings.items():
        try:
            conf.insert_json5(key, json.dumps(value))
        except Exception as exc:  # zenoh raises ZError; the caller wants the setting named
            raise ZenohConfigError(f"zenoh setting {key}={value!r} rejected: {exc}") from None
    return conf


def from_settings(zc: Any, extra: Mapping[str, Any] | None = None) -> zenoh.Config:
    """Build from an object with ``mode``, ``listen``, ``connect`` and optional ``scouting``
    (multicast), ``link_lease_ms``, ``connect_timeout_ms``, ``config_file`` attributes (the
    agent's ``[zenoh]`` section, ``bus_agent.config.ZenohConfig``). A ``config_file`` (JSON5: TLS, ACL, auth) is loaded first and the
    other settings are applied on top of it, ``extra`` (as in :func:`make_zenoh_config`) last."""
    base = None
    path = getattr(zc, "config_file", None)
    if path:
        try:
            base = zenoh.Config.from_file(str(path))
        except Exception as exc:
            raise ZenohConfigError(f"zenoh config file {path}: {exc}") from None
    return make_zenoh_config(
        getattr(zc, "mode", "peer"),
        getattr(zc, "listen", ()) or (),
        getattr(zc, "connect", ()) or (),
        multicast_scouting=bool(getattr(zc, "multicast_scouting", getattr(zc, "scouting", False))),
        link_lease_ms=int(getattr(zc, "link_lease_ms", None) or DEFAULT_LINK_LEASE_MS),
        connect_timeout_ms=getattr(zc, "connect_timeout_ms", None),
        base=base,
        pki=getattr(zc, "pki", None),
        identity=getattr(zc, "identity", None),
        extra=extra,
    )
