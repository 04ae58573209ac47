"""Supervisor benchmark: fleet-wide enable/disable and status fan-in, on loopback.

    .venv/bin/python -m bench.bench_supervisor                 # default: 4x16 and 32x32, short
    .venv/bin/python -m bench.bench_supervisor --sizes 4x16 --rounds 5
    .venv/bin/python -m bench.bench_supervisor --sizes 32x32 --per-process 8 --cycle-us 10000

For each size AxD (A agents of D simulated drives, ``--per-process`` agents per process, each
agent with its own Zenoh session, all through one router process):

- ``enable``: two-phase enable of every drive (``**``: one fan-out query per phase), and
  ``disable`` of every drive; per step the supervisor's wall time, the slowest drive's own time
  (``CommandReply.elapsed_s``: receipt to goal, i.e. the drive's transition cycles), and the
  difference: the supervisor's and the network's share (``overhead_s``); per enable the CPU
  time of each party (``cpu_ms``, and per thread name of the gateways and the supervisor) and
  the drive statuses the supervisor's ``Fleet`` took in while the enable ran (``statuses``);
- ``get_rtt_bare``: a bare zenoh get round trip in the same run (p50/p99) to a queryable in its
  own idle process, for scale; ``get_rtt_drive_status``: the same to one agent's status
  queryable (an agent process busy with its cycles);
- ``fanin`` (largest size): a watcher in its own process (a ``Fleet``) receives the status
  of every drive while all are enabled and disabled; it reports status messages received,
  state changes seen, sequence-number gaps (missed messages: must be 0) and its CPU time;
- ``departure`` (last, every size): one agents process is killed (SIGKILL, no clean-up) and the
  supervisor's ``Fleet`` times each of its agents' departure (liveliness token gone): the
  latency the system tests only bound generously.

Results go to ``bench/results/bench_supervisor.json`` and are printed. Flags: ``--sizes``,
``--rounds``, ``--per-process``, ``--cycle-us`` (default 5000 up to 64 drives, else 20000, so
that the simulated drives leave the supervisor and Zenoh a share of a 2-core machine: the
figures exclude the drives' own time, see :data:`CYCLE_US`), ``--sm-watchdog-s`` (default 5 s, so a
starved machine's late cycles do not drop simulated slaves), ``--gets``, ``--no-fanin``,
``--pin`` (the agents' processes on the last half of the CPUs, the supervisor, router, echo
and watcher on the first: the bare get is then measured away from the agents' load; on 2 CPUs
the agents of 4x16 at 1 kHz do not fit in one core, so it is not the default).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from schemas import keys
from supervisor.fleet import Fleet
from supervisor.results import CommandResult, Report
from bench.common import proc_cpu_s, thread_cpu_ns
from supervisor.testbed import Proc, spawn, start_agents, start_router

RESULTS = Path(__file__).resolve().parent / "results" / "bench_supervisor.json"
#: The simulated agents' cycle up to 64 drives. The figures are the supervisor's and Zenoh's share
#: (wall time minus the slowest drive's own time), but at 1 ms the 4x16 agents (64 simulated
#: drives, one process, their 4 gateway processes) took about a core and a half during an enable
#: and starved the supervisor and the router of the 2-core machine: at load 4-5, two alternating
#: pairs of runs gave an enable overhead of 80 and 71 ms at 1 ms, 38 and 40 ms at 5 ms (the
#: agents' process 84/69 -> 42/43 ms of CPU per enable).
CYCLE_US = 5000
#: Beyond 64 drives (1024 simulated drives must fit on 2 cores).
CYCLE_US_LARGE = 20000

WATCHER = r"""
import json, sys, threading, time
from supervisor.fleet import Fleet
ep, n_drives = sys.argv[1], int(sys.argv[2])
pki = sys.argv[3] if len(sys.argv) > 3 else None  # with a PKI the watcher is principal bench-watcher
changes = {}
lock = threading.Lock()
def on_status(st):
    with lock:
        key = (st.host, st.axis)
        last = changes.get(key)
        if last is None or last[0] != st.state:
            changes[key] = (st.state, (last[1] + 1) if last else 0)
def counts(f):
    with lock:
        return f.status_count, sum(v[1] for v in changes.values()), sum(f.missed().values())
