"""Real-time scheduling of the agent's threads (Linux SCHED_FIFO).

With the cycle thread under SCHED_FIFO, every other thread of the cycle process that takes the
GIL (the management thread, the bridge threads) must run under SCHED_FIFO too, one level below:
a normal-priority thread preempted by other processes while it holds the GIL would hold the
real-time cycle thread back for a whole scheduler slice (priority inversion through the GIL).
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger(__name__)


def helper_priority(cycle_priority: int) -> int:
    """SCHED_FIFO priority for the cycle process's other GIL users (0 when the cycle has none)."""
    return max(1, cycle_priority - 1) if cycle_priority else 0


def set_thread_fifo(priority: int, what: str) -> bool:
    """Put the calling thread under SCHED_FIFO ``priority`` (0: leave it alone). Needs
    CAP_SYS_NICE; a refusal is logged and returns False (the thread keeps normal scheduling)."""
    if not priority:
        return False
    try:  # pid 0 = the calling thread on Linux
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (OSError, AttributeError, ValueError) as e:
        log.warning("SCHED_FIFO %d for %s refused: %s", priority, what, e)
        return False


# prctl(2) options (linux/prctl.h)
PR_SET_NAME = 15
PR_SET_TIMERSLACK = 29
_libc = None


def _prctl(option: int, arg: int | bytes) -> bool:
    global _libc
    try:
        if _libc is None:
            import ctypes
            import ctypes.util

            _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return _libc.prctl(option, arg, 0, 0, 0) == 0
    except (OSError, AttributeError, TypeError):
        return False


def name_thread(name: str) -> bool:
    """Give the calling thread its name in the kernel (``comm``, at most 15 bytes), so that ``top
    -H``, ``ps -L`` and /proc/<pid>/task/*/comm tell the agent's threads apart."""
    return _prctl(PR_SET_NAME, name.encode()[:15])


def set_timer_slack_ns(ns: int) -> bool:
    """Timer slack of the calling thread (default 50 us): how much later than asked the kernel may
    end its sleeps. The cycle thread asks for 1 ns, so its sleep wakes close to the deadline and
    the spin before it can stay short. Threads under SCHED_FIFO have no slack anyway."""
    return _prctl(PR_SET_TIMERSLACK, ns)
