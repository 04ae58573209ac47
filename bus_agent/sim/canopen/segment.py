"""The nodes of one simulated CAN bus and their I/O: one python-can bus, one thread.

The thread receives frames (python-can ``recv`` with a short timeout), hands each to every
node, sends what the nodes answer, and every :data:`TICK_S` lets time pass for heartbeats,
watchdogs and drive steps. Fault injection (:meth:`Segment.control_handlers`, served on
``drives/@sim/<segment>/<node index>/<action>``) runs under the same lock.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import can

from bus_agent.sim.canopen.dictionary import NodeDictionary
from bus_agent.sim.canopen.node import Frame, SimNode
from bus_agent.sim.drive_model import PROFILES
from bus_agent.stop_signals import StopSignals

log = logging.getLogger(__name__)

TICK_S = 0.002


class Segment:
    """``node_ids`` nodes on ``bus`` (index i = node_ids[i]): of one drive profile, or each with
    its own dictionary (``dictionaries[i]``, from its EDS)."""

    def __init__(self, bus: can.BusABC, node_ids: list[int], profile: str = "generic",
                 clock: Callable[[], float] = time.monotonic,
                 dictionaries: list[NodeDictionary] | None = None) -> None:
        if profile not in PROFILES:
            raise ValueError(f"unknown drive profile {profile!r}; known: {', '.join(sorted(PROFILES))}")
        if len(set(node_ids)) != len(node_ids):
            raise ValueError(f"node ids repeat: {node_ids}")
        self.bus = bus
        self.clock = clock
        if dictionaries is not None and len(dictionaries) != len(node_ids):
            raise ValueError(f"{len(dictionaries)} dictionaries for {len(node_ids)} nodes")
        self.nodes = [SimNode(n, PROFILES[profile], serial=n, dictionary=dictionaries[i] if dictionaries else None)
                      for i, n in enumerate(node_ids)]
        self.lock = threading.Lock()
        self.frames_in = 0
        self.frames_out = 0
        self.send_errors = 0
        self.max_lag_s = 0.0
        self.stop_event = threading.Event()
        #: The process's stop signals (canopen-sim's CLI): the loop ends when one arrived.
        self.stop_signals: StopSignals | None = None
        self._thread: threading.Thread | None = None

    def boot(self) -> None:
        """Every node sends its boot-up message (power on)."""
        with self.lock:
            now = self.clock()
            for node in self.nodes:
                self._send([(0x700 + node.node_id, b"\x00")])
                node.tick(now)

    def _send(self, frames: list[Frame]) -> None:
        for cob, data in frames:
            try:
                self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
                self.frames_out += 1
            except can.CanError as e:
                self.send_errors += 1
                log.debug("send 0x%03X failed: %s", cob, e)

    def run(self) -> None:
        """Receive and tick until :meth:`stop` (the calling thread)."""
        next_tick = self.clock()
        while not self.stop_event.is_set() and not (self.stop_signals is not None and self.stop_signals.stopped):
            msg = self.bus.recv(timeout=TICK_S)
            now = self.clock()
            with self.lock:
                if msg is not None and not msg.is_remote_frame and not msg.is_error_frame:
                    self.frames_in += 1
                    if msg.timestamp:  # kernel receive time (wall clock): how far behind the bus we are
                        lag = time.time() - msg.timestamp
                        if lag > self.max_lag_s:
                            self.max_lag_s = lag
                    cob, data = msg.arbitration_id, bytes(msg.data)
                    for node in self.nodes:
                        out = node.on_frame(cob, data, now)
                        if out:
                            self._send(out)
                if now >= next_tick:
                    next_tick = now + TICK_S
                    for node in self.nodes:
                        out = node.tick(now)
                        if out:
                            self._send(out)

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="canopen-sim", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self.stop_event.set()
        if self._thread is not None:
            self._thread.join(5)

    # ------------------------------------------------------------------ fault injection

    def _node(self, position: int) -> SimNode:
        if not 0 <= position < len(self.nodes):
            raise ValueError(f"no node at position {position} (0..{len(self.nodes) - 1})")
        return self.nodes[position]

    def control_handlers(self) -> dict[str, Callable[[int, dict], str]]:
        """``fault {error_code}``, ``unplug``, ``plug``, ``status`` per node position."""

        def fault(position: int, args: dict) -> str:
            code = args.get("error_code")
            if set(args) != {"error_code"} or not isinstance(code, int) or isinstance(code, bool):
                raise ValueError(f"fault takes exactly {{'error_code': int}}, got {args!r}")
            with self.lock:
                node = self._node(position)
                self._send(node.inject_fault(code, self.clock()))
            return f"node {node.node_id}: fault 0x{code:04X} injected"

        def unplug(position: int, args: dict) -> str:
            _no_args(args)
            with self.lock:
                node = self._node(position)
                node.unplug()
            log.warning("node %d: unplugged", node.node_id)
            return f"node {node.node_id}: unplugged"

        def plug(position: int, args: dict) -> str:
            _no_args(args)
            with self.lock:
                node = self._node(position)
                self._send(node.plug(self.clock()))
            return f"node {node.node_id}: plugged (boot-up, pre-operational)"

        def status(position: int, args: dict) -> str:
            _no_args(args)
            with self.lock:
                node = self._node(position)
                return (f"node {node.node_id}: nmt {node.state.wire_name} drive {node.model.state.value} "
                        f"plugged {node.plugged} counters {node.counters}")

        return {"fault": fault, "unplug": unplug, "plug": plug, "status": status}


def _no_args(args: dict) -> None:
    if args:
        raise ValueError(f"takes no arguments, got {args!r}")