with Fleet(connect=[ep], name="bench-watcher", pki=pki, identity="bench-watcher" if pki else None) as f:
    f.on("status", on_status)
    assert f.wait_until(lambda f: len(f.roster()) >= n_drives, 60), len(f.roster())
    print("watching", flush=True)
    for line in sys.stdin:  # mark, report, mark, report, ... until stdin closes
        cmd = line.strip()
        if cmd == "mark":
            t0, c0, (n0, s0, m0) = time.monotonic(), time.process_time(), counts(f)
            print("marked", flush=True)
        elif cmd == "report":
            time.sleep(0.5)  # let the last publications arrive
            t1, c1, (n1, s1, m1) = time.monotonic(), time.process_time(), counts(f)
            print(json.dumps({
                "drives_seen": len(f.drives()),
                "status_received": n1 - n0,
                "state_changes_seen": s1 - s0,
                "missed_by_seq": m1 - m0,
                "drives_with_gaps": sum(1 for v in f.missed().values() if v),
                "window_s": round(t1 - t0, 3),
                "cpu_s": round(c1 - c0, 6),
                "cpu_pct_of_one_core": round(100 * (c1 - c0) / (t1 - t0), 1),
            }), flush=True)
"""


class Watcher:
    """A watcher ``Fleet`` in its own process receiving every drive status (``WATCHER``):
    ``mark()`` opens a window, ``report()`` closes it and returns what arrived in it (messages,
    sequence gaps, the watcher's CPU by ``time.process_time``); windows may repeat."""

    def __init__(self, ep: str, total: int, pki: str | None = None) -> None:
        import subprocess

        from supervisor.testbed import _env

        self.proc = subprocess.Popen([sys.executable, "-c", WATCHER, ep, str(total), *([pki] if pki else [])],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=_env())
        self.pid = self.proc.pid
        if self._line() != "watching":
            self.close()
            raise RuntimeError(f"the watcher did not see {total} drives")

    def _line(self, cmd: str | None = None) -> str:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        if cmd is not None:
            self.proc.stdin.write(cmd + "\n")
            self.proc.stdin.flush()
        return self.proc.stdout.readline().strip()

    def mark(self) -> None:
        if self._line("mark") != "marked":
            raise RuntimeError("the watcher did not answer mark")

    def report(self) -> dict[str, Any]:
        return json.loads(self._line("report"))

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait(10)


ECHO = r"""
import json, signal, sys, threading, zenoh
conf = zenoh.Config.from_json5(json.dumps({"mode": "peer", "connect": {"endpoints": [sys.argv[1]]},
                                           "listen": {"endpoints": []}, "scouting": {"multicast": {"enabled": False}}}))
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
def on_query(q):
    with q:
        q.reply(q.key_expr, b"pong")
with zenoh.open(conf) as s:
    qb = s.declare_queryable("bench/echo", on_query)
    print("echo ready", flush=True)
    stop.wait()
    qb.undeclare()
"""


def pct(values: list[float], q: float) -> float:
    v = sorted(values)
    return v[min(len(v) - 1, int(round(q * (len(v) - 1))))]


def step_figures(res: CommandResult) -> dict[str, Any]:
    agent_max = max((r.elapsed_s for r in res.results if r.outcome != "missing"), default=0.0)
    return {
        "op": res.op, "drives": len(res.results), "ok": res.ok, "counts": res.counts(),
        "wall_s": round(res.elapsed_s, 6), "drive_max_s": round(agent_max, 6),
        "overhead_s": round(res.elapsed_s - agent_max, 6), "queries": 1,
    }


def report_figures(rep: Report) -> dict[str, Any]:
    steps = [step_figures(res) for _, res in rep.steps]
    return {"ok": rep.ok, "reason": rep.reason, "steps": steps,
            "wall_s": round(sum(s["wall_s"] for s in steps), 6),
            "overhead_s": round(sum(s["overhead_s"] for s in steps), 6)}


def get_rtt(session: zenoh.Session, key: str, n: int) -> dict[str, Any]:
    times = []
    errors = 0
    for _ in range(n):
        t0 = time.perf_counter()
        replies = list(session.get(key, timeout=2.0))
        if replies and replies[0].ok is not None:
            times.append(time.perf_counter() - t0)
        else:
            errors += 1
    if not times:
        return {"n": n, "errors": errors}
    return {"errors": errors, "n": n, "p50_ms": round(1e3 * statistics.median(times), 3), "p99_ms": round(1e3 * pct(times, 0.99), 3),
            "max_ms": round(1e3 * max(times), 3)}


#: Principals of a secure run (``run_size(pki=...)``): the router, the supervisor and the watcher
#: (agents are their host names, ``host_names``).
SECURE_PRINCIPALS = {"bench-router": "router", "bench-sup": "operator", "bench-watcher": "viewer"}


def host_names(n_agents: int) -> list[str]:
    return [f"b{i:02d}" for i in range(n_agents)]


def run_size(n_agents: int, n_drives: int, args: argparse.Namespace, fanin: bool,
             pki: str | None = None) -> dict[str, Any]:
    """One size on one transport: plain TCP, or with ``pki`` mutual TLS and the routers' ACL
    (the PKI must hold SECURE_PRINCIPALS and an agent certificate per host name). Without a PKI
    the bare get goes to an echo queryable; with one (its key is outside every role) it is left out."""
    total = n_agents * n_drives
    cycle_us = args.cycle_us or (CYCLE_US if total <= 64 else CYCLE_US_LARGE)
    router, ep = start_router(pki=pki, identity="bench-router")
    procs: list[Proc] = []
    hosts = host_names(n_agents)
    out: dict[str, Any] = {"transport": "tls+acl" if pki else "tcp", "agents": n_agents, "drives_per_agent": n_drives, "drives": total, "cycle_us": cycle_us,
                           "agents_per_process": args.per_process, "sm_watchdog_s": args.sm_watchdog_s,
                           "load_avg_1min_at_start": round(os.getloadavg()[0], 2)}
    pin = cpu_split(args.pin)
    try:
        t0 = time.monotonic()
        if pin:  # the agents (and their gateway processes) inherit the agents' CPUs
            os.sched_setaffinity(0, pin[1])
        try:
            for i in range(0, n_agents, args.per_process):
                procs.append(start_agents(hosts[i:i + args.per_process], n_drives, ep, cycle_us=cycle_us,
                                          sm_watchdog_s=args.sm_watchdog_s, ready_timeout_s=180, pki=pki))
        finally:
            if pin:  # this process (the supervisor), the router, the echo and the watcher share the rest
                os.sched_setaffinity(0, pin[0])
                pin_process(router.pid, pin[0])
        out["cpus_supervisor_agents"] = [sorted(c) for c in pin] if pin else None
        with Fleet(connect=[ep], name="bench-sup", pki=pki, identity="bench-sup" if pki else None) as fleet:
            assert fleet.wait_for_agents(n_agents, 60, drives=total), (len(fleet.hosts()), len(fleet.roster()))
            out["startup_s"] = round(time.monotonic() - t0, 2)
            cpu0 = proc_cpu_s(router.pid)
            if not pki:
                echo = spawn("echo", [sys.executable, "-c", ECHO, ep], ready_marker="echo ready")
                procs.append(echo)
                assert echo.wait_ready(30), echo.output()
                list(fleet.session.get("bench/echo", timeout=2.0))  # routes in place
                out["get_rtt_bare"] = get_rtt(fleet.session, "bench/echo", args.gets)
            out["get_rtt_drive_status"] = get_rtt(fleet.session, keys.drive_status(hosts[0], "axis0"), args.gets)
            t = time.perf_counter()
            replies = list(fleet.session.get(keys.ALL_DRIVE_STATUS, target=zenoh.QueryTarget.ALL,
                                             consolidation=zenoh.ConsolidationMode.NONE, timeout=10))
            out["status_fanout_get"] = {"replies": len(replies), "wall_ms": round(1e3 * (time.perf_counter() - t), 3)}
            rounds = []
            groups = {"router": [router.pid], "agents": [p.pid for p in procs if p.name.startswith("agents")]}
            groups["gateways"] = [c for pid in groups["agents"] for c in child_pids(pid)]
            threads_of = {"gateways": groups["gateways"], "supervisor": [os.getpid()]}
            for _ in range(args.rounds):
                cpu = {g: cpu_s(pids) for g, pids in groups.items()}
                by_thread = {g: threads_ns(pids) for g, pids in threads_of.items()}
                cpu["supervisor"] = time.process_time()
                n_status = fleet.status_count
                en = fleet.enable("**", timeout_s=10)
                cpu["supervisor"] = time.process_time() - cpu["supervisor"]
                n_status = fleet.status_count - n_status
                for g, pids in groups.items():
                    cpu[g] = cpu_s(pids) - cpu[g]
                by_thread = {g: _ms_delta(threads_ns(threads_of[g]), before) for g, before in by_thread.items()}
                dis = fleet.command("disable", "**", timeout_s=10)
                rounds.append({"enable": {**report_figures(en), "cpu_ms": {g: round(1e3 * v, 2) for g, v in cpu.items()},
                                          "cpu_ms_by_thread": by_thread, "statuses": n_status},
                               "disable": step_figures(dis)})
                if not (en.ok and dis.ok):
                    print(f"  round failed: {en.reason} {dis.failures[:3]}", file=sys.stderr)
            out["rounds"] = rounds
            ok_rounds = [r for r in rounds if r["enable"]["ok"] and r["disable"]["ok"]]
            if ok_rounds:
                out["enable_wall_s_median"] = statistics.median(r["enable"]["wall_s"] for r in ok_rounds)
                out["enable_overhead_s_median"] = statistics.median(r["enable"]["overhead_s"] for r in ok_rounds)
                # CPU time of each party during the enable: robust where wall-clock times are not
                # (a loaded machine), so it shows what a change costs or saves
                out["enable_cpu_ms_median"] = {g: round(statistics.median(r["enable"]["cpu_ms"][g] for r in ok_rounds), 2)
                                               for g in ok_rounds[0]["enable"]["cpu_ms"]}
                out["enable_statuses_median"] = statistics.median(r["enable"]["statuses"] for r in ok_rounds)
                out["enable_cpu_ms_by_thread_median"] = {
                    g: {t: round(statistics.median(r["enable"]["cpu_ms_by_thread"][g].get(t, 0.0) for r in ok_rounds), 2)
                        for t in ok_rounds[0]["enable"]["cpu_ms_by_thread"][g]}
                    for g in ok_rounds[0]["enable"]["cpu_ms_by_thread"]}
                out["disable_wall_s_median"] = statistics.median(r["disable"]["wall_s"] for r in ok_rounds)
                out["disable_overhead_s_median"] = statistics.median(r["disable"]["overhead_s"] for r in ok_rounds)
            if fanin:
                out["fanin"] = run_fanin(fleet, ep, total, pki)
            out["router_cpu_s"] = round(proc_cpu_s(router.pid) - cpu0, 3)
            out["departure"] = run_departure(fleet, procs[0], hosts[:args.per_process])
    finally:
        for p in procs:
            p.stop(timeout_s=60)
        router.stop()
    return out


def cpu_split(pin: bool) -> tuple[set[int], set[int]] | None:
    """(supervisor's CPUs, agents' CPUs) when pinning and there are at least two CPUs: the last
    half to the agents, so that their cycles do not starve the supervisor and Zenoh being
    measured (nor the other way round)."""
    cpus = sorted(os.sched_getaffinity(0))
    if not pin or len(cpus) < 2:
        return None
    half = len(cpus) // 2
    return set(cpus[:half]), set(cpus[half:])


def cpu_s(pids: list[int]) -> float:
    """CPU time of the processes' live threads (schedstat: ns, not the 10 ms ticks of /stat)."""
    return sum(sum(thread_cpu_ns(pid).values()) for pid in pids) / 1e9


def threads_ns(pids: list[int]) -> dict[str, int]:
    """CPU time (ns) per thread name over the processes ``pids`` (see ``thread_cpu_ns``)."""
    out: dict[str, int] = {}
    for pid in pids:
        for name, ns in thread_cpu_ns(pid).items():
            out[name] = out.get(name, 0) + ns
    return out


def _ms_delta(after: dict[str, int], before: dict[str, int]) -> dict[str, float]:
    """Per thread name, the CPU ms between two ``threads_ns`` readings (threads over 0.05 ms)."""
    delta = {t: (ns - before.get(t, 0)) / 1e6 for t, ns in after.items()}
    return {t: round(v, 2) for t, v in sorted(delta.items(), key=lambda kv: -kv[1]) if v >= 0.05}


def child_pids(pid: int) -> list[int]:
    """The child processes of ``pid`` (an agents process's gateway processes)."""
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(c) for c in f.read().split()]
    except OSError:
        return []


