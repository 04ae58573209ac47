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

Both go through a session the routers route for, whatever the agent's own session mode
(:func:`claim_config`): zenoh's routers do not forward between two *peers* (peer-to-peer
routing: peers are expected to link directly), so two ``bus-agent --connect ROUTER`` in peer
mode without ``--listen`` never saw each other's token or status and both ran under one name.
A peer with ``connect`` endpoints therefore checks through a small *client* session to the same
endpoints (a client's traffic the router always routes), opened at start and, while the router
is unreachable, again in the background.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from types import SimpleNamespace
from typing import Any, Callable

from bus_agent import runtime as rt
from bus_agent.gateway.settings import GatewaySettings
from schemas import keys
from schemas import messages as m

log = logging.getLogger(__name__)
#: The running conflict is logged under the gateway's logger name, like the gateway's other news.
gwlog = logging.getLogger("bus_agent.gateway.gateway")

#: How long start-up waits for a link to a configured router or peer before it checks anyway.
LINK_WAIT_S = 2.0
#: How long after the link start-up keeps asking (token propagation after a new link takes a moment).
SETTLE_S = 1.0
#: How long the liveliness query for the host name waits for answers.
QUERY_TIMEOUT_S = 1.0


#: How long the claim's client session waits for a router in ``open``; then it retries every
#: :data:`CLAIM_RETRY_S` in the background.
CLAIM_OPEN_TIMEOUT_MS = 2000
CLAIM_RETRY_S = 1.0


class HostNameTaken(RuntimeError):
    """Another agent holds this host name (its liveliness token answered)."""


def new_instance() -> str:
    """A random id for this agent process (12 hex digits)."""
    return uuid.uuid4().hex[:12]


def claim_config(zc: Any) -> Any:
    """The ``zenoh.Config`` of the claim's client session for an agent whose zenoh settings are
    ``zc`` (``bus_agent.config.ZenohConfig``), or None when the agent's own session serves: a
    client or router session is routed by the routers it links to, and a session without
    ``connect`` endpoints is reached directly by whoever connects to it. Same endpoints and
    identity as the agent's session; listens nowhere."""
    if getattr(zc, "mode", "peer") != "peer" or not getattr(zc, "connect", ()):
        return None
    from bus_agent.gateway.zenoh_config import from_settings

    kept = ("connect", "scouting", "multicast_scouting", "link_lease_ms", "config_file", "pki", "identity")
    client = SimpleNamespace(**{k: getattr(zc, k) for k in kept if hasattr(zc, k)}, mode="client", listen=())
    return from_settings(client, extra={"listen/endpoints": [], "connect/timeout_ms": CLAIM_OPEN_TIMEOUT_MS})


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


class ClaimLink:
    """The claim's own client session (:func:`claim_config`) and its subscriber to the status
    published under our host name. :meth:`open` tries once (bounded by the client's connect
    timeout); :meth:`retry` keeps trying in the background until it opens or ``stop`` is set."""

    def __init__(self, config: Any, status_key: str, on_status: Any) -> None:
        self._config = config
        self._key = status_key
        self._on_status = on_status
        self._lock = threading.Lock()
        self._closed = False
        self.session: Any = None
        self._sub: Any = None

    def open(self) -> Any:
        """The opened session, or None (no router reachable yet: the reason is logged)."""
        import zenoh

        try:
            session = zenoh.open(self._config)
        except zenoh.ZError as exc:
            log.warning("host claim: no router reachable for the claim's client session yet (%s): "
                        "retrying every %.0f s", exc, CLAIM_RETRY_S)
            return None
        with self._lock:
            if self._closed:
                session.close()
                return None
            self.session = session
            self._sub = session.declare_subscriber(self._key, self._on_status)
        return session

    def retry(self, stop: threading.Event) -> threading.Thread:
        """Start thread ``gw-claim``: :meth:`open` every :data:`CLAIM_RETRY_S` until it succeeds."""
        def loop() -> None:
            while not stop.wait(CLAIM_RETRY_S) and self.open() is None:
                pass
        t = threading.Thread(target=loop, name="gw-claim", daemon=True)
        t.start()
        return t

    def close(self) -> None:
        with self._lock:
            self._closed = True
            sub, session, self._sub, self.session = self._sub, self.session, None, None
        for close in ((sub.undeclare if sub is not None else None), (session.close if session is not None else None)):
            if close is not None:
                try:
                    close()
                except Exception as exc:  # closing must finish
                    log.warning("host claim: close: %s", exc)


class HostClaim:
    """The gateway's part for its host name: this process' instance id, the start-up check, the
    claim's own session (:class:`ClaimLink`, when ``config`` is given) and the running conflict.

    Given: the settings' host, instance and check flags, the claim session's ``config``
    (:func:`claim_config`; None when the agent's own session serves), and ``emit`` and
    ``agent_status_now`` of the gateway's feed, to say when a conflict begins or ends.
    :meth:`on_own_status` and :meth:`tick` run on ``gw-command``."""

    def __init__(self, settings: GatewaySettings, config: Any, emit: Callable[[rt.CycleEvent], None],
                 agent_status_now: Callable[[], None]) -> None:
        self.host = settings.host
        self.instance = settings.instance or new_instance()
        self._check_host = settings.check_host
        self._has_connect = settings.has_connect
        # Other agents under our host name; a conflict ends after three silent status periods.
        self._conflicts = ConflictTracker(self.host, self.instance, max(1.0, 3 * settings.agent_period_s))
        #: '' without a conflict, else what it is (refuses the ops of CONFLICT_REFUSED_OPS).
        self.conflict_text = ""
        self._config = config
        self._link: ClaimLink | None = None
        self._opened = False
        self._emit = emit
        self._agent_status_now = agent_status_now

    def check(self, session: Any, on_own_status: Callable[[Any], None]) -> None:
        """Open the claim's session (if configured; it listens to our host's agent status with
        ``on_own_status``) and, unless disabled, raise :class:`HostNameTaken` when another agent
        holds the host name (the claim's session closed again)."""
        # The claim goes through a session the routers route for (claim_config): a peer's own
        # session does not reach another peer behind the same router.
        claim = None
        if self._config is not None:
            self._link = ClaimLink(self._config, keys.agent_status(self.host), on_own_status)
            claim = self._link.open()
        self._opened = claim is not None
        if not self._check_host:
            return
        try:
            if claim is not None:
                check_host_free(claim, self.host, has_connect=True)
            else:  # a client open already waited for a router: check what the own session sees now
                check_host_free(session, self.host, has_connect=self._has_connect and self._link is None)
        except Exception:
            if self._link is not None:
                self._link.close()
            raise

    def retry(self, stop: threading.Event) -> threading.Thread | None:
        """Thread ``gw-claim`` when the claim's session did not open at :meth:`check`, else None."""
        if self._link is None or self._opened:
            return None
        return self._link.retry(stop)

    def on_own_status(self, sample: Any) -> None:
        """An agent status under our host name (ours, or another instance's: a conflict)."""
        try:
            st = m.decode(sample.payload.to_bytes(), m.AgentStatus)
        except m.SchemaError:
            return
        if self._conflicts.seen(st.instance, time.monotonic()):
            self._conflict_changed()

    def tick(self, now: float) -> None:
        """End the conflict once the other instances were silent long enough."""
        if self._conflicts.expire(now):
            self._conflict_changed()

    def _conflict_changed(self) -> None:
        self.conflict_text = self._conflicts.text
        if self.conflict_text:
            gwlog.error("agent %s: %s", self.host, self.conflict_text)
        else:
            gwlog.warning("agent %s: host name conflict over (no other instance for %.0f s)", self.host,
                        self._conflicts.hold_s)
        self._emit(rt.CycleEvent("", "conflict", detail=self.conflict_text or "host name conflict over"))
        self._agent_status_now()  # say it in the agent status now

    def close(self) -> None:
        if self._link is not None:
            self._link.close()
