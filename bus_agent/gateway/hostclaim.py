"""One agent per host name: the start-up check and the running conflict detector.

A host name is the agent's address in the key space (``drives/@v1/<host>/...``): two agents under
one name would both obey every command sent to it. So:

- at start, before the gateway declares anything, :func:`check_host_free` waits (bounded) for a
  link to the configured routers/peers and asks for the liveliness token
  ``drives/@v1/<host>/alive``; if one answers, another agent holds the name and start-up fails
  (``bus-agent`` exit code 3);
- while running, every agent puts a random ``instance`` id in its ``AgentStatus`` and listens to
  the status published under its own host name; a status with another instance id (two
  partitions that healed, or an agent started where the check could not reach the other) is a
  conflict, tracked by :class:`ConflictTracker` (pure: instance ids and times in, the conflict
  text out) until the other instance has been silent for ``hold_s``.
"""

from __future__ import annotations

import logging
import time
import uuid
from typing import Any

from schemas import keys

log = logging.getLogger(__name__)

#: How long start-up waits for a link to a configured router or peer before it checks anyway.
LINK_WAIT_S = 2.0
#: How long after the link start-up keeps asking (token propagation after a new link takes a moment).
SETTLE_S = 1.0
#: How long the liveliness query for the host name waits for answers.
QUERY_TIMEOUT_S = 1.0


class HostNameTaken(RuntimeError):
    """Another agent holds this host name (its liveliness token answered)."""


def new_instance() -> str:
    """A random id for this agent process (12 hex digits)."""
    return uuid.uuid4().hex[:12]


def _linked(session: Any) -> bool:
    info = session.info
    return any(True for _ in info.routers_zid()) or any(True for _ in info.peers_zid())


def check_host_free(session: Any, host: str, *, has_connect: bool, link_wait_s: float = LINK_WAIT_S,
                    timeout_s: float = QUERY_TIMEOUT_S) -> None:
    """Raise :class:`HostNameTaken` when another agent's liveliness token for ``host`` answers.

    ``has_connect``: the session has ``connect`` endpoints; then wait up to ``link_wait_s`` for a
    link first (peers connect in the background), so the query reaches the network."""
    if has_connect:
        deadline = time.monotonic() + link_wait_s
        while not _linked(session) and time.monotonic() < deadline:
            time.sleep(0.02)
        if not _linked(session):
            log.warning("agent %s: no router or peer reachable yet: the host name is checked again "
                        "when other agents' status arrives", host)
    token = keys.alive(host)
    # A router that has just linked this session may not have passed on every token yet: ask again
    # until SETTLE_S after the link (seen in CI: a single query right after the link missed a token).
    settle_until = time.monotonic() + (SETTLE_S if has_connect else 0.0)
    while True:
        for reply in session.liveliness().get(token, timeout=timeout_s):
            if reply.ok is not None:
                raise HostNameTaken(
                    f"host name {host!r} is taken: another agent's liveliness token {token} answered; stop "
                    f"that agent or start this one with another --host")
        if time.monotonic() >= settle_until:
            return
        time.sleep(0.2)


class ConflictTracker:
    """Other agent instances seen under our host name (pure; the gateway feeds it)."""

    def __init__(self, host: str, instance: str, hold_s: float) -> None:
        self.host = host
        self.instance = instance
        self.hold_s = hold_s
        self._others: dict[str, float] = {}  # instance -> last seen (monotonic s)

    def seen(self, instance: str, now_s: float) -> bool:
        """A status of ``instance`` under our host name arrived; True when a conflict begins."""
        if not instance or instance == self.instance:
            return False
        began = not self._others
        self._others[instance] = now_s
        return began

    def expire(self, now_s: float) -> bool:
        """Forget instances silent for ``hold_s``; True when the conflict just ended."""
        if not self._others:
            return False
        self._others = {i: t for i, t in self._others.items() if now_s - t < self.hold_s}
        return not self._others

    @property
    def text(self) -> str:
        """'' without a conflict, else what it is."""
        if not self._others:
            return ""
        return (f"host name {self.host} is also used by agent instance(s) {', '.join(sorted(self._others))} "
                f"(this one: {self.instance}): stop one of them")
