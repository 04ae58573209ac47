"""Benchmark: the CAN agent cycle (CanopenBus, 8 nodes) next to a bare python-can SYNC loop, at a
1 ms and a 4 ms SYNC period, in the same run.

    python -m bench.bench_canopen [--nodes 8] [--periods-us 1000,4000] [--seconds 10] [--out FILE]

Everything runs in a network namespace of its own with only ``lo`` (CAN frames over python-can's
``udp_multicast`` stay in it); the script re-runs itself inside it. One ``canopen-sim`` process
serves both phases of each period:

1. ``bare``: a python-can program: NMT start, then every period the 16 RPDOs and one SYNC on
   drift-free deadlines (sleep coarse, spin the last 150 us, like the cycle) with the cycle's GC
   and switch-interval settings; a ``can.Notifier`` thread counts the TPDOs of every SYNC;
2. ``agent``: ``bus_agent.cycle.cycle.Cycle`` over ``CanopenBus`` (start-up SDOs, PDO policy
   ``default``, NMT start), drives disabled, controllers stepping, a snapshot per cycle.

Per phase: period and jitter |period - cycle| p50/p99/p99.9/max (us), overruns, frames sent per
cycle, TPDOs expected and missed (a TPDO of SYNC k not received before cycle k+1 starts), CPU of
the phase. Ratios: agent jitter over bare at p99/p99.9/max. With ``--rt-priority N`` both loops run
SCHED_FIFO N and canopen-sim N + 10 (as bench_agent does with ecat-sim). The machine's load average is
recorded before and after. JSON printed and written to bench/results/bench_canopen.json. Root.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from bench.common import ROOT, bench_parser, main_result, paced_loop, period_figures, self_cpu_s, stop_process

CHANNEL = "239.74.163.99"


def _bare(args, period_us: int) -> dict:
    import can

    from bus_agent.bus.canopen.cob import SYNC_COB_ID
    from bus_agent.bus.canopen.pdo import PdoFrames, default_mapping
    from bus_agent.bus.canopen.nmt import NmtCommand, nmt_frame
    from bus_agent.bus.pdo import DriveOutputs
    from bus_agent.bus.canopen.bus import open_can

    bus = open_can(CHANNEL, "udp_multicast")
    ids = list(range(1, args.nodes + 1))
    codecs = [PdoFrames(default_mapping(n)) for n in ids]
    tpdo_ids = {cob for c in codecs for cob in c.tpdo_cob_ids}
    got = [0]

    class Count(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            if msg.arbitration_id in tpdo_ids:
                got[0] += 1

    notifier = can.Notifier(bus, [Count()], 0.5)
    bus.send(can.Message(arbitration_id=0, data=nmt_frame(NmtCommand.START, 0), is_extended_id=False))
    time.sleep(0.5)
    frames = [can.Message(arbitration_id=cob, data=data, is_extended_id=False)
              for c in codecs for cob, data in c.rpdo_frames(DriveOutputs(modes_of_operation=8))]
    frames.append(can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False))
    period = period_us * 1000
    missed = seen = 0

    def step(i: int) -> None:
        nonlocal missed, seen
        if i:  # the TPDOs of the previous SYNC
            arrived = got[0] - seen
            seen = got[0]
            missed += max(0, len(tpdo_ids) - arrived)
        for f in frames:
            bus.send(f)

    run = paced_loop(int(args.seconds * 1e9 / period), period, step, args.rt_priority)
    notifier.stop()
    bus.send(can.Message(arbitration_id=0, data=nmt_frame(NmtCommand.ENTER_PRE_OPERATIONAL, 0), is_extended_id=False))
    bus.shutdown()
    n = len(run.periods)
    expected = len(tpdo_ids) * (n - 1)
    return {"cycles": n, "seconds": round(run.elapsed_s, 2), "overruns": run.overruns, "frames_sent_per_cycle": len(frames),
            "tpdos_expected": expected, "tpdos_missed": missed, "tpdos_missed_pct": round(100 * missed / expected, 3),
            "cpu_pct": round(100 * run.cpu_s / run.elapsed_s, 1), **period_figures(list(run.periods[1:]), period)}


def _agent(args, period_us: int) -> dict:
    from bus_agent.bus.canopen.bus import CanopenBus
    from bus_agent.can_config import can_config
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import Cycle

    ids = tuple(range(1, args.nodes + 1))
    cfg = AgentConfig(host="bench", cycle_us=period_us, can=can_config(CHANNEL, "udp_multicast", ids))
    bus = CanopenBus(CHANNEL, ids, interface="udp_multicast")
    period = period_us * 1000
    n = int(args.seconds * 1e9 / period)
    cyc = Cycle(bus, cfg, record_periods=n, rt_priority=args.rt_priority)
    cyc.open()
    ov0, wk0 = cyc.overruns, cyc.wkc_errors
    cpu0 = self_cpu_s()
    t0 = time.monotonic()
    cyc.start()
    while cyc.period_log_len < n and time.monotonic() - t0 < args.seconds * 3 + 10:
        time.sleep(0.05)
    elapsed = time.monotonic() - t0
    cpu = self_cpu_s() - cpu0
    got = cyc.period_log_len
    periods = list(cyc.period_log[:got]) if cyc.period_log is not None else []
    exchanges, sent, missed = bus.exchanges, bus.frames_sent, bus.missed_tpdos
    overruns, wkc_errors = cyc.overruns - ov0, cyc.wkc_errors - wk0
    cyc.stop(ordered=False)
    expected = 2 * args.nodes * max(1, exchanges - 1)
    return {"cycles": got, "seconds": round(elapsed, 2), "overruns": overruns, "wkc_errors": wkc_errors,
            "frames_sent_per_cycle": round(sent / max(1, exchanges), 2), "tpdos_expected": expected,
            "tpdos_missed": missed, "tpdos_missed_pct": round(100 * missed / expected, 3),
            "cpu_pct": round(100 * cpu / max(elapsed, 1e-9), 1), **period_figures(periods[1:], period)}


def inside(args) -> dict:
    """The measurement, run inside the namespace."""
    result: dict = {"nodes": args.nodes, "seconds": args.seconds, "rt_priority": args.rt_priority,
                    "load_before": os.getloadavg(), "periods": {}}
    sim = subprocess.Popen([sys.executable, "-m", "bus_agent.sim.canopen.cli", "--channel", CHANNEL,
                            "--interface", "udp_multicast", "--nodes", str(args.nodes),
                            "--rt-priority", str(args.rt_priority + 10 if args.rt_priority else 0)],
                           cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert sim.stdout is not None
        if not sim.stdout.readline().startswith("canopen-sim ready"):
            raise RuntimeError("canopen-sim did not start")
        for period_us in args.periods_us:
            bare = _bare(args, period_us)
            agent = _agent(args, period_us)
            ratios = {f"agent_{q}_jitter_over_bare": (round(agent["jitter_us"][q] / bare["jitter_us"][q], 3)
                                                       if bare["jitter_us"][q] else None)
                      for q in ("p99", "p999", "max")}
            result["periods"][str(period_us)] = {"bare": bare, "agent": agent, "ratios": ratios}
    finally:
        stop_process(sim)
    result["load_after"] = os.getloadavg()
    return result


def run(args) -> dict:
    """Make the namespace, run :func:`inside` in it, remove the namespace."""
    from bus_agent.sim.netns import netns_add, netns_del

    ns = f"zcb{os.getpid() % 100000}"
    netns_add(ns)
    try:
        subprocess.run(["ip", "-n", ns, "link", "set", "lo", "multicast", "on"], check=True)
        subprocess.run(["ip", "-n", ns, "route", "add", "224.0.0.0/4", "dev", "lo"], check=True)
        argv = [sys.executable, "-m", "bench.bench_canopen", "--inside", "--nodes", str(args.nodes),
                "--seconds", str(args.seconds), "--rt-priority", str(args.rt_priority),
                "--periods-us", ",".join(map(str, args.periods_us))]
        done = subprocess.run(["ip", "netns", "exec", ns, *argv], cwd=ROOT, capture_output=True, text=True,
                              timeout=args.seconds * 20 + 120)
        if done.returncode != 0:
            raise RuntimeError(f"bench_canopen inside {ns} failed: {done.stderr[-2000:]}")
        return json.loads(done.stdout)
    finally:
        netns_del(ns)


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_canopen", __doc__)
    p.add_argument("--nodes", type=int, default=8)
    p.add_argument("--periods-us", type=lambda s: [int(x) for x in s.split(",")], default=[1000, 4000])
    p.add_argument("--seconds", type=float, default=10.0, help="per phase and period")
    p.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO of both loops (0: off)")
    p.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.inside:
        print(json.dumps(inside(args)))
        return 0
    return main_result("bench_canopen", lambda: run(args), args.out)


if __name__ == "__main__":
    sys.exit(main())
