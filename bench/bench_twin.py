"""drives-twin: time from start to ready, and CPU at rest, next to the bare processes it runs.

    python -m bench.bench_twin [--hosts 3,10,32] [--axes 2] [--rest-s 10] [--settle-s 3] [--cycle-us 1000] [--out FILE]

For each fleet size N (hosts of ``--axes`` simulated drives each), in the same run:

- **bare** (the baseline): a ``drives-router`` and N ``bus-agent --sim`` processes started at once,
  each connected straight to the router; ready when every agent printed its readiness line. This
  is what a person starting the parts by hand gets, without knowing whether the drives answer.
- **twin**: ``drives-twin --fleet`` for the same fleet (router, N agents with the fleet's axis
  names, a link relay per host, the twin's own supervisor); ready when it prints its ready line,
  which it does only once every expected drive answered on Zenoh (``ready_s`` from the start of
  the process; ``ready_s_reported`` is the twin's own figure, from ``Twin.start``, without the
  interpreter's start-up).

Then, ``--settle-s`` after ready, both rest for ``--rest-s`` seconds and the CPU time (user +
system, /proc) of every process of the tree (the agents' gateway children included) is summed:
the twin's own process (relays, supervisor, monitor) is reported apart. Ratios twin / bare. CPU
time is what stays meaningful on a loaded machine; the ready times are wall-clock and are not.
The machine's load average is recorded at the start, after every size and at the end. The run
stops the twin with SIGTERM and records its exit code, how long the stop took and how many of its
processes were left (0 expected). Needs no root.
"""

from __future__ import annotations

import os
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.common import ROOT, bench_parser, loadavg, proc_cpu_s, run_stamp, write_result
from bus_agent.sim.child import ChildProcess, descendants, free_port, running

READY_TIMEOUT_S = 600.0


def tree_cpu_s(roots: list[int]) -> dict[int, float]:
    """CPU seconds (user + system) of every process under ``roots``."""
    cpu = {}
    for r in roots:
        for p in {r, *descendants(r)}:
            try:
                cpu[p] = proc_cpu_s(p)
            except (OSError, ValueError, IndexError):
                pass
    return cpu


def rest_cpu(roots: list[int], rest_s: float, settle_s: float, own: int | None = None) -> dict[str, float]:
    """Percent of one core used by the trees under ``roots`` over ``rest_s``, ``settle_s`` after
    ready (start-up work done), and by ``own`` alone."""
    time.sleep(settle_s)
    before = tree_cpu_s(roots)
    t0 = time.monotonic()
    time.sleep(rest_s)
    after = tree_cpu_s(roots)
    dt = time.monotonic() - t0
    total = sum(after[p] - before[p] for p in after if p in before)
    out = {"cpu_pct_total": round(100 * total / dt, 1), "processes": len(after)}
    if own is not None and own in after and own in before:
        out["cpu_pct_twin_process"] = round(100 * (after[own] - before[own]) / dt, 1)
    return out


def run_bare(hosts: int, axes: int, rest_s: float, settle_s: float, cycle_us: int) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    procs = [ChildProcess("router", [sys.executable, "-m", "bus_agent.router", "--listen", ep],
                          ready_marker="drives-router ready")]
    procs += [ChildProcess(f"agent b{i}", [sys.executable, "-m", "bus_agent.cli", "--sim", str(axes), "--host", f"b{i}",
                                           "--connect", ep, "--mode", "client", "--cycle-us", str(cycle_us),
                                           "--log-level", "WARNING"], ready_marker="bus-agent ready")
              for i in range(hosts)]
    try:
        for p in procs:
            if not p.wait_ready(READY_TIMEOUT_S):
                raise RuntimeError(f"{p.name} not ready:\n{p.output()}")
        ready_s = time.monotonic() - t0
        return {"ready_s": round(ready_s, 3), **rest_cpu([p.pid for p in procs], rest_s, settle_s)}
    finally:
        for p in procs:
            p.stop(30)


def run_twin(hosts: int, axes: int, rest_s: float, settle_s: float, cycle_us: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="bench-twin-") as tmp:
        fleet = Path(tmp, "fleet.toml")
        fleet.write_text("".join(f'[hosts.t{i}]\naxes = [{", ".join(f"{chr(34)}a{j}{chr(34)}" for j in range(axes))}]\n'
                                 f"cycle_us = {cycle_us}\n" for i in range(hosts)))
        t0 = time.monotonic()
        p = ChildProcess("drives-twin", [sys.executable, "-m", "twin.cli", "--fleet", str(fleet), "--ready-timeout",
                                         str(READY_TIMEOUT_S)], ready_marker="drives-twin ready", stdin=True)
        try:
            if not p.wait_ready(READY_TIMEOUT_S):
                raise RuntimeError(f"drives-twin not ready:\n{p.output()}")
            ready_s = time.monotonic() - t0
            line = next(ln for ln in p.lines if ln.startswith("drives-twin ready"))
            reported = float(dict(w.split("=", 1) for w in line.split()[2:])["ready_s"])
            rest = rest_cpu([p.pid], rest_s, settle_s, own=p.pid)
            tree = descendants(p.pid)
            t1 = time.monotonic()
            p.popen.send_signal(signal.SIGTERM)
            code = p.popen.wait(120)
            stop_s = time.monotonic() - t1
            left = running(tree)
            return {"ready_s": round(ready_s, 3), "ready_s_reported": reported, **rest, "stop_s": round(stop_s, 3), "exit_code": code,
                    "left_after_stop": len(left)}
        finally:
            p.stop(60)


def run(sizes: list[int], axes: int, rest_s: float, settle_s: float, cycle_us: int) -> dict[str, Any]:
    start = loadavg()
    result: dict[str, Any] = {
        "benchmark": "bench_twin", "axes_per_host": axes, "rest_s": rest_s, "settle_s": settle_s,
        "cycle_us": cycle_us, "sizes": {},
    }
    for n in sizes:
        bare = run_bare(n, axes, rest_s, settle_s, cycle_us)
        twin = run_twin(n, axes, rest_s, settle_s, cycle_us)
        result["sizes"][str(n)] = {
            "bare": bare, "twin": twin,
            "ready_ratio": round(twin["ready_s"] / bare["ready_s"], 2),
            "cpu_ratio": round(twin["cpu_pct_total"] / bare["cpu_pct_total"], 2) if bare["cpu_pct_total"] else None,
            "loadavg_after": loadavg(),
        }
        print(f"{n} hosts: twin ready {twin['ready_s']:.2f} s (bare {bare['ready_s']:.2f} s), CPU at rest "
              f"{twin['cpu_pct_total']} % (bare {bare['cpu_pct_total']} %), load {os.getloadavg()[0]:.1f}",
              file=sys.stderr, flush=True)
    return {**result, **run_stamp(start)}


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_twin", __doc__)
    p.add_argument("--hosts", default="3,10,32", help="fleet sizes (hosts), comma-separated")
    p.add_argument("--axes", type=int, default=2, help="simulated drives per host")
    p.add_argument("--rest-s", type=float, default=10.0, help="how long to measure CPU at rest")
    p.add_argument("--settle-s", type=float, default=3.0, help="how long after ready the CPU measurement starts")
    p.add_argument("--cycle-us", type=int, default=1000, help="cycle period of every agent")
    args = p.parse_args(argv)
    result = run([int(x) for x in args.hosts.split(",")], args.axes, args.rest_s, args.settle_s, args.cycle_us)
    write_result(result, args.out)
    return 0


if __name__ == "__main__":
    os.chdir(ROOT)
    sys.exit(main())
