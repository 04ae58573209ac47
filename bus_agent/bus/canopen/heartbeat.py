"""Heartbeat consumer (CiA 301 §7.2.8.3.2.2): the NMT state of every node from its heartbeats.

Fed by frames on 0x700 + node id (heartbeat or boot-up), read by the bus's management calls.
A node whose last heartbeat is older than its consumer time is *silent* (state UNKNOWN); a
boot-up message (state 0x00) marks the node *booted*: it lost its communication parameters
(PDO mapping, heartbeat time) and is reported INITIALISING until :meth:`configured` is called.
Pure: time comes in as arguments. Thread-safe enough for one writer (the CAN receive thread)
and readers (plain attribute swaps).
"""

from __future__ import annotations

from dataclasses import dataclass

from bus_agent.bus.canopen.nmt import NmtState, decode_heartbeat


@dataclass
class _Seen:
    state: NmtState = NmtState.UNKNOWN
    at_s: float | None = None
    booted: bool = False
    boots: int = 0


class HeartbeatConsumer:
    """Last heartbeat per node. ``timeout_s``: the consumer time (0x1016), after which a node
    that sent nothing is silent."""

    def __init__(self, node_ids: tuple[int, ...], timeout_s: float) -> None:
        if timeout_s <= 0:
            raise ValueError(f"heartbeat consumer time must be > 0, got {timeout_s}")
        self.timeout_s = timeout_s
        self._seen = {n: _Seen() for n in node_ids}

    def on_frame(self, node_id: int, data: bytes | bytearray, t_s: float) -> None:
        """A heartbeat or boot-up frame from ``node_id`` at ``t_s``."""
        seen = self._seen.get(node_id)
        if seen is None:
            return
        state = decode_heartbeat(data)
        if state is NmtState.INITIALISING:
            seen.booted = True
            seen.boots += 1
        seen.state, seen.at_s = state, t_s

    def state(self, node_id: int, now_s: float) -> NmtState:
        """INITIALISING while booted and not configured again; UNKNOWN when silent; else the
        state of the last heartbeat."""
        seen = self._seen[node_id]
        if seen.booted:
            return NmtState.INITIALISING
        if seen.at_s is None or now_s - seen.at_s > self.timeout_s:
            return NmtState.UNKNOWN
        return seen.state

    def heard(self, node_id: int, now_s: float) -> bool:
        """Some heartbeat or boot-up came within the consumer time."""
        at = self._seen[node_id].at_s
        return at is not None and now_s - at <= self.timeout_s

    def booted(self, node_id: int) -> bool:
        return self._seen[node_id].booted

    def boots(self, node_id: int) -> int:
        """Boot-up messages seen from the node since the consumer started."""
        return self._seen[node_id].boots

    def configured(self, node_id: int) -> None:
        """The node's communication parameters were written again after its boot-up."""
        self._seen[node_id].booted = False
