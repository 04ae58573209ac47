"""Children of the test beds and of drives-twin die with the process that started them
(bus_agent/sim/child.py: setpriv --pdeathsig), also when they were started from a thread that
has ended since (the kernel's parent-death signal follows the forking *thread*)."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

from bus_agent.sim.child import ChildProcess, running, wait_for

PARENT = '''
import sys, threading
from bus_agent.sim.child import ChildProcess
kept = [ChildProcess("main", ["sleep", "300"])]
t = threading.Thread(target=lambda: kept.append(ChildProcess("thread", ["sleep", "301"])))
t.start()
t.join()
print("children", kept[0].pid, kept[1].pid, "thread", t.native_id, flush=True)
sys.stdin.read()
'''


def test_children_outlive_their_spawning_thread_but_not_their_parent():
    parent = ChildProcess("parent", [sys.executable, "-c", PARENT], ready_marker="children", stdin=True)
    try:
        parent.expect_ready(60)
        words = next(ln for ln in parent.lines if ln.startswith("children")).split()
        kids, tid = {int(words[1]), int(words[2])}, int(words[4])
        # the thread that asked for the second child has ended (gone from the parent's tasks) ...
        wait_for(lambda: not Path(f"/proc/{parent.pid}/task/{tid}").exists(), 30, "the spawning thread's end")
        assert running(kids) == kids  # ... and both children still run
        os.kill(parent.pid, signal.SIGKILL)  # no handler, no clean-up: only the kernel acts
        wait_for(lambda: not running(kids), 20, f"the children of the SIGKILLed parent gone ({running(kids)})")
    finally:
        parent.kill()
