"""The flight recorder's server: recording queries answered one at a time on thread ``gw-record``.

:class:`RecordingServer` is the part of :class:`bus_agent.gateway.gateway.Gateway` that owns the
queue of waiting recording queries; copies of a recording take a while, so they never run on the
command thread.
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any

import zenoh

from bus_agent.gateway.requests import (MSGPACK, RECORDING_QUEUE, RECORDING_TIMEOUT_S, finish, recording_message,
                                        reply_err)
from schemas import keys
from schemas import messages as m

log = logging.getLogger("bus_agent.gateway.gateway")


class RecordingServer:
    """Given: the host, the cycle (its ``recording`` method, if it has a flight recorder) and the
    gateway's ``stop``."""

    def __init__(self, host: str, cycle: Any, stop: threading.Event) -> None:
        self.host = host
        self._cycle = cycle
        self._stop = stop
        self._queries: queue.Queue[zenoh.Query] = queue.Queue(maxsize=RECORDING_QUEUE)

    def on_query(self, query: zenoh.Query) -> None:
        """Zenoh's callback: queue the query, or refuse it as busy when the queue is full."""
        try:
            self._queries.put_nowait(query)
        except queue.Full:
            reply_err(query, f"{self.host}: flight recorder busy: {RECORDING_QUEUE} requests are waiting")

    def run(self) -> None:
        """The ``gw-record`` thread, until ``stop``."""
        while not self._stop.is_set():
            try:
                query = self._queries.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._serve(query)
            except Exception as exc:  # keep serving; the querier gets the reason
                log.exception("gateway %s: recording query failed", self.host)
                reply_err(query, f"{self.host}: recording failed: {exc}")

    def _serve(self, query: zenoh.Query) -> None:
        try:
            payload: Any = query.payload
            req = m.RecordingRequest() if payload is None else m.decode(payload, m.RecordingRequest)
        except m.SchemaError as exc:
            reply_err(query, f"{self.host}: invalid recording_request: {exc}")
            return
        fetch = getattr(self._cycle, "recording", None)
        if fetch is None:
            reply_err(query, f"{self.host}: this agent has no flight recorder")
            return
        try:
            data = fetch(req.what, req.last_s, RECORDING_TIMEOUT_S)
        except LookupError as exc:
            reply_err(query, f"{self.host}: {exc}")
            return
        query.reply(keys.agent_recording(self.host), m.encode(recording_message(self.host, data)), encoding=MSGPACK)
        finish(query)
