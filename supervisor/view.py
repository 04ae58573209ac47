"""The Fleet's view: which agents are alive, the latest status of every drive and agent, the
other supervisors, and the host-name conflicts; kept current from Zenoh callbacks.

Callbacks decode, update under one reentrant condition (:attr:`FleetView.lock`, notified on
every update so :meth:`FleetView.wait_until` re-checks) and hand events to the emitter; nothing
here blocks or sends.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable, TypeVar

import zenoh

from schemas import keys
from schemas.messages import AgentStatus, DriveStatus, SchemaError, decode

from .selectors import DriveRef

log = logging.getLogger("supervisor.fleet")

T = TypeVar("T")

#: Two agent instances seen under one host name within this window are a conflict (agents
#: publish their status every second).
CONFLICT_HOLD_S = 3.5


@dataclass
class AgentInfo:
    """What the supervisor knows about one agent (host)."""

    host: str
    alive: bool
    status: AgentStatus | None = None
    seen_monotonic: float = 0.0
    gone_monotonic: float | None = None


class FleetView:
    """Agents, drives and supervisors as the subscriptions report them.

    ``emit(event, *args)`` queues ``arrival``/``departure``/``status``/``agent`` events;
    ``departed(host)`` is called when an agent goes (the commands waiting for it stop waiting).
    """

    def __init__(self, name: str, emit: Callable[..., None], departed: Callable[[str], None]) -> None:
        self._name = name
        self._emit = emit
        self._departed = departed
        #: Guards everything below; notified on every update. Reentrant: wait_until predicates
        #: call back into the view.
        self.lock = threading.Condition()
        self._agents: dict[str, AgentInfo] = {}
        self._drives: dict[DriveRef, DriveStatus] = {}
        self._missed: dict[DriveRef, int] = {}
        # host -> agent instance id -> (last seen monotonic, the agent's own conflict text)
        self._instances: dict[str, dict[str, tuple[float, str]]] = {}
        self._status_count = 0
        self._supervisors: set[str] = set()

    # ---- updates (Zenoh callbacks and get replies) ---------------------------------------

    def host_alive(self, key: str, alive: bool) -> None:
        """An agent's liveliness token ``key`` appeared (``alive``) or vanished."""
        try:
            parsed = keys.parse(key)
        except keys.InvalidKey:
            log.warning("supervisor %s: ignoring liveliness key %s", self._name, key)
            return
        if parsed.kind is not keys.KeyKind.ALIVE or parsed.host is None:
            return
        host = parsed.host
        now = time.monotonic()
        with self.lock:
            info = self._agents.get(host)
            was = info.alive if info else False
            if info is None:
                info = self._agents[host] = AgentInfo(host, alive, seen_monotonic=now)
            info.alive = alive
            if alive and not was:
                info.seen_monotonic, info.gone_monotonic = now, None
                # An agent that comes back starts its sequence numbers anew.
                for ref in [r for r in self._drives if r.host == host]:
                    self._missed.pop(ref, None)
            elif not alive and was:
                info.gone_monotonic = now
                self._instances.pop(host, None)  # a restarted agent is not a second one
            self.lock.notify_all()
        if alive and not was:
            log.info("agent %s arrived", host)
            self._emit("arrival", host)
        elif was and not alive:
            self._departed(host)
            log.warning("agent %s is gone", host)
            self._emit("departure", host)

    def on_alive(self, sample: zenoh.Sample) -> None:
        self.host_alive(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    def on_supervisor(self, sample: zenoh.Sample) -> None:
        try:
            parsed = keys.parse(str(sample.key_expr))
        except keys.InvalidKey:
            return
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._supervisors.add(parsed.name or "")
            else:
                self._supervisors.discard(parsed.name or "")

    def decoded(self, sample: zenoh.Sample, cls: type[T], what: str) -> T | None:
        """A put's message, or None (a delete, or a payload that is not a valid ``cls``: logged)."""
        if sample.kind != zenoh.SampleKind.PUT:
            return None
        try:
            return decode(sample.payload.to_bytes(), cls)
        except SchemaError as exc:
            log.warning("supervisor %s: bad %s on %s: %s", self._name, what, sample.key_expr, exc)
            return None

    def on_status_sample(self, sample: zenoh.Sample) -> None:
        st = self.decoded(sample, DriveStatus, "status")
        if st is not None:
            self.apply_status(st)

    def apply_status(self, st: DriveStatus) -> None:
        """Take a drive's status into the view (unless older than what is there) and emit it."""
        ref = DriveRef(st.host, st.axis)
        with self.lock:
            old = self._drives.get(ref)
            restarted = ref not in self._missed
            if old is not None and not restarted and st.seq <= old.seq:
                return  # a get reply older than, or equal to, what the subscription brought
            if old is not None and not restarted and st.seq > old.seq + 1:
                self._missed[ref] = self._missed.get(ref, 0) + (st.seq - old.seq - 1)
            else:
                self._missed.setdefault(ref, 0)
            self._drives[ref] = st
            self._status_count += 1
            self.lock.notify_all()
        self._emit("status", st)

    def on_agent_sample(self, sample: zenoh.Sample) -> None:
        st = self.decoded(sample, AgentStatus, "agent status")
        if st is None:
            return
        with self.lock:
            if st.instance:
                self._instances.setdefault(st.host, {})[st.instance] = (time.monotonic(), st.conflict)
            info = self._agents.get(st.host)
            if info is None:
                # Status before the liveliness token: known, not yet counted alive.
                info = self._agents[st.host] = AgentInfo(st.host, False, seen_monotonic=time.monotonic())
            if info.status is not None and 0 < st.seq <= info.status.seq and info.alive:
                return
            info.status = st
            self.lock.notify_all()
        self._emit("agent", st)

    # ---- queries -------------------------------------------------------------------------

    def alive(self) -> set[str]:
        """Hosts whose agent is alive now (unsorted)."""
        with self.lock:
            return {h for h, a in self._agents.items() if a.alive}

    def hosts(self) -> list[str]:
        return sorted(self.alive())

    def agents(self) -> dict[str, AgentInfo]:
        with self.lock:
            return {h: AgentInfo(a.host, a.alive, a.status, a.seen_monotonic, a.gone_monotonic)
                    for h, a in self._agents.items()}

    def drives(self) -> dict[DriveRef, DriveStatus]:
        with self.lock:
            return dict(self._drives)

    def status(self, ref: DriveRef) -> DriveStatus | None:
        with self.lock:
            return self._drives.get(ref)

    def missed(self) -> dict[DriveRef, int]:
        with self.lock:
            return dict(self._missed)

    @property
    def status_count(self) -> int:
        with self.lock:
            return self._status_count

    def supervisors(self) -> list[str]:
        with self.lock:
            return sorted(self._supervisors)

    def host_axes(self) -> dict[str, list[str]]:
        """Each live agent's own complete axis list (AgentStatus.axes), where known."""
        with self.lock:
            return {h: list(a.status.axes) for h, a in self._agents.items()
                    if a.alive and a.status is not None and a.status.axes}

    def host_groups(self) -> list[dict[str, list[str]]]:
        """The groups each live agent announces (AgentStatus.groups)."""
        with self.lock:
            return [a.status.groups for a in self._agents.values() if a.alive and a.status is not None]

    def roster(self) -> list[DriveRef]:
        """Drives of live agents: from their status publications and their agent status."""
        with self.lock:
            alive = {h for h, a in self._agents.items() if a.alive}
            refs = {r for r in self._drives if r.host in alive}
            for h in alive:
                st = self._agents[h].status
                if st is not None:
                    refs.update(DriveRef(h, ax) for ax in st.axes)
            return sorted(refs)

    def conflicts(self) -> dict[str, str]:
        """Hosts whose name two agents use (two instance ids within :data:`CONFLICT_HOLD_S`, or an
        agent saying so), with what is known."""
        now = time.monotonic()
        out: dict[str, str] = {}
        with self.lock:
            for host, seen in self._instances.items():
                if not (host in self._agents and self._agents[host].alive):
                    continue  # a departed host (its last status may still come in) commands nothing
                recent = {i: c for i, (t, c) in seen.items() if now - t < CONFLICT_HOLD_S}
                said = [c for c in recent.values() if c]
                if len(recent) > 1:
                    out[host] = (f"host name {host} is used by {len(recent)} agents (instances "
                                 f"{', '.join(sorted(recent))}): not commanded until one stops")
                elif said:
                    out[host] = said[0]
        return out

    def wait_until(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Wait until ``predicate()`` holds (re-checked on every update) or the deadline."""
        deadline = time.monotonic() + timeout_s
        with self.lock:
            while True:
                if predicate():
                    return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.lock.wait(min(left, 0.1))


__all__ = ["AgentInfo", "CONFLICT_HOLD_S", "FleetView"]
