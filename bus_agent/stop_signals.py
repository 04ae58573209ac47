"""SIGTERM and SIGINT as a stop request for a process's main loop, safe against signals in bursts.

A Python signal handler runs in the main thread between bytecodes, and a second signal can run
it again inside the first run. A handler that takes a lock (``threading.Event.set`` takes its
condition's lock) then deadlocks against itself: two stop signals close together (a forwarded
SIGTERM and a process-group kill, as ``timeout make demo`` sends) left ``bus-agent`` hanging
with no ordered stop. The handler here only appends to a list; :meth:`StopSignals.wait` looks at
it between short waits.
"""

from __future__ import annotations

import signal
import threading
import time
from types import FrameType
from typing import Callable

#: How often :meth:`StopSignals.wait` looks for a received signal (the stop's added latency).
POLL_S = 0.05


class StopSignals:
    """Installs handlers for ``signals`` (SIGTERM and SIGINT by default) that record them.

    ``stopped`` is true once a signal arrived or :meth:`request` was called (from any thread);
    :meth:`wait` blocks until then or a timeout. :meth:`restore` puts the previous handlers back
    (also on leaving a ``with`` block). Install from the main thread only (as ``signal`` requires).
    """

    def __init__(self, signals: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT),
                 on_signal: Callable[[int], None] | None = None) -> None:
        #: The signals received, in order (appended by the handler: no lock taken there).
        self.received: list[int] = []
        self._on_signal = on_signal
        self._requested = threading.Event()
        self._previous = {sig: signal.signal(sig, self._handler) for sig in signals}

    def _handler(self, signum: int, _frame: FrameType | None) -> None:
        self.received.append(signum)
        if self._on_signal is not None:
            self._on_signal(signum)  # must take no lock either

    def request(self) -> None:
        """A stop asked for by the program itself (thread-safe; not from a signal handler)."""
        self._requested.set()

    @property
    def stopped(self) -> bool:
        return bool(self.received) or self._requested.is_set()

    @property
    def signal_name(self) -> str | None:
        """The first signal received (``SIGTERM``), None when none."""
        return signal.Signals(self.received[0]).name if self.received else None

    def wait(self, timeout_s: float | None = None) -> bool:
        """Until a stop (True) or ``timeout_s`` (False; None: no timeout)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self.stopped:
            step = POLL_S if deadline is None else min(POLL_S, deadline - time.monotonic())
            if step <= 0:
                return False
            self._requested.wait(step)
        return True

    def restore(self) -> None:
        """The handlers that were installed before."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def __enter__(self) -> "StopSignals":
        return self

    def __exit__(self, *exc: object) -> None:
        self.restore()
