"""The cycle's timing: process-wide settings while the loop runs, and the wait before each deadline.

A mixin of :class:`bus_agent.cycle.cycle.Cycle` (cycle thread only). Drift-free deadlines are the
loop's (``Cycle._run``); here: sleep until the spin before the deadline (a ``select`` on the wake
eventfd and the trigger socket, so a remote group trigger ends it at once), then spin to the
deadline; the adaptive spin follows the sleep's overshoot. See docs/agent-cycle.md, "Timing".
"""

from __future__ import annotations

import gc
import os
import select
import sys

from bus_agent.cycle.base import SPIN_MARGIN_NS, SPIN_MIN_NS, SPIN_NS, SPIN_QUANTILE, STATS_WINDOW, CycleBase


class TimingMixin(CycleBase):
    """Process settings, the wait before each deadline and the adaptive spin of the :class:`Cycle`."""

    def _prepare_process(self) -> None:
        """Process-wide settings while the loop runs (restored when it ends); see docs/agent-cycle.md."""
        self._old_switch = sys.getswitchinterval()
        self._gc_was_enabled = gc.isenabled()
        if self.switch_interval_s:
            # A thread waiting for the GIL asks for it after this long (default 5 ms): the cycle
            # thread waits at most about this long when another thread holds the GIL.
            sys.setswitchinterval(self.switch_interval_s)
        if self.manage_gc:
            # No cyclic-GC pauses in the loop: move what exists to the permanent generation and
            # disable collection while running (reference counting still frees everything acyclic).
            gc.collect()
            gc.freeze()
            gc.disable()

    def _restore_process(self) -> None:
        if self.manage_gc:
            gc.unfreeze()
            if self._gc_was_enabled:
                gc.enable()
        if self.switch_interval_s:
            sys.setswitchinterval(self._old_switch)

    def _wait_until(self, deadline_ns: int) -> bool:
        """Sleep until the spin before ``deadline_ns``, then spin to it. True (at once, without
        spinning) when a remote trigger woke the sleep; a trigger during the spin waits for the
        cycle (at most the spin away)."""
        if self._armed or self.spin_at_rest or self._dc is not None:
            spin = self.spin_ns if self.spin_ns is not None else self._spin_auto_ns
        else:
            spin = 0  # every drive off and no SYNC0: nothing the period's jitter could move
        wake = deadline_ns - spin
        remaining = wake - self.clock_ns()
        if remaining > 0:
            if self._doze(remaining / 1e9):
                return True
            over = self._oversleep[self.cycles % STATS_WINDOW] = self.clock_ns() - wake
            if over > self._spin_auto_ns:  # late past the spin: more spin from the next cycle on
                self._spin_auto_ns = min(SPIN_NS, over + SPIN_MARGIN_NS)
        while self.clock_ns() < deadline_ns:
            pass
        return False

    def _doze(self, seconds: float) -> bool:
        """Sleep ``seconds``, or until ``trigger_group`` writes the wake eventfd (True). select's
        timeout has microsecond resolution, and the thread's 1 ns timer slack holds as for a sleep."""
        fd = self._wake_fd
        if fd < 0:
            self._sleep(seconds)
            # an injected sleep (tests, tools): a trigger queued meanwhile counts as a wake
            return self.express_reflex and bool(self._triggers)
        sock = self._trigger_sock
        ready = select.select((fd,) if sock is None else (fd, sock), (), (), seconds)[0]
        if not ready:
            # The socket was empty just now: the cycle need not look (a datagram arriving in the
            # spin or the cycle wakes the next sleep at once, which applies it then).
            self._socket_watched = True
            return False
        if fd in ready:
            try:
                os.eventfd_read(fd)
            except OSError:  # BlockingIOError: read by a wake before; EBADF: closed while stopping
                pass
        if sock is not None and sock in ready:
            self._take_trigger_datagrams()
        return True

    def _adapt_spin(self) -> None:
        """The adaptive spin (see SPIN_MIN_NS) from the overshoots of the last sleeps."""
        over = sorted(self._oversleep)
        q = over[min(len(over) - 1, int(len(over) * SPIN_QUANTILE))]
        self._spin_auto_ns = min(SPIN_NS, max(SPIN_MIN_NS, q + SPIN_MARGIN_NS))
