"""Benchmark: the agent cycle vs a bare pysoem loop, 16 drives at 1 kHz on the virtual segment.

    python -m bench.bench_agent [--drives 16] [--seconds 60] [--rounds 6] [--rt-priority 10]
                                [--gateway-modes thread,process] [--no-gateway]
                                [--enable-rounds 50] [--gets-per-round 5] [--out FILE]

One veth pair and one ``ecat-sim`` serve every phase; the phases alternate in ``--rounds``
rounds (N/rounds seconds each), each run in its own process (so process CPU is its own), and
the periods of all rounds of a phase are merged:

1. ``bare``: pysoem send/receive on drift-free deadlines (sleep coarse, spin the last 150 us,
   like the cycle), the same GC and switch-interval settings, outputs packed every cycle;
2. ``agent``: ``bus_agent.cycle.cycle.Cycle`` over ``PysoemBus``, every drive enabled (controllers
   stepping, snapshots built and handed to a sink every cycle);
3. ``gateway_thread`` / ``gateway_process``: the real ``bus_agent.agent.Agent`` composition
   with the Zenoh gateway as threads of the agent process (``gateway = "thread"``) or in its
   own child process behind ``bus_agent.gateway.bridge`` (``gateway = "process"``, the default), while
   a separate process sends 200 queries/s (gets on drive status keys) and subscribes to all
   status. The process phase also reports the gateway process's CPU and the bridge's rate.

After the rounds, ``enable_latency`` (``--enable-rounds`` rounds, 0: skip; ``bench.enable_latency``,
where it is described): an enable of every drive through the real agent and its gateway process,
timed to the last drive's reply, next to a bare zenoh get in the same rounds, with the time split
by hop (``bus_agent.hops``).

The JSON also holds ``bridge_encoding``: bytes and encode/decode time of one bridge snapshot
message, pickle vs msgpack, and the cost of the per-cycle forward check.

Per phase: period p50/p99/p99.9/max, jitter |period - cycle| p50/p99/p99.9/max, overruns, WKC
errors and the phase process's CPU. Ratios: each phase's jitter over the bare loop's at p99, p99.9
and max (none where the bare figure rounds to 0). JSON is printed and written to
bench/results/bench_agent.json. Needs root (veth, raw sockets).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from bench.agent_phases import enable_all, measure, phase_bare
from bench.codec_cost import codec_figures
from bench.common import (ROOT, alternate_phases, bench_parser, free_port, main_result, period_figures, proc_cpu_s, quantiles,
                          read_period_logs, run_json, segment)
from bus_agent import hops

def jitter_ratios(results: dict) -> dict:
    """``<phase>_<q>_jitter_over_bare`` for q in p99, p999, max: the phase's period jitter over the
    bare loop's in the same run. None where the bare figure is 0 (below the 0.1 us resolution):
    no ratio is better than one against a made-up baseline."""
    bare = results["bare"]["jitter_us"]
    return {f"{k}_{q}_jitter_over_bare": round(v["jitter_us"][q] / bare[q], 2) if bare[q] else None
            for k, v in results.items() if k != "bare" for q in ("p99", "p999", "max")}


def phase_agent(args) -> dict:
    from collections import deque

    from bus_agent.bus.pysoem_bus import PysoemBus
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import Cycle

    from bus_agent.bus.dc import DcConfig

    cfg = AgentConfig(host="bench", ifname=args.ifname, cycle_us=args.cycle_us, dc=DcConfig(mode=args.dc))
    cyc = Cycle(PysoemBus(args.ifname, receive_timeout_us=args.receive_timeout_us), cfg, rt_priority=args.rt_priority)
    sink: deque = deque(maxlen=64)
    cyc.snapshot_sink = sink.append  # what a gateway does: enqueue only
    cyc.start()
    try:
        resets = enable_all(cyc)
        out = measure(cyc, args)
        out["startup_fault_resets"] = resets
        if cyc.dc.sync is not None:
            out["dc_pi_held_cycles"] = cyc.dc.sync.held
        return out
    finally:
        cyc.stop()


def _phase_gateway(args, mode: str) -> dict:
    """The real agent composition (``bus_agent.agent.Agent``) with its gateway in ``mode``
    ("process": a child process, the default; "thread": threads of this process, as before)."""
    from bus_agent.agent import Agent
    from bus_agent.bus.pysoem_bus import PysoemBus
    from bus_agent.config import AgentConfig, ZenohConfig

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    cfg = AgentConfig(host="bench", ifname=args.ifname, cycle_us=args.cycle_us, gateway=mode,
                      rt_priority=args.rt_priority, zenoh=ZenohConfig(mode="peer", listen=(ep,), scouting=False))
    agent = Agent(cfg, bus=PysoemBus(args.ifname, receive_timeout_us=args.receive_timeout_us))
    agent.start()
    load = None
    try:
        resets = enable_all(agent.cycle)
        load = subprocess.Popen([sys.executable, "-m", "bench.bench_agent", "--phase", "load", "--connect", ep,
                                 "--host", "bench", "--drives", str(args.drives), "--rate", str(args.query_rate),
                                 "--seconds", str(args.seconds + 5)],
                                cwd=ROOT, stdout=subprocess.PIPE, text=True)
        time.sleep(2.0)  # load warm-up: subscription and queries flowing
        bridge = agent.bridge
        child = bridge.pid if bridge is not None else None
        fwd0, gcpu0, t0 = (bridge.forwarded if bridge else 0), (proc_cpu_s(child) if child else 0.0), time.monotonic()
        res = measure(agent.cycle, args)
        res["startup_fault_resets"] = resets
        if bridge is not None and child:
            el = time.monotonic() - t0
            res["gateway_process_cpu_pct"] = round(100 * (proc_cpu_s(child) - gcpu0) / el, 1)
            res["bridge_snapshots_per_s"] = round((bridge.forwarded - fwd0) / el, 1)
        out, _ = load.communicate(timeout=args.seconds + 30)
        res["load"] = json.loads(out.strip().splitlines()[-1])
        return res
    finally:
        if load is not None and load.poll() is None:
            load.kill()
            load.wait()
        agent.stop()


def phase_gateway_thread(args) -> dict:
    return _phase_gateway(args, "thread")


def phase_gateway_process(args) -> dict:
    return _phase_gateway(args, "process")


def encoding_figures(drives: int, n: int = 2000) -> dict:
    """Bridge message size and encode+decode cost for one snapshot of ``drives`` drives:
    pickle (what the bridge uses) vs msgpack of the same tuples."""
    import msgpack

    from bus_agent import runtime as rt
    from bus_agent.gateway import wire as bridge

    snap = rt.CycleSnapshot(
        cycle=123456, time_ns=time.time_ns(), events=(), stats=rt.CycleStats(cycles=123456, period_p99_us=1001.2),
        drives=tuple(rt.DriveSnapshot(f"axis{i}", i, "operation_enabled", 0x1237, 0x000F, "enabled", False, 8, 8,
                                      1_000_000 + i, -300, 12, 0, "", "op", False) for i in range(drives)))
    out = {}
    for name, enc, dec in (("pickle", bridge.dumps, bridge.loads),
                           ("msgpack", lambda m: msgpack.packb(m), lambda b: msgpack.unpackb(b, use_list=False))):
        msg = (bridge.Msg.UPDATE.value, bridge.encode_snapshot(snap), (), ())
        t0 = time.perf_counter()
        for _ in range(n):
            data = enc(msg)
        t1 = time.perf_counter()
        for _ in range(n):
            bridge.decode_snapshot(dec(data)[1])
        t2 = time.perf_counter()
        out[name] = {"bytes": len(data), "encode_us": round((t1 - t0) / n * 1e6, 1),
                     "decode_us": round((t2 - t1) / n * 1e6, 1)}
    f = bridge.ForwardFilter()
    t0 = time.perf_counter()
    for i in range(n):
        f.due(snap, 0.0)   # the per-cycle check of bridge-out (nothing changed, not due)
    out["filter_check_us"] = round((time.perf_counter() - t0) / n * 1e6, 2)
    return out


def phase_load(args) -> dict:
    """Another process: 200 queries/s on drive status keys, subscribed to all drive status."""
    import zenoh

    from bus_agent.gateway.zenoh_config import make_zenoh_config
    from schemas import keys

    session = zenoh.open(make_zenoh_config("peer", connect=[args.connect]))
    received = [0]
    sub = session.declare_subscriber(keys.ALL_DRIVE_STATUS, lambda s: received.__setitem__(0, received[0] + 1))
    axes = [f"axis{i}" for i in range(args.drives)]
    period = 1.0 / args.query_rate
    t0 = time.monotonic()
    sent = replies = errors = 0
    rtts = []
    k = 0
    while time.monotonic() - t0 < args.seconds:
        dl = t0 + k * period
        d = dl - time.monotonic()
        if d > 0:
            time.sleep(d)
        q0 = time.monotonic()
        try:
            for r in session.get(keys.drive_status(args.host, axes[k % len(axes)]), timeout=1.0):
                if r.ok is not None:
                    replies += 1
                else:
                    errors += 1
        except Exception:
            errors += 1
        rtts.append(time.monotonic() - q0)
        sent += 1
        k += 1
    el = time.monotonic() - t0
    sub.undeclare()
    session.close()
    rtts.sort()
    return {"queries": sent, "query_rate": round(sent / el, 1), "replies": replies, "errors": errors,
            "query_rtt_ms_p50": round(rtts[len(rtts) // 2] * 1000, 2) if rtts else None,
            "query_rtt_ms_p99": round(rtts[int(len(rtts) * 0.99)] * 1000, 2) if rtts else None,
            "status_samples_received": received[0]}


PHASES = {"bare": phase_bare, "agent": phase_agent, "gateway_thread": phase_gateway_thread,
          "gateway_process": phase_gateway_process, "load": phase_load}


# ---- orchestration ---------------------------------------------------------------------------


def _run_phase(name: str, ifname: str, args, seconds: float, log_file: str, timeout_s: float | None = None,
               module: str = "bench.bench_agent", env: dict | None = None) -> dict:
    cmd = [sys.executable, "-m", module, "--phase", name, "--ifname", ifname,
           "--drives", str(args.drives), "--seconds", str(seconds), "--cycle-us", str(args.cycle_us),
           "--rt-priority", str(args.rt_priority), "--receive-timeout-us", str(args.receive_timeout_us),
           "--rate", str(args.query_rate), "--log-file", log_file, "--enable-rounds", str(args.enable_rounds),
           "--gets-per-round", str(args.gets_per_round), "--profile", args.profile, "--dc", args.dc,
           "--client-rt-priority", str(args.client_rt_priority)]
    return run_json(cmd, f"phase {name}", timeout_s or seconds * 4 + 120, env=env)


def _merge(parts: list[dict], logs: list[str], cycle_ns: int) -> dict:
    periods = read_period_logs(logs)
    seconds = sum(p["seconds"] for p in parts)
    cpu = sum(p["cpu_s"] for p in parts)
    out = {"rounds": len(parts), "cycles": sum(p["cycles"] for p in parts), "seconds": round(seconds, 2),
           "overruns": sum(p["overruns"] for p in parts), "wkc_errors": sum(p["wkc_errors"] for p in parts),
           "startup_fault_resets": sum(p.get("startup_fault_resets", 0) for p in parts),
           "cpu_pct": round(100 * cpu / seconds, 1) if seconds else None,
           "overruns_per_round": [p["overruns"] for p in parts],
           "jitter_p99_us_per_round": [p["jitter_us"]["p99"] for p in parts], **period_figures(periods, cycle_ns)}
    dc_logs = [p + ".dc" for p in logs if os.path.exists(p + ".dc")]
    if dc_logs:  # frame-to-SYNC0 offset: where in the SYNC0 period the frames passed the reference
        offs = sorted(read_period_logs(dc_logs))
        out["dc_offset_us"] = {**quantiles(offs, ("p1", "p50", "p99"), 1e-3), "samples": len(offs)}
    if any("dc_pi_held_cycles" in p for p in parts):  # cycles late enough to hold the PI (a loaded host)
        out["dc_pi_held_cycles"] = sum(p.get("dc_pi_held_cycles", 0) for p in parts)
    for key in ("gateway_process_cpu_pct", "bridge_snapshots_per_s"):
        vals = [p[key] for p in parts if key in p]
        if vals:
            out[key] = round(sum(vals) / len(vals), 1)
    loads = [p["load"] for p in parts if "load" in p]
    if loads:
        out["load"] = {"queries": sum(x["queries"] for x in loads), "errors": sum(x["errors"] for x in loads),
                       "query_rate": round(sum(x["query_rate"] for x in loads) / len(loads), 1),
                       "query_rtt_ms_p50": max(x["query_rtt_ms_p50"] or 0 for x in loads),
                       "query_rtt_ms_p99": max(x["query_rtt_ms_p99"] or 0 for x in loads),
                       "status_samples_received": sum(x["status_samples_received"] for x in loads)}
    return out


def run(args) -> dict:
    with segment("bag", args.drives, args.sim_rt_priority, args.profile) as seg:
        phases = ["bare", "agent"] + ([] if args.no_gateway else [f"gateway_{m}" for m in args.gateway_modes])
        # Phases alternate in rounds, so a burst of load from other work on the host lands on
        # all of them alike rather than on whichever phase happened to run then.
        parts, logs = alternate_phases("bench_agent", phases, args.rounds, args.seconds, seg.workdir,
                                       lambda name, s, log: _run_phase(name, seg.master_if, args, s, log))
        results = {name: _merge(parts[name], logs[name], args.cycle_us * 1000) for name in phases}
        ratios = jitter_ratios(results)
        enable = None
        if args.enable_rounds > 0:
            print(f"bench_agent: phase enable_latency ({args.enable_rounds} enable/disable rounds)...",
                  file=sys.stderr, flush=True)
            # Every process of the phase records the hops of each command (bus_agent.hops).
            hop_dir = os.path.join(seg.workdir, "hops")
            os.makedirs(hop_dir, exist_ok=True)
            enable = _run_phase("enable_latency", seg.master_if, args, 0, os.path.join(seg.workdir, "enable"),
                                timeout_s=180 + args.enable_rounds * 30, module="bench.enable_latency",
                                env={**os.environ, hops.ENV: hop_dir})
        return {"drives": args.drives, "cycle_us": args.cycle_us, "seconds_per_phase": args.seconds,
                "rounds": args.rounds, "rt_priority": args.rt_priority, "sim_rt_priority": args.sim_rt_priority,
                "receive_timeout_us": args.receive_timeout_us, "query_rate": args.query_rate,
                "gateway_modes": [] if args.no_gateway else args.gateway_modes, "phases": results, "ratios": ratios,
                "enable_latency": enable,
                "bridge_encoding": encoding_figures(args.drives),
                "profile": args.profile, "dc": args.dc, "codec_cost": codec_figures(args.drives, 3000),
                "loadavg_1m": os.getloadavg()[0], "loadavg": list(os.getloadavg()), "cpus": os.cpu_count(),
                "time": time.strftime("%Y-%m-%dT%H:%M:%S")}


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_agent", __doc__)
    p.add_argument("--drives", type=int, default=16)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--cycle-us", type=int, default=1000)
    p.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority of the loop thread (0: off)")
    p.add_argument("--sim-rt-priority", type=int, default=20, help="SCHED_FIFO priority of ecat-sim (0: off)")
    p.add_argument("--receive-timeout-us", type=int, default=1000)
    p.add_argument("--query-rate", "--rate", dest="query_rate", type=float, default=200.0)
    p.add_argument("--rounds", type=int, default=6, help="phases alternate in this many rounds (default 6)")
    p.add_argument("--no-gateway", action="store_true", help="skip the agent+gateway+load phases")
    p.add_argument("--gateway-modes", type=lambda v: [m for m in v.split(",") if m], default=["thread", "process"],
                   help="gateway phases to run: thread, process or both (default thread,process)")
    p.add_argument("--enable-rounds", type=int, default=50,
                   help="enable_latency phase: enable/disable rounds of every drive (default 50, 0: skip)")
    p.add_argument("--gets-per-round", type=int, default=5,
                   help="enable_latency phase: bare zenoh gets per round (default 5)")
    p.add_argument("--client-rt-priority", type=int, default=0,
                   help="enable_latency phase: SCHED_FIFO of the client process, a stand-in for a supervisor on "
                        "another host (default 0: normal scheduling)")
    p.add_argument("--profile", default="generic",
                   help="ecat-sim slave profile(s), e.g. omron1s:dc-required (predefined PDOs, DC SYNC0)")
    p.add_argument("--dc", choices=("auto", "off"), default="auto",
                   help="[dc] mode of the agent phases; auto also starts SYNC0 in the bare loop")
    # internal: one phase in this process
    p.add_argument("--phase", choices=sorted(PHASES), help=argparse.SUPPRESS)
    p.add_argument("--ifname", help=argparse.SUPPRESS)
    p.add_argument("--connect", help=argparse.SUPPRESS)
    p.add_argument("--echo", help=argparse.SUPPRESS)
    p.add_argument("--listen", help=argparse.SUPPRESS)
    p.add_argument("--host", default="bench", help=argparse.SUPPRESS)
    p.add_argument("--log-file", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.phase:
        out = PHASES[args.phase](args)
        if args.phase != "echo":
            print(json.dumps(out), flush=True)
        return 0
    return main_result("bench_agent", lambda: run(args), args.out)


if __name__ == "__main__":
    sys.exit(main())
