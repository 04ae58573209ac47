"""The Fleet's events: listeners and the dispatcher thread they run on.

Zenoh callbacks only enqueue (:meth:`FleetEvents.emit`); listeners run on this part's own thread,
so they may call back into the Fleet (never on a Zenoh thread, where that could deadlock).
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any, Callable

log = logging.getLogger("supervisor.fleet")

Listener = Callable[..., None]

#: The events a Fleet emits, with what their listeners get.
EVENTS = ("arrival", "departure", "status", "agent", "lease_lost")


class FleetEvents:
    """Listeners per event, a queue, and the dispatcher thread draining it (``name``: the
    supervisor's, for the thread's name and the log)."""

    def __init__(self, name: str) -> None:
        self._name = name
        self._lock = threading.Lock()
        self._listeners: dict[str, list[Listener]] = {}
        self._queue: queue.SimpleQueue[tuple[str, tuple[Any, ...]] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None

    def on(self, event: str, fn: Listener) -> None:
        """Register ``fn`` for one of :data:`EVENTS` (ValueError otherwise)."""
        if event not in EVENTS:
            raise ValueError(f"unknown event {event!r}")
        with self._lock:
            self._listeners.setdefault(event, []).append(fn)

    def emit(self, event: str, *args: Any) -> None:
        """Queue ``event`` for its listeners (nothing when it has none). Never blocks."""
        if self._listeners.get(event):
            self._queue.put((event, args))

    def start(self) -> None:
        self._thread = threading.Thread(target=self._dispatch, name=f"fleet-{self._name}-events", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the dispatcher once the events queued before have run."""
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _dispatch(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            event, args = item
            for fn in list(self._listeners.get(event, ())):
                try:
                    fn(*args)
                except Exception:
                    log.exception("supervisor %s: %s listener failed", self._name, event)
