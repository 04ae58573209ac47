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
