"""The two hand-offs between the gateway's threads: :class:`Feed` (cycle -> ``gw-publish``) and
:class:`Inbox` (Zenoh callbacks and the cycle's outcomes -> ``gw-command``).

Both only store and signal: whoever hands over never waits (the cycle thread least of all).
"""

from __future__ import annotations

import collections
import queue
import threading
import time
from typing import Callable, Iterable

from bus_agent import runtime as rt

#: Events waiting for the publisher at most (the oldest go first).
FEED_EVENTS_MAX = 8192


class Feed:
    """The latest snapshot and the events waiting to be published, and the publisher's wake-up.

    Written by the cycle thread (:meth:`on_snapshot`), the bridge reader (:meth:`on_events`) and
    ``gw-command`` (:meth:`emit`, :meth:`emit_all`); read by the publisher and, for the state of
    a drive, by the command path."""

    def __init__(self) -> None:
        self.latest: rt.CycleSnapshot | None = None
        #: (event, cycle, wall time ns) in order; the publisher pops from the left.
        self.events: collections.deque[tuple[rt.CycleEvent, int, int]] = collections.deque(maxlen=FEED_EVENTS_MAX)
        self.wake = threading.Event()
        #: The agent status is due now (set by :meth:`agent_status_now`, cleared by the publisher).
        self.agent_due = False

    def on_snapshot(self, snap: rt.CycleSnapshot) -> None:
        """Snapshot sink of the cycle. Cycle-safe: no I/O, no locks held for long."""
        self.latest = snap
        if snap.events:
            self.events.extend((ev, snap.cycle, snap.time_ns) for ev in snap.events)
        self.wake.set()

    def on_events(self, items: Iterable[tuple[rt.CycleEvent, int, int]]) -> None:
        """Events with the cycle number and wall time of the snapshot they came in, in order."""
        self.events.extend(items)
        self.wake.set()

    def emit(self, ev: rt.CycleEvent) -> None:
        """An event of the gateway's own (an outcome it decided, a lease, a conflict)."""
        self.emit_all((ev,))

    def emit_all(self, events: Iterable[rt.CycleEvent]) -> None:
        """Several events of the gateway's own, queued with one wake-up of the publisher."""
        snap = self.latest
        cycle, now_ns = (snap.cycle if snap else 0), time.time_ns()
        self.events.extend((ev, cycle, now_ns) for ev in events)
        self.wake.set()

    def agent_status_now(self) -> None:
        """Have the publisher put the agent status in its next pass, not at its period."""
        self.agent_due = True
        self.wake.set()

    def state(self, axis: str) -> str:
        """The CiA 402 state of ``axis`` in the latest snapshot ('unknown' before one)."""
        snap = self.latest
        if snap is not None:
            for d in snap.drives:
                if d.axis == axis:
                    return d.state
        return "unknown"


class Inbox:
    """Work for ``gw-command``: (function, args) items run there in order, and whether that
    thread is busy (:attr:`idle`, which the publisher waits for before each put)."""

    def __init__(self) -> None:
        q: queue.SimpleQueue[tuple[Callable[..., None], tuple]] = queue.SimpleQueue()
        #: Queue work that answers nobody waiting (timers, tokens, own status); any thread.
        self.put = q.put
        self.get = q.get
        self.empty = q.empty
        #: Set while ``gw-command`` has nothing to do.
        self.idle = threading.Event()
        self.idle.set()

    def work(self, item: tuple[Callable[..., None], tuple]) -> None:
        """Queue work that answers a querier (a command, a batch of outcomes), marking
        ``gw-command`` busy at once: the publish thread, woken by the same bridge message or
        status change, waits before its next put instead of taking the GIL from the replies
        while ``gw-command`` is still waking up."""
        self.idle.clear()
        self.put(item)
