"""What security costs: plain TCP against mutual TLS with the routers' ACL, in the same run.

    .venv/bin/python -m bench.bench_security                        # 50 rounds of 1x16 enable, 32x32 fan-in
    .venv/bin/python -m bench.bench_security --quick                # 20 rounds, 4x16 fan-in
    .venv/bin/python -m bench.bench_security --rounds 100 --fanin 8x32 --repeat 2

On loopback, with a router process, agents on simulated drives in their own processes and a
supervisor ``Fleet``, each plain (tcp) and secure (tls: mutual TLS, the router's ACL, the
authenticated command keys):

- ``enable``: both stacks up at once (one agent of 16 drives each), ``--rounds`` rounds
  alternating between them, so load swings of the shared machine hit both alike: a two-phase
  enable of every drive (the supervisor's wall time, p50 and p99, and the share beyond the
  drives' own transition time), then a disable;
- ``fanin``: ``bench.bench_supervisor.run_size`` with its watcher, tcp then tls (``--repeat``
  times): a watcher ``Fleet`` in its own process receives every drive status while all
  ``--fanin`` drives are enabled and disabled: messages missed (sequence gaps: must be 0 on
  both), the watcher's CPU per 1000 messages, and the router's CPU over the run.

Ratios are tls / tcp. Target: at most 1.2 x on the enable wall time p50 and on the watcher's
CPU per message, and no message missed. The machine's load is recorded with
every run. Results: ``bench/results/bench_security.json``. The PKI is made fresh in a temporary
directory (``drives-pki``'s code, in-process).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from bench.bench_supervisor import SECURE_PRINCIPALS, host_names, report_figures, run_size
from bench.common import RESULTS, percentile
from bus_agent.security import pki as pki_mod
from supervisor.fleet import Fleet
from supervisor.testbed import start_agents, start_router

TARGET_RATIO = 1.2


def make_pki(d: Path, n_agents: int) -> None:
    pki_mod.init(d)
    for name, role in SECURE_PRINCIPALS.items():
        pki_mod.issue(d, name, [role])
    for host in host_names(n_agents):
        pki_mod.issue(d, host, ["agent"])


@contextlib.contextmanager
def bed(pki: str | None, n_drives: int) -> Iterator[Fleet]:
    """A router and one agent of ``n_drives`` (own processes), and a Fleet: plain or secure."""
    router, ep = start_router(pki=pki, identity="bench-router")
    agents = None
    try:
        agents = start_agents(host_names(1), n_drives, ep, sm_watchdog_s=5.0, pki=pki)
        with Fleet(connect=[ep], name="bench-sup", pki=pki, identity="bench-sup" if pki else None) as fleet:
            assert fleet.wait_for_agents(1, 30, drives=n_drives), fleet.roster()
            yield fleet
    finally:
        if agents is not None:
            agents.stop(timeout_s=60)
        router.stop()


def enable_rounds(pki: str, rounds: int, n_drives: int = 16) -> dict[str, Any]:
    """Both stacks up at once, rounds alternating between them (tcp then tls, tls then tcp,
    ...): a load swing on the shared machine hits both alike. Per round: a two-phase enable of every drive
    (the supervisor's wall time, and beyond the drives' own transition time), then a disable."""
    walls: dict[str, list[float]] = {"tcp": [], "tls": []}
    over: dict[str, list[float]] = {"tcp": [], "tls": []}
    failed = {"tcp": 0, "tls": 0}
    with bed(None, n_drives) as tcp, bed(pki, n_drives) as tls:
        for i in range(rounds):
            pair = (("tcp", tcp), ("tls", tls))
            for name, fleet in pair if i % 2 == 0 else pair[::-1]:  # neither always goes first
                rep = fleet.enable("**", timeout_s=10)
                dis = fleet.command("disable", "**", timeout_s=10)
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


def fanin_figures(r: dict[str, Any]) -> dict[str, Any]:
    f = r.get("fanin", {})
    n, cpu = f.get("status_received"), f.get("cpu_s")
    return {"drives": r.get("drives"), "status_received": n,
            "watcher_cpu_ms_per_1000": round(1e6 * cpu / n, 3) if n and cpu is not None else None,
            "missed_by_seq": f.get("missed_by_seq"), "supervisor_missed_by_seq": f.get("supervisor_missed_by_seq"),
            "watcher_cpu_s": f.get("cpu_s"), "watcher_cpu_pct_of_one_core": f.get("cpu_pct_of_one_core"),
            "commands_ok": f.get("commands_ok"), "router_cpu_s": r.get("router_cpu_s"),
            "load_avg_1min_at_start": r.get("load_avg_1min_at_start")}


def _median(runs: list[dict[str, Any]], key: str) -> float | None:
    values = [r[key] for r in runs if r.get(key) is not None]
    return statistics.median(values) if values else None


def _ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 3) if a is not None and b else None


def summarize(enable: dict[str, Any], fanin: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """Ratios tls / tcp, and whether the targets hold."""
    out: dict[str, Any] = {
        "enable_wall_p50_ratio": _ratio(enable["tls"]["wall_ms_p50"], enable["tcp"]["wall_ms_p50"]),
        "enable_wall_p99_ratio": _ratio(enable["tls"]["wall_ms_p99"], enable["tcp"]["wall_ms_p99"]),
        "fanin_watcher_cpu_per_msg_ratio": _ratio(_median(fanin["tls"], "watcher_cpu_ms_per_1000"),
                                                  _median(fanin["tcp"], "watcher_cpu_ms_per_1000")),
        "fanin_router_cpu_ratio": _ratio(_median(fanin["tls"], "router_cpu_s"), _median(fanin["tcp"], "router_cpu_s")),
        "fanin_missed": {t: [r["missed_by_seq"] for r in fanin[t]] for t in fanin},
    }
    ratios = (out["enable_wall_p50_ratio"], out["fanin_watcher_cpu_per_msg_ratio"])
    out["target_ratio_max"] = TARGET_RATIO
    out["target"] = f"tls/tcp <= {TARGET_RATIO} on enable wall p50 and watcher CPU per message, 0 missed"
    out["target_met"] = (all(r is not None and r <= TARGET_RATIO for r in ratios)
                         and all(m == 0 for ms in out["fanin_missed"].values() for m in ms))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="defaults 20 enable rounds, 4x16 fan-in, one repeat")
    p.add_argument("--rounds", type=int, help="enable rounds per transport (default 50)")
    p.add_argument("--fanin", help="AGENTSxDRIVES of the fan-in (default 32x32 = 1024 drives)")
    p.add_argument("--repeat", type=int, help="fan-in runs per transport (default 1)")
    p.add_argument("--per-process", type=int, default=8)
    p.add_argument("--sm-watchdog-s", type=float, default=5.0)
    p.add_argument("--out", "--output", dest="output", default=str(RESULTS / "bench_security.json"), help="JSON file")
    args = p.parse_args(argv)
    # SIGTERM unwinds like an exception, so every router, agent and watcher started is stopped.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    for name, full, quick in (("rounds", 50, 20), ("fanin", "32x32", "4x16"), ("repeat", 1, 1)):
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    fa, _, fd = args.fanin.partition("x")
    n_agents, n_drives = int(fa), int(fd)
    common = dict(per_process=args.per_process, sm_watchdog_s=args.sm_watchdog_s, gets=20)
    d = Path(tempfile.mkdtemp(prefix="bench-pki-"))
    result: dict[str, Any] = {"bench": "security", "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                              "cpus": os.cpu_count(), "python": sys.version.split()[0],
                              "load_avg_at_start": [round(x, 2) for x in os.getloadavg()],
                              "settings": {"rounds": args.rounds, "fanin": args.fanin, "repeat": args.repeat,
                                           "quick": args.quick}}
    fanin: dict[str, list[dict[str, Any]]] = {"tcp": [], "tls": []}
    try:
        make_pki(d, max(n_agents, 1))
        print(f"== enable 1x16, {args.rounds} rounds on each transport, alternating", flush=True)
        result["enable"] = enable_rounds(str(d), args.rounds)
        print(json.dumps(result["enable"]), flush=True)
        for i in range(args.repeat):
            for transport, pki in (("tcp", None), ("tls", str(d))):
                print(f"== {transport} ({i + 1}/{args.repeat}): fan-in {args.fanin}", flush=True)
                r = run_size(n_agents, n_drives, argparse.Namespace(rounds=1, cycle_us=0, **common), True, pki=pki)
                fanin[transport].append(fanin_figures(r))
                print(json.dumps(fanin[transport][-1]), flush=True)
    finally:
        shutil.rmtree(d, ignore_errors=True)
    result["fanin"] = fanin
    result["load_avg_at_end"] = [round(x, 2) for x in os.getloadavg()]
    result["summary"] = summarize(result["enable"], fanin)
    print(json.dumps(result["summary"], indent=1))
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"written {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
