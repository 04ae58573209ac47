"""Command hop stamps (bus_agent.hops), the gateway process's scheduling of zenoh's threads and
of gw-publish, and the remembered axes of a command key."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

from bus_agent import hops
from bus_agent.gateway.publisher import PublishPriority
from bus_agent.gateway.requests import axes_in_key
from schemas import keys
from tests.conftest import require_root

ROOT = Path(__file__).resolve().parents[2]


def _run(code: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, capture_output=True, text=True,
                          timeout=60, env={**os.environ, **(env or {})})


def test_rounds_and_breakdown_place_each_hop_after_its_rounds_start():
    ms = 1_000_000
    stamps = [(0, "gw.query"),                       # before any round: ignored
              (10 * ms, "cl.send.enable"), (11 * ms, "gw.query"), (13 * ms, "gw.reply"), (14 * ms, "gw.reply"),
              (15 * ms, "cl.done.enable"), (16 * ms, "gw.finish"),   # after the round's end: ignored
              (20 * ms, "cl.send.enable"), (23 * ms, "gw.query"), (24 * ms, "gw.reply"), (25 * ms, "gw.reply"),
              (26 * ms, "gw.reply"), (29 * ms, "cl.done.enable"),
              (30 * ms, "cl.send.enable"), (31 * ms, "gw.query")]    # no end: dropped
    rounds = hops.rounds(stamps, "cl.send.enable", "cl.done.enable")
    assert rounds == [{"gw.query": [1.0], "gw.reply": [3.0, 4.0], "cl.done.enable": [5.0]},
                      {"gw.query": [3.0], "gw.reply": [4.0, 5.0, 6.0], "cl.done.enable": [9.0]}]
    table = hops.breakdown(rounds)
    assert list(table) == ["gw.query", "gw.reply", "cl.done.enable"]   # in the order of their first stamp
    assert table["gw.reply"] == {"first_ms": 4.0, "last_ms": 6.0, "per_round": 2.5}


def test_stamps_are_off_by_default_and_written_per_process_when_asked(tmp_path):
    code = """
        from bus_agent import hops
        hops.stamp("a"); hops.stamp("b")
        print(hops.ENABLED)
    """
    off = _run(code, {hops.ENV: ""})
    assert off.returncode == 0 and off.stdout.strip() == "False", off.stderr
    assert list(tmp_path.iterdir()) == []
    on = _run(code, {hops.ENV: str(tmp_path)})
    assert on.returncode == 0 and on.stdout.strip() == "True", on.stderr
    stamps = hops.read(str(tmp_path))
    assert [h for _, h in stamps] == ["a", "b"] and stamps[0][0] <= stamps[1][0]


def test_zenoh_threads_are_put_under_sched_fifo():
    require_root()
    out = _run("""
        import os, time, zenoh
        from bus_agent.gateway.child import ZENOH_THREADS, zenoh_threads_fifo
        from bus_agent.gateway.zenoh_config import make_zenoh_config
        s = zenoh.open(make_zenoh_config("peer"))
        seen, deadline = set(), time.monotonic() + 10
        # zenoh names its threads after they start: scanned again until those named are all done
        while True:
            zenoh_threads_fifo(3, seen)
            rows = []
            for tid in os.listdir("/proc/self/task"):
                name = open(f"/proc/self/task/{tid}/comm").read().strip()
                fifo = os.sched_getscheduler(int(tid)) == os.SCHED_FIFO
                rows.append((name, fifo, os.sched_getparam(int(tid)).sched_priority if fifo else 0))
            named = [r for r in rows if r[0].startswith(ZENOH_THREADS)]
            if (len(named) >= 2 and all(r[1] for r in named)) or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        for row in rows:
            print(*row)
        s.close()
    """)
    assert out.returncode == 0, out.stderr
    threads = [line.split() for line in out.stdout.splitlines()]
    zenoh_threads = [ln for ln in threads if ln[0].startswith(("app-", "acc-", "tx-", "rx-", "net-"))]
    assert len(zenoh_threads) >= 2 and all(ln[1:] == ["True", "3"] for ln in zenoh_threads), threads
    assert all(ln[1] == "False" for ln in threads if ln not in zenoh_threads), threads  # Python's own: untouched


def test_publish_pass_runs_under_normal_scheduling_and_waits_under_sched_fifo():
    require_root()
    priority = PublishPriority(2, "h1")
    seen: list[int] = []

    def thread() -> None:
        from bus_agent.cycle.realtime import set_thread_fifo

        priority.fifo = set_thread_fifo(2, "test")
        seen.append(os.sched_getscheduler(0))
        priority.to_normal()   # after the alarms of a pass
        seen.append(os.sched_getscheduler(0))
        priority.to_fifo()    # before waiting for the next snapshot
        seen.append(os.sched_getscheduler(0))

    t = threading.Thread(target=thread)
    t.start()
    t.join(10)
    assert seen == [os.SCHED_FIFO, os.SCHED_OTHER, os.SCHED_FIFO]
    assert priority.normal is False


def test_axes_in_key_is_remembered_per_key_op_and_principal():
    axes = ("x", "y", "z")
    for _ in range(2):  # the second time from memory: the same answers
        assert axes_in_key(keys.drive_cmd("h1", "*", "enable"), "h1", axes) == axes
        assert axes_in_key(keys.drive_cmd("h1", "y", "enable"), "h1", axes) == ("y",)
        assert axes_in_key(keys.drive_cmd("h1", "*", "enable"), "h1", axes, op="disable") == ()
        assert axes_in_key(keys.drive_cmd("h1", "*", "enable"), "h1", list(axes), op="enable") == axes
        assert axes_in_key(keys.drive_cmd("h1", "*", "enable", "alice"), "h1", axes) == ()
        assert axes_in_key(keys.drive_cmd("h1", "*", "enable", "alice"), "h1", axes, principal="*") == axes
        assert axes_in_key(keys.drive_cmd("h1", "*", "enable"), "h2", axes) == ()


def test_reply_keys_are_the_command_keys_asked():
    from bus_agent.gateway.requests import reply_key

    for _ in range(2):  # the second time from memory
        assert reply_key("h1", "x", "enable", None) == keys.drive_cmd("h1", "x", "enable")
        assert reply_key("h1", "x", "enable", "alice") == keys.drive_cmd("h1", "x", "enable", "alice")
        assert reply_key("h1", "", "nmt", None) == keys.agent_cmd("h1", "nmt")
        assert reply_key("h1", "", "nmt", "alice") == keys.agent_cmd("h1", "nmt", "alice")