def pin_process(pid: int, cpus: set[int]) -> None:
    """Every thread of ``pid`` onto ``cpus`` (``sched_setaffinity`` on a pid moves one thread)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            os.sched_setaffinity(int(tid), cpus)
        except (ProcessLookupError, PermissionError):
            pass


def run_departure(fleet: Fleet, proc: Proc, hosts: list[str], timeout_s: float = 10.0) -> dict[str, Any]:
    """SIGKILL one agents process (no clean-up) and time each of its hosts' departure as the
    supervisor's Fleet reports it (its liveliness token vanishing)."""
    seen: dict[str, float] = {}
    done = threading.Event()

    def on_departure(host: str) -> None:
        if host in hosts and host not in seen:
            seen[host] = time.monotonic()
            if len(seen) == len(hosts):
                done.set()

    fleet.on("departure", on_departure)
    t0 = time.monotonic()
    proc.kill()
    done.wait(timeout_s)
    lat = sorted(seen.values())
    return {"killed_agents": len(hosts), "reported": len(seen), "timeout_s": timeout_s,
            "first_ms": round(1e3 * (lat[0] - t0), 1) if lat else None,
            "last_ms": round(1e3 * (lat[-1] - t0), 1) if lat else None}


def run_fanin(fleet: Fleet, ep: str, total: int, pki: str | None = None) -> dict[str, Any]:
    w = Watcher(ep, total, pki)
    try:
        w.mark()
        m0 = sum(fleet.missed().values())
        t0 = time.monotonic()
        en = fleet.enable("**", timeout_s=10)
        dis = fleet.command("disable", "**", timeout_s=10)
        active_s = time.monotonic() - t0
        body = w.report()
        body["commands_ok"] = en.ok and dis.ok
        # the same count in the commanding supervisor's own Fleet: equal gaps in two independent
        # subscribers mean the samples were lost upstream (publisher or router), not by a watcher
        body["supervisor_missed_by_seq"] = sum(fleet.missed().values()) - m0
        body["active_s"] = round(active_s, 3)
        return body
    finally:
        w.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="4x16,32x32", help="comma-separated AGENTSxDRIVES (default 4x16,32x32)")
    p.add_argument("--rounds", type=int, default=3, help="enable+disable rounds per size (default 3)")
    p.add_argument("--per-process", type=int, default=8, help="agents per process (default 8)")
    p.add_argument("--cycle-us", type=int, default=0,
                   help=f"agent cycle (default {CYCLE_US}, {CYCLE_US_LARGE} beyond 64 drives)")
    p.add_argument("--sm-watchdog-s", type=float, default=5.0,
                   help="simulated slaves' SM watchdog (default 5 s: a starved 2-core box must not drop slaves)")
    p.add_argument("--gets", type=int, default=200, help="bare get round trips to time (default 200)")
    p.add_argument("--no-fanin", action="store_true", help="skip the status fan-in watcher")
    p.add_argument("--pin", action="store_true",
                   help="split the CPUs: agents on the last half, supervisor/router/echo/watcher on the first")
    p.add_argument("--out", "--output", dest="output", default=str(RESULTS), help="JSON file")
    args = p.parse_args(argv)
    sizes = []
    for s in args.sizes.split(","):
        a, _, d = s.partition("x")
        sizes.append((int(a), int(d)))
    largest = max(sizes, key=lambda s: s[0] * s[1])
    result: dict[str, Any] = {"bench": "supervisor", "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                              "cpus": os.cpu_count(), "python": sys.version.split()[0], "pin": args.pin,
                              "loadavg_start": [round(x, 2) for x in os.getloadavg()], "sizes": []}
    for a, d in sizes:
        print(f"== {a} agents x {d} drives", flush=True)
        r = run_size(a, d, args, fanin=not args.no_fanin and (a, d) == largest)
        result["sizes"].append(r)
        print(json.dumps({k: v for k, v in r.items() if k != "rounds"}, indent=1), flush=True)
    result["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(json.dumps(result, indent=1) + "\n")
    print(f"written {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
