"""What every simulator process (``ecat-sim``, ``canopen-sim``) does the same way at start: its
``--rt-priority`` and ``--log-level`` options, logging to stderr, and SCHED_FIFO for its loop
(:func:`bus_agent.cycle.realtime.set_thread_fifo`: a refusal is logged, the loop runs anyway).
"""

from __future__ import annotations

import argparse
import logging
import sys

from bus_agent.cycle.realtime import set_thread_fifo


def add_options(p: argparse.ArgumentParser, loop: str) -> None:
    """``--rt-priority N`` (SCHED_FIFO for ``loop``, 0: normal scheduling) and ``--log-level``."""
    p.add_argument("--rt-priority", type=int, default=0,
                   help=f"run the {loop} SCHED_FIFO at this priority (1..99; 0: normal scheduling)")
    p.add_argument("--log-level", default="WARNING")


def start_logging(args: argparse.Namespace) -> None:
    """Log records of ``--log-level`` and above to stderr, with time, level and logger."""
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def enter_rt(args: argparse.Namespace, loop: str) -> bool:
    """The calling thread (the one that runs ``loop``) under SCHED_FIFO ``--rt-priority``."""
    return set_thread_fifo(args.rt_priority, loop)
