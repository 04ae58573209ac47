"""What security costs: plain TCP against mutual TLS with the routers' ACL, in the same run.

    .venv/bin/python -m bench.bench_security                        # 50 rounds of 1x16 enable, 32x32 fan-in, 12 windows
    .venv/bin/python -m bench.bench_security --quick                # 20 rounds, 4x16 fan-in, 6 windows
    .venv/bin/python -m bench.bench_security --rounds 50 --fanin 8x32 --fanin-rounds 12   # run_all's row

On loopback, with a router process, agents on simulated drives in their own processes and a
supervisor ``Fleet``, each plain (tcp) and secure (tls: mutual TLS, the router's ACL, the
authenticated command keys). Both stacks are up at once and rounds alternate between them (tcp
then tls, tls then tcp, ...), so the load swings of a shared machine hit both alike:

- ``enable``: one agent of 16 drives per stack, ``--rounds`` rounds: a two-phase enable of every
  drive (the supervisor's wall time, p50 and p99, and the share beyond the drives' own
  transition time), then a disable;
- ``fanin``: ``--fanin`` drives per stack, each with a watcher ``Fleet`` in its own process
  receiving every drive status; ``--fanin-rounds`` windows, each while every drive is enabled
  and disabled: messages received and missed (sequence gaps: must be 0 on both), and CPU time
  per message read in nanoseconds from /proc/<pid>/task/*/schedstat (not wall time, not 10 ms
  ticks): the watcher's, by thread name (``python``: the Python callbacks; ``rx``, ``tx``,
  ``net``, ``app``: zenoh's runtime, where TLS records are decrypted), and the router's.

Ratios are tls / tcp: of the per-transport medians over the windows (the target), of their
minima (min-of-N), and the p10-p90 spread of the paired per-window ratios. Target: at most
1.2 x on the enable wall time p50 and on the watcher's CPU per message, and no message missed.
The machine's load is recorded with every run. Results: ``bench/results/bench_security.json``.
The PKI is made fresh in a temporary directory (``drives-pki``'s code, in-process).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import statistics
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from bench.bench_supervisor import SECURE_PRINCIPALS, Watcher, host_names, report_figures
from bench.common import bench_parser, loadavg, percentile, run_stamp, thread_cpu_ns, write_result
from bus_agent.security import pki as pki_mod
from supervisor.fleet import Fleet
from supervisor.testbed import Proc, start_agents, start_router

TARGET_RATIO = 1.2


def make_pki(d: Path, n_agents: int) -> None:
    pki_mod.init(d)
    for name, role in SECURE_PRINCIPALS.items():
        pki_mod.issue(d, name, [role])
    for host in host_names(n_agents):
        pki_mod.issue(d, host, ["agent"])


@dataclass
class Bed:
    """One stack: a router and agents in their own processes, a supervisor Fleet, maybe a watcher."""

    fleet: Fleet
    router_pid: int
    watcher: Watcher | None = None


@contextlib.contextmanager
def bed(pki: str | None, n_agents: int, n_drives: int, *, per_process: int = 8, sm_watchdog_s: float = 5.0,
        watch: bool = False) -> Iterator[Bed]:
    """A router, ``n_agents`` agents of ``n_drives`` each (``per_process`` to a process), a Fleet
    and with ``watch`` a watcher process: plain (tcp) or secure (``pki``: tls, ACL)."""
    total = n_agents * n_drives
    router, ep = start_router(pki=pki, identity="bench-router")
    procs: list[Proc] = []
    hosts = host_names(n_agents)
    try:
        for i in range(0, n_agents, per_process):
            procs.append(start_agents(hosts[i:i + per_process], n_drives, ep, cycle_us=1000 if total <= 64 else 20000,
                                      sm_watchdog_s=sm_watchdog_s, ready_timeout_s=180, pki=pki))
        with Fleet(connect=[ep], name="bench-sup", pki=pki, identity="bench-sup" if pki else None) as fleet:
            assert fleet.wait_for_agents(n_agents, 60, drives=total), (len(fleet.hosts()), len(fleet.roster()))
            watcher = Watcher(ep, total, pki) if watch else None
            try:
                yield Bed(fleet, router.pid, watcher)
            finally:
                if watcher is not None:
                    watcher.close()
    finally:
        for proc in procs:
            proc.stop(timeout_s=60)
        router.stop()


def alternating(i: int, pair: tuple[tuple[str, Bed], tuple[str, Bed]]) -> tuple[tuple[str, Bed], ...]:
    """tcp then tls in even rounds, tls then tcp in odd ones: neither always goes first."""
    return pair if i % 2 == 0 else pair[::-1]


def enable_rounds(pki: str, rounds: int, n_drives: int = 16) -> dict[str, Any]:
    """Both stacks up at once, rounds alternating between them: a load swing on the shared
    machine hits both alike. Per round: a two-phase enable of every drive (the supervisor's wall
    time, and beyond the drives' own transition time), then a disable."""
    walls: dict[str, list[float]] = {"tcp": [], "tls": []}
    over: dict[str, list[float]] = {"tcp": [], "tls": []}
    failed = {"tcp": 0, "tls": 0}
    with bed(None, 1, n_drives) as tcp, bed(pki, 1, n_drives) as tls:
        for i in range(rounds):
            for name, b in alternating(i, (("tcp", tcp), ("tls", tls))):
                rep = b.fleet.enable("**", timeout_s=10)
                dis = b.fleet.command("disable", "**", timeout_s=10)
                if not (rep.ok and dis.ok):
                    failed[name] += 1
                    continue
                fig = report_figures(rep)
                walls[name].append(fig["wall_s"])
                over[name].append(fig["overhead_s"])
    out: dict[str, Any] = {"drives": n_drives, "rounds": rounds, "load_avg_1min_at_end": round(os.getloadavg()[0], 2)}
    for name in ("tcp", "tls"):
        w, o = sorted(walls[name]), sorted(over[name])
        out[name] = {"rounds_ok": len(w), "failed": failed[name],
                     "wall_ms_p50": round(1e3 * statistics.median(w), 3) if w else None,
                     "wall_ms_p99": round(1e3 * percentile(w, 0.99), 3) if w else None,
                     "overhead_ms_p50": round(1e3 * statistics.median(o), 3) if o else None}
    return out


def _delta(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    return {k: v - before.get(k, 0) for k, v in after.items() if v - before.get(k, 0) > 0}


def fanin_round(b: Bed) -> dict[str, Any]:
    """One window of the watcher while every drive is enabled and disabled: messages, gaps, and
    CPU in ns (the watcher's threads by name, the router's process) read from /proc."""
    assert b.watcher is not None
    w0, r0 = thread_cpu_ns(b.watcher.pid), sum(thread_cpu_ns(b.router_pid).values())
    b.watcher.mark()
    en = b.fleet.enable("**", timeout_s=10)
    dis = b.fleet.command("disable", "**", timeout_s=10)
    body = b.watcher.report()
    threads = _delta(thread_cpu_ns(b.watcher.pid), w0)
    n = body["status_received"]
    body.update(commands_ok=en.ok and dis.ok, failure=None if en.ok and dis.ok else
                str(en.reason if not en.ok else dis.failures[:2])[:300], watcher_threads_ns=threads,
                watcher_cpu_us_per_msg=round(sum(threads.values()) / 1e3 / n, 3) if n else None,
                router_cpu_us_per_msg=round((sum(thread_cpu_ns(b.router_pid).values()) - r0) / 1e3 / n, 3) if n else None)
    return body


def fanin_rounds(pki: str, n_agents: int, n_drives: int, rounds: int, **bed_args: Any) -> dict[str, list[dict[str, Any]]]:
    """Both stacks of ``n_agents`` x ``n_drives`` up at once, each with its watcher; ``rounds``
    fan-in windows alternating between them."""
    out: dict[str, list[dict[str, Any]]] = {"tcp": [], "tls": []}
    with bed(None, n_agents, n_drives, watch=True, **bed_args) as tcp, \
            bed(pki, n_agents, n_drives, watch=True, **bed_args) as tls:
        for i in range(rounds):
            for name, b in alternating(i, (("tcp", tcp), ("tls", tls))):
                out[name].append(fanin_round(b))
    return out


def _q(values: list[float], q: float) -> float | None:
    return round(percentile(sorted(values), q), 3) if values else None


def _ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 3) if a is not None and b else None


def fanin_summary(fanin: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """Per transport: CPU per message (median, min), messages and gaps, and where the watcher's
    CPU went (ns per message by thread name, over all rounds); tls / tcp ratios of the medians,
    of the minima, and the spread (p10, p90) of the per-round ratios (round i tls / round i tcp)."""
    out: dict[str, Any] = {}
    for t, rows in fanin.items():
        ok = [r for r in rows if r["commands_ok"] and r["watcher_cpu_us_per_msg"] is not None]
        msgs = sum(r["status_received"] for r in ok)
        threads: dict[str, int] = {}
        for r in ok:
            for k, v in r["watcher_threads_ns"].items():
                threads[k] = threads.get(k, 0) + v
        w = [r["watcher_cpu_us_per_msg"] for r in ok]
        rt = [r["router_cpu_us_per_msg"] for r in ok]
        out[t] = {"rounds_ok": len(ok), "rounds_failed": len(rows) - len(ok),
                  "messages_per_round_p50": _q([r["status_received"] for r in ok], 0.5),
                  "missed_by_seq": sum(r["missed_by_seq"] for r in rows),
                  "watcher_cpu_us_per_msg_p50": _q(w, 0.5), "watcher_cpu_us_per_msg_min": _q(w, 0.0),
                  "router_cpu_us_per_msg_p50": _q(rt, 0.5),
                  "watcher_ns_per_msg_by_thread": {k: round(v / msgs) for k, v in sorted(threads.items())} if msgs else {}}
    tcp, tls = out["tcp"], out["tls"]
    paired = [b["watcher_cpu_us_per_msg"] / a["watcher_cpu_us_per_msg"] for a, b in zip(fanin["tcp"], fanin["tls"])
              if a["watcher_cpu_us_per_msg"] and b["watcher_cpu_us_per_msg"]]
    out["watcher_cpu_per_msg_ratio"] = _ratio(tls["watcher_cpu_us_per_msg_p50"], tcp["watcher_cpu_us_per_msg_p50"])
    out["watcher_cpu_per_msg_ratio_min_of_n"] = _ratio(tls["watcher_cpu_us_per_msg_min"], tcp["watcher_cpu_us_per_msg_min"])
    out["watcher_cpu_per_msg_ratio_paired_p10_p90"] = [_q(paired, 0.1), _q(paired, 0.9)]
    out["router_cpu_per_msg_ratio"] = _ratio(tls["router_cpu_us_per_msg_p50"], tcp["router_cpu_us_per_msg_p50"])
    return out


def summarize(enable: dict[str, Any], fanin: dict[str, Any]) -> dict[str, Any]:
    """Ratios tls / tcp, and whether the targets hold."""
    out: dict[str, Any] = {
        "enable_wall_p50_ratio": _ratio(enable["tls"]["wall_ms_p50"], enable["tcp"]["wall_ms_p50"]),
        "enable_wall_p99_ratio": _ratio(enable["tls"]["wall_ms_p99"], enable["tcp"]["wall_ms_p99"]),
        "fanin_watcher_cpu_per_msg_ratio": fanin["watcher_cpu_per_msg_ratio"],
        "fanin_watcher_cpu_per_msg_ratio_min_of_n": fanin["watcher_cpu_per_msg_ratio_min_of_n"],
        "fanin_watcher_cpu_per_msg_ratio_paired_p10_p90": fanin["watcher_cpu_per_msg_ratio_paired_p10_p90"],
        "fanin_router_cpu_ratio": fanin["router_cpu_per_msg_ratio"],
        "fanin_missed": {t: fanin[t]["missed_by_seq"] for t in ("tcp", "tls")},
    }
    ratios = (out["enable_wall_p50_ratio"], out["fanin_watcher_cpu_per_msg_ratio"])
    out["target_ratio_max"] = TARGET_RATIO
    out["target"] = f"tls/tcp <= {TARGET_RATIO} on enable wall p50 and watcher CPU per message (p50), 0 missed"
    out["target_met"] = (all(r is not None and r <= TARGET_RATIO for r in ratios)
                         and all(m == 0 for m in out["fanin_missed"].values()))
    return out


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_security", __doc__)
    p.add_argument("--quick", action="store_true", help="defaults 20 enable rounds, 4x16 fan-in, 6 fan-in rounds")
    p.add_argument("--rounds", type=int, help="enable rounds per transport (default 50)")
    p.add_argument("--fanin", help="AGENTSxDRIVES of the fan-in (default 32x32 = 1024 drives)")
    p.add_argument("--fanin-rounds", type=int, help="fan-in windows per transport, alternating (default 12)")
    p.add_argument("--per-process", type=int, default=8)
    p.add_argument("--sm-watchdog-s", type=float, default=5.0)
    args = p.parse_args(argv)
    # SIGTERM unwinds like an exception, so every router, agent and watcher started is stopped.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    # A failed round is counted and its reason kept in the JSON; the Fleet's warning would list every drive.
    logging.getLogger("supervisor").setLevel(logging.ERROR)
    for name, full, quick in (("rounds", 50, 20), ("fanin", "32x32", "4x16"), ("fanin_rounds", 12, 6)):
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    fa, _, fd = args.fanin.partition("x")
    n_agents, n_drives = int(fa), int(fd)
    load_start = loadavg()
    d = Path(tempfile.mkdtemp(prefix="bench-pki-"))
    result: dict[str, Any] = {"bench": "security", "python": sys.version.split()[0],
                              "settings": {"rounds": args.rounds, "fanin": args.fanin,
                                           "fanin_rounds": args.fanin_rounds, "quick": args.quick}}
    try:
        make_pki(d, max(n_agents, 1))
        print(f"== enable 1x16, {args.rounds} rounds on each transport, alternating", flush=True)
        result["enable"] = enable_rounds(str(d), args.rounds)
        print(json.dumps(result["enable"]), flush=True)
        result["loadavg_after_enable"] = loadavg()
        print(f"== fan-in {args.fanin}, {args.fanin_rounds} windows on each transport, alternating", flush=True)
        rows = fanin_rounds(str(d), n_agents, n_drives, args.fanin_rounds,
                            per_process=args.per_process, sm_watchdog_s=args.sm_watchdog_s)
    finally:
        shutil.rmtree(d, ignore_errors=True)
    result["fanin"] = {"drives": n_agents * n_drives, **fanin_summary(rows), "rounds": rows}
    result["summary"] = summarize(result["enable"], result["fanin"])
    result.update(run_stamp(load_start))
    write_result(result, args.out)
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
