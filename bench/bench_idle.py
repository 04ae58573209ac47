"""Benchmark: the CPU of the idle demo agent (``bus-agent --sim 4``), per process and per thread,
and what the cycle's spin before each deadline costs, fixed against adaptive.

    python -m bench.bench_idle [--drives 4] [--seconds 20] [--rounds 2] [--out FILE]

1. ``demo``: ``bus-agent --sim N`` as ``make demo`` runs it (1 kHz, gateway in its child process,
   flight recorder on), listening on a free loopback port, scouting off, nobody commanding it. After
   2 s of warm-up, over ``--seconds``: the CPU of the agent process and of its gateway child (% of
   one core, from /proc/<pid>/stat), the agent's threads by name (/proc/<pid>/task/*/schedstat;
   the agent names its cycle and management threads), and the agent's own cycle statistics
   (agent status over Zenoh: period p99/max, overruns).
2. ``spin_fixed`` / ``spin_auto``: ``Cycle`` over ``SimBus(N)`` at 1 kHz in a process of its own,
   with the spin before each deadline fixed at 150 us (the default) or adaptive (``spin_ns =
   None``: the sleep's recent overshoot plus a margin, 30..150 us); they alternate in ``--rounds`` rounds.
   ``--rt-priority`` puts their cycle thread under SCHED_FIFO (root), as a real agent would run.
   Reported: the cycle thread's CPU (% of a core) and the period jitter |period - cycle|
   p99/p99.9/max of each, and their ratios (auto over fixed).

CPU time rather than wall-clock time, so the figures hold up under load; the load average is
recorded. No root needed. JSON is printed and written to bench/results/bench_idle.json.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import time
from array import array
from pathlib import Path

from bench.common import (ROOT, bench_parser, free_port, main_result, period_figures, proc_cpu_s, read_period_logs,
                          run_json, stop_process, task_cpu_ns, thread_cpu_ns)

#: The spin before each deadline: fixed 150 us, adaptive (the default), none.
SPIN_PHASES = ("spin_fixed", "spin_auto", "spin_none")



def _children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _agent_status(ep: str, host: str) -> dict:
    import zenoh

    from bus_agent.gateway.zenoh_config import make_zenoh_config
    from schemas import keys
    from schemas.messages import AgentStatus, decode

    with zenoh.open(make_zenoh_config("peer", connect=[ep])) as s:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            for r in s.get(keys.agent_status(host), timeout=2.0):
                if r.ok is not None:
                    st = decode(r.ok.payload.to_bytes(), AgentStatus)
                    return {"period_p99_us": st.period_p99_us, "period_max_us": st.period_max_us,
                            "overruns": st.overruns, "cycles": st.cycles}
            time.sleep(0.2)
    return {}


def run_demo(args) -> dict:
    """``bus-agent --sim N``, idle: CPU per process and thread over ``--seconds``."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    host = f"idle{os.getpid()}"
    agent = subprocess.Popen([sys.executable, "-m", "bus_agent.cli", "--sim", str(args.drives), "--host", host,
                              "--listen", ep, "--log-level", "WARNING"],
                             cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert agent.stdout is not None
        ready, _, _ = select.select([agent.stdout], [], [], 30)
        line = agent.stdout.readline() if ready else ""
        if not line.startswith("bus-agent ready"):
            raise RuntimeError(f"bus-agent did not get ready: {line!r}")
        time.sleep(2.0)  # warm-up: the gateway's first publications, the spin adapted
        kids = _children(agent.pid)
        t0 = time.monotonic()
        cpu0 = proc_cpu_s(agent.pid)
        kid0 = {k: proc_cpu_s(k) for k in kids}
        th0 = thread_cpu_ns(agent.pid)
        kth0 = {k: thread_cpu_ns(k) for k in kids}
        time.sleep(args.seconds)
        el = time.monotonic() - t0
        cpu = proc_cpu_s(agent.pid) - cpu0
        kid = sum(proc_cpu_s(k) - c for k, c in kid0.items())
        th1 = thread_cpu_ns(agent.pid)
        threads = {n: round(100 * (ns - th0.get(n, 0)) / 1e9 / el, 2) for n, ns in th1.items()}
        gw_threads: dict[str, float] = {}  # the gateway process's threads (Python's unnamed: "python")
        for k, before in kth0.items():
            for n, ns in thread_cpu_ns(k).items():
                gw_threads[n] = round(gw_threads.get(n, 0.0) + 100 * (ns - before.get(n, 0)) / 1e9 / el, 2)
        status = _agent_status(ep, host)
    finally:
        agent.send_signal(signal.SIGTERM)
        try:
            agent.wait(20)
        except subprocess.TimeoutExpired:
            stop_process(agent)
    return {"seconds": round(el, 1), "agent_cpu_pct": round(100 * cpu / el, 1),
            "gateway_cpu_pct": round(100 * kid / el, 1), "total_cpu_pct": round(100 * (cpu + kid) / el, 1),
            "threads_cpu_pct": dict(sorted(threads.items(), key=lambda kv: -kv[1])),
            "gateway_threads_cpu_pct": dict(sorted(gw_threads.items(), key=lambda kv: -kv[1])), "cycle_stats": status}


def phase_spin(args) -> dict:
    """Cycle over SimBus at 1 kHz for ``--seconds`` with the spin fixed or adaptive."""
    from bus_agent.bus.sim_bus import SimBus
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import SPIN_NS, Cycle

    cfg = AgentConfig(host="idle", sim_drives=args.drives, cycle_us=1000)
    n = int(args.seconds * 1000)
    cyc = Cycle(SimBus(args.drives), cfg, record_periods=n + 2000, rt_priority=args.rt_priority)
    cyc.spin_ns = {"spin_fixed": SPIN_NS, "spin_auto": None, "spin_none": 0}[args.phase]
    cyc.spin_at_rest = True  # the spin itself: its drives are off (the demo spins only while one is on)
    cyc.start()
    try:
        time.sleep(1.0)  # warm-up: the adaptive spin has measured its first sleeps
        assert cyc.thread is not None and cyc.thread.native_id is not None
        tid = cyc.thread.native_id
        first, t0, ns0 = cyc.period_log_len, time.monotonic(), task_cpu_ns(tid)
        while cyc.period_log_len - first < n and time.monotonic() - t0 < args.seconds * 3 + 10:
            time.sleep(0.05)
        el, ns, last = time.monotonic() - t0, task_cpu_ns(tid) - ns0, cyc.period_log_len
        spin = cyc.timing.spin_auto_ns if cyc.spin_ns is None else cyc.spin_ns
    finally:
        cyc.stop()
    periods = array("q", cyc.period_log[first:last]) if cyc.period_log is not None else array("q")
    with open(args.log_file, "wb") as f:
        periods.tofile(f)
    return {"cycles": last - first, "seconds": round(el, 2), "cpu_ns": ns, "spin_us_at_end": spin / 1000}


def work_per_cycle(drives: int, reps: int = 9, ticks: int = 1000) -> dict:
    """What one idle cycle costs without any waiting: ``Cycle.tick()`` over ``SimBus(drives)`` as
    the demo runs it (recorder on, snapshots to a sink), and the simulated bus's exchange (the
    drive models) alone; thread CPU time, minimum of ``reps`` runs (robust under load). Hot
    caches: the loop's real cost per cycle is higher by its wake-up and cold caches."""
    from bus_agent.bus.sim_bus import SimBus
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import Cycle

    bus = SimBus(drives)
    cyc = Cycle(bus, AgentConfig(host="idle", sim_drives=drives), manage_gc=False, switch_interval_s=None)
    cyc.snapshot_sink = lambda snap: None
    cyc.open()
    try:
        for _ in range(300):
            cyc.tick()

        def run(fn) -> float:
            t0 = time.thread_time_ns()
            for _ in range(ticks):
                fn()
            return (time.thread_time_ns() - t0) / ticks / 1000

        # interleaved, so that both minima come from the same minutes of a VM whose speed varies
        tick_us = exchange_us = float("inf")
        for _ in range(reps):
            tick_us = min(tick_us, run(cyc.tick))
            exchange_us = min(exchange_us, run(bus.exchange))
        tick_us, exchange_us = round(tick_us, 1), round(exchange_us, 1)
    finally:
        cyc.stop(ordered=False)
    return {"tick_us": tick_us, "sim_exchange_us": exchange_us, "cycle_beyond_sim_us": round(tick_us - exchange_us, 1),
            "tick_pct_at_1khz": round(tick_us / 10, 1), "recorder": cyc.recorder is not None}


def _spin_rounds(args) -> dict:
    import tempfile

    phases = SPIN_PHASES
    parts: dict[str, list[dict]] = {p: [] for p in phases}
    periods: dict[str, list[int]] = {p: [] for p in phases}
    with tempfile.TemporaryDirectory(prefix="bench-idle-") as tmp:
        for r in range(args.rounds):
            for name in phases:
                print(f"bench_idle: round {r + 1}/{args.rounds} {name} ({args.seconds:g} s)...", file=sys.stderr,
                      flush=True)
                log_file = os.path.join(tmp, f"{name}-{r}")
                parts[name].append(run_json(
                    [sys.executable, "-m", "bench.bench_idle", "--phase", name, "--drives", str(args.drives),
                     "--seconds", str(args.seconds), "--log-file", log_file, "--rt-priority", str(args.rt_priority)],
                    f"phase {name}", args.seconds * 4 + 60))
                periods[name] += read_period_logs([log_file])
    out: dict = {}
    for name in phases:
        el = sum(x["seconds"] for x in parts[name])
        out[name] = {"cycles": sum(x["cycles"] for x in parts[name]), "seconds": round(el, 2),
                     "cycle_cpu_pct": round(100 * sum(x["cpu_ns"] for x in parts[name]) / 1e9 / el, 1),
                     "spin_us_at_end": [x["spin_us_at_end"] for x in parts[name]],
                     **period_figures(periods[name], 1_000_000)}
    fixed = out["spin_fixed"]
    out["ratios"] = {}
    for name in ("auto", "none"):
        other = out[f"spin_{name}"]
        out["ratios"].update({f"cpu_{name}_over_fixed": round(other["cycle_cpu_pct"] / fixed["cycle_cpu_pct"], 2),
                              **{f"jitter_{q}_{name}_over_fixed": (round(other["jitter_us"][q] / fixed["jitter_us"][q], 2)
                                                                   if fixed["jitter_us"][q] else None)
                                 for q in ("p99", "p999", "max")}})
    return out


def run(args) -> dict:
    load_start = list(os.getloadavg())
    print(f"bench_idle: bus-agent --sim {args.drives}, idle ({args.seconds:g} s)...", file=sys.stderr, flush=True)
    demo = run_demo(args)
    spin = _spin_rounds(args)
    work = work_per_cycle(args.drives)
    return {"drives": args.drives, "seconds": args.seconds, "rounds": args.rounds, "rt_priority": args.rt_priority,
            "demo": demo, "spin": spin, "work": work,
            "loadavg_start": load_start, "loadavg": list(os.getloadavg()), "cpus": os.cpu_count(),
            "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_idle", __doc__)
    p.add_argument("--drives", type=int, default=4)
    p.add_argument("--seconds", type=float, default=20.0, help="seconds measured per phase (default 20)")
    p.add_argument("--rounds", type=int, default=2, help="spin phases alternate in this many rounds (default 2)")
    p.add_argument("--rt-priority", type=int, default=0,
                   help="SCHED_FIFO priority of the cycle thread in the spin phases (default 0, as the demo)")
    p.add_argument("--phase", choices=SPIN_PHASES, help=argparse.SUPPRESS)
    p.add_argument("--log-file", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.phase:
        print(json.dumps(phase_spin(args)), flush=True)
        return 0
    return main_result("bench_idle", lambda: run(args), args.out)


if __name__ == "__main__":
    sys.exit(main())
