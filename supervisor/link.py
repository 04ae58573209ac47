"""The Fleet's link to Zenoh: the session, the supervisor's liveliness token, the subscriptions
that keep the :class:`~supervisor.view.FleetView` current, and the snapshot gets.

Status goes through a deep FIFO drained by this part's own thread: a burst (every drive of a
large fleet changing at once) is absorbed here instead of backing up into the router, which
drops samples published with congestion control DROP towards a slow subscriber.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Iterable

import zenoh

from bus_agent.gateway.zenoh_config import zenoh_error_text
from schemas import keys
from schemas.messages import DriveStatus, SchemaError, decode

from .session import DEFAULT_CONNECT, zenoh_config
from .view import FleetView

log = logging.getLogger("supervisor.fleet")

#: Depth of the status subscriber's FIFO (samples): a few status bursts of a 1024-drive fleet.
STATUS_FIFO = 65536


class FleetError(RuntimeError):
    """The fleet could not be reached or a command could not be sent."""


class NoAgentError(FleetError):
    """No router/agent answered: nothing to supervise."""


class FleetLink:
    """One Zenoh session and what is declared on it, feeding ``view``."""

    def __init__(self, name: str, view: FleetView) -> None:
        self._name = name
        self._view = view
        self._session: zenoh.Session | None = None
        self._decls: list[Any] = []
        self._token: Any = None
        self._drainer: threading.Thread | None = None

    @property
    def is_open(self) -> bool:
        return self._session is not None

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise FleetError("fleet is not open")
        return self._session

    def open(self, config: dict[str, Any]) -> None:
        """Open the session with ``zenoh_config(**config)``, declare the token and subscriptions.
        Raise :class:`NoAgentError` when no endpoint answers in time."""
        identity, pki = config.get("identity"), config.get("pki")
        try:
            self._session = zenoh.open(zenoh_config(**config))
        except zenoh.ZError as exc:
            raise NoAgentError(f"cannot reach {', '.join(config['connect'])} ({zenoh_error_text(exc)}); check that "
                               "a router or bus agent is running and listening there (bus-agent --sim listens "
                               f"on {DEFAULT_CONNECT[0]}), or give --connect"
                               + (f"; as {identity}: check that the router trusts the CA of {pki} and "
                                  "that its certificate names the address dialled" if identity else
                                  "; a secure router (tls/) needs --pki DIR --identity NAME")) from None

    def declare(self) -> None:
        """The supervisor's liveliness token and the subscriptions (after the events run)."""
        s, v = self.session, self._view
        self._token = s.liveliness().declare_token(keys.supervisor_alive(self._name))
        self._decls.append(s.liveliness().declare_subscriber(keys.ALL_ALIVE, v.on_alive, history=True))
        self._decls.append(s.liveliness().declare_subscriber(keys.ALL_SUPERVISORS, v.on_supervisor, history=True))
        status_sub = s.declare_subscriber(keys.ALL_DRIVE_STATUS, zenoh.handlers.FifoChannel(STATUS_FIFO))
        self._decls.append(status_sub)
        self._drainer = threading.Thread(target=self._drain, args=(status_sub,), name=f"fleet-{self._name}-status",
                                         daemon=True)
        self._drainer.start()
        self._decls.append(s.declare_subscriber(keys.ALL_AGENT_STATUS, v.on_agent_sample))

    def close(self) -> None:
        """Undeclare everything and close the session."""
        for d in self._decls:
            try:
                d.undeclare()
            except Exception:
                pass
        self._decls.clear()
        if self._drainer is not None:
            self._drainer.join(timeout=5)
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        if self._session is not None:
            self._session.close()
            self._session = None

    def _drain(self, sub: Any) -> None:
        for sample in sub:  # ends when the subscriber is undeclared
            try:
                self._view.on_status_sample(sample)
            except Exception:
                log.exception("supervisor %s: status handling failed", self._name)

    def refresh(self, timeout_s: float) -> None:
        """Query liveliness tokens, drive status and agent status once (a synchronous snapshot)."""
        s, v = self.session, self._view
        for reply in s.liveliness().get(keys.ALL_ALIVE, timeout=timeout_s):
            if reply.ok is not None:
                v.host_alive(str(reply.ok.key_expr), True)
        for selector, handler in ((keys.ALL_DRIVE_STATUS, v.on_status_sample),
                                  (keys.ALL_AGENT_STATUS, v.on_agent_sample)):
            for reply in s.get(selector, target=zenoh.QueryTarget.ALL,
                               consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
                if reply.ok is not None:
                    handler(reply.ok)

    def get_status(self, pairs: Iterable[tuple[str, str]], timeout_s: float) -> list[DriveStatus]:
        """The agents' current status under each ``(host, axis)`` key expression (one get each),
        each merged into the view too."""
        out: list[DriveStatus] = []
        for host, axis in pairs:
            for reply in self.session.get(keys.drive_status(host, axis), target=zenoh.QueryTarget.ALL,
                                          consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
                if reply.ok is None:
                    continue
                try:
                    st = decode(reply.ok.payload.to_bytes(), DriveStatus)
                except SchemaError as exc:
                    log.warning("supervisor %s: bad status on %s: %s", self._name, reply.ok.key_expr, exc)
                    continue
                out.append(st)
                self._view.apply_status(st)  # decoded once
        return out


__all__ = ["FleetError", "FleetLink", "NoAgentError", "STATUS_FIFO"]
