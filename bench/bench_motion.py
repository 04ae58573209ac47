"""Benchmark: motion in the agent's cycle, 16 axes at 1 kHz over ecat-sim (pysoem, veth pair).

    python -m bench.bench_motion [--drives 16] [--seconds 30] [--rounds 3] [--rt-priority 10]
                                 [--latency-moves 50] [--sync-moves 10] [--out FILE]

One veth pair and one ``ecat-sim`` serve every phase; the phases alternate in ``--rounds`` rounds
(each in its own process, so the process CPU is its own), and the periods of a phase's rounds
are merged:

1. ``bare``: the bare pysoem loop of :mod:`bench.agent_phases` (the baseline);
2. ``idle``: the agent's cycle (``Cycle`` over ``PysoemBus``), every drive enabled, no motion;
3. ``motion``: the same with every axis moving all the time: synchronized moves of all 16 axes
   back and forth (a jerk-limited ruckig profile per axis, sampled every cycle and written as
   0x607A), the next one submitted as soon as the last one is done.

Per phase: period p50/p99/p99.9/max and jitter |period - cycle|, overruns, WKC errors, process CPU
(percent and microseconds per cycle). Ratios in the same run: each agent phase's jitter over the
bare loop's (target: motion at most 1.25x at p99), and motion's CPU per cycle over idle's (the
cost of motion).

After the rounds, in one more agent process (``latency``):

- ``query_to_first_target``: ``--latency-moves`` single-axis moves; time from ``Cycle.submit``
  to the cycle whose output carries the first changed 0x607A (seen by the snapshot sink, which
  stamps time.monotonic_ns in the cycle thread), and the same in cycles;
- ``sync_arrival``: ``--sync-moves`` synchronized moves of all axes to random targets; per move,
  the cycle each drive's reported position reaches its target (the drives' own reports, one
  cycle of process data later), and the spread max - min in cycles.

The cross-host spread (two agents on two namespaced hosts) is measured by
tests/system/test_motion_multihost.py, not here. JSON is printed and written to
bench/results/bench_motion.json, with the load average. Needs root (veth, raw sockets).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import threading
import time
from collections import deque

from bench.agent_phases import enable_all, measure, phase_bare
from bench.bench_agent import jitter_ratios
from bench.common import (alternate_phases, bench_parser, loadavg, main_result, percentile, period_figures, run_stamp, segment,
                          read_period_logs, run_json, summary_ms)

#: Back-and-forth targets of the motion phase (counts): well within the default limits.
SWING = 40_000


def _cycle(args):
    from bus_agent.bus.dc import DcConfig
    from bus_agent.bus.pysoem_bus import PysoemBus
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import Cycle

    cfg = AgentConfig(host="bench", ifname=args.ifname, cycle_us=args.cycle_us, dc=DcConfig(mode=args.dc))
    return Cycle(PysoemBus(args.ifname, receive_timeout_us=args.receive_timeout_us), cfg, rt_priority=args.rt_priority)


def _sync_move(cyc, targets: dict[str, float], timeout_s: float = 20.0) -> list:
    from bus_agent.runtime import DriveCommand

    done = threading.Semaphore(0)
    outs: list = []

    def on(o) -> None:
        outs.append(o)
        done.release()

    assert cyc.submit(DriveCommand(request_id=f"bench-sync-{time.monotonic_ns()}", op="move", axes=tuple(targets),
                                   args={"sync": True, "targets": targets}, on_outcome=on,
                                   received_ns=time.monotonic_ns(), timeout_s=timeout_s))
    for _ in targets:
        if not done.acquire(timeout=timeout_s + 2):
            raise RuntimeError("synchronized move did not finish")
    return outs


def phase_idle(args) -> dict:
    cyc = _cycle(args)
    sink: deque = deque(maxlen=64)
    cyc.snapshot_sink = sink.append
    cyc.start()
    try:
        resets = enable_all(cyc)
        out = measure(cyc, args)
        out["startup_fault_resets"] = resets
        return out
    finally:
        cyc.stop()


def phase_motion(args) -> dict:
    cyc = _cycle(args)
    sink: deque = deque(maxlen=64)
    cyc.snapshot_sink = sink.append
    cyc.start()
    stop = threading.Event()
    moves = [0]
    bad: list = []

    def feeder() -> None:
        sign = 1
        while not stop.is_set():
            outs = _sync_move(cyc, {a: float(sign * SWING) for a in cyc.axes})
            bad.extend(o for o in outs if o.outcome != "done")
            moves[0] += 1
            sign = -sign

    try:
        resets = enable_all(cyc)
        t = threading.Thread(target=feeder, daemon=True)
        t.start()
        out = measure(cyc, args)
        stop.set()
        t.join(30)
        out["startup_fault_resets"] = resets
        out["sync_moves"] = moves[0]
        out["moves_not_done"] = len(bad)
        return out
    finally:
        cyc.stop()


def phase_latency(args) -> dict:
    from bus_agent.runtime import DriveCommand

    cyc = _cycle(args)
    marks: deque = deque(maxlen=100_000)
    clock = time.monotonic_ns

    def sink(snap) -> None:  # cycle thread: one tuple per cycle
        marks.append((clock(), snap.cycle, tuple(d.target_position for d in snap.drives),
                      tuple(d.position for d in snap.drives), tuple(d.motion_request_id for d in snap.drives)))

    cyc.snapshot_sink = sink
    cyc.start()
    try:
        enable_all(cyc)
        rng = random.Random(1)
        lat_ms: list[float] = []
        lat_cycles: list[int] = []
        applied_ms: list[float] = []
        for k in range(args.latency_moves):
            axis = cyc.axes[k % len(cyc.axes)]
            i = cyc.axes.index(axis)
            marks.clear()
            before = cyc.latest.drives[i].target_position
            t0 = clock()
            c0 = cyc.cycles
            got = threading.Event()
            rid = f"bench-lat-{k}"
            assert cyc.submit(DriveCommand(request_id=rid, op="move", axes=(axis,),
                                           args={"by": float(rng.choice((-1, 1)) * 5_000)},
                                           on_outcome=lambda o: got.set(), received_ns=t0, timeout_s=10.0))
            if not got.wait(12):
                raise RuntimeError("latency move did not finish")
            rows = list(marks)
            applied = next((m for m in rows if m[4][i] == rid), None)
            if applied is not None:
                applied_ms.append((applied[0] - t0) / 1e6)
            first = next((m for m in rows if m[0] >= t0 and m[2][i] != before), None)
            if first is not None:
                lat_ms.append((first[0] - t0) / 1e6)
                lat_cycles.append(first[1] - c0)
        spreads: list[int] = []
        for k in range(args.sync_moves):
            targets = {a: float(rng.randrange(-60_000, 60_000)) for a in cyc.axes}
            marks.clear()
            outs = _sync_move(cyc, targets)
            if any(o.outcome != "done" for o in outs):
                raise RuntimeError(f"sync move not done: {[o for o in outs if o.outcome != 'done'][:2]}")
            rows = list(marks)
            arrive = []
            for i, a in enumerate(cyc.axes):
                hit = next((m[1] for m in rows if m[3][i] == int(targets[a])), None)
                if hit is not None:
                    arrive.append(hit)
            if len(arrive) == len(cyc.axes):
                spreads.append(max(arrive) - min(arrive))
        lat_ms.sort()
        lat_cycles.sort()
        applied_ms.sort()
        spreads.sort()
        return {
            "query_to_applied": {"moves": len(applied_ms), **summary_ms([x / 1e3 for x in applied_ms])},
            "query_to_first_target": {
                "moves": len(lat_ms), "ms_p50": round(percentile(lat_ms, 0.5), 3) if lat_ms else None,
                "ms_p99": round(percentile(lat_ms, 0.99), 3) if lat_ms else None,
                "ms_max": round(lat_ms[-1], 3) if lat_ms else None,
                "cycles_p50": percentile(lat_cycles, 0.5) if lat_cycles else None,
                "cycles_max": lat_cycles[-1] if lat_cycles else None},
            "sync_arrival": {"moves": len(spreads), "axes": len(cyc.axes),
                             "spread_cycles_max": spreads[-1] if spreads else None,
                             "spread_cycles_p50": percentile(spreads, 0.5) if spreads else None}}
    finally:
        cyc.stop()


def step_cost(axes: int = 16, cycles: int = 1000, repeats: int = 15) -> dict:
    """The motion layer's own work per cycle, pure and in this process (robust under load: the
    minimum of ``repeats`` runs of ``cycles`` cycles): ``AxisMotion.observe`` + ``step`` of
    ``axes`` axes standing still vs all moving (one ruckig sample each), and the planning of one
    synchronized move of every axis (done in the cycle that applies the command)."""
    from bus_agent.motion.axis import AxisMotion
    from bus_agent.motion.config import MotionConfig
    from bus_agent.motion.planner import Kinematic, Limits, plan_group, plan_position

    cfg = MotionConfig()
    lim = Limits(cfg.max_velocity, cfg.max_acceleration, cfg.max_jerk)

    def run(moving: bool) -> float:
        ms = [AxisMotion(cfg, 0.001) for _ in range(axes)]
        for m in ms:
            m.observe(enabled=True, fault=False, state="operation_enabled", error_code=0, position=0, velocity=0,
                      mode=8, halted=False, commanded=0)
            if moving:  # a long move: still under way after every timed cycle
                m.start_plan(None, "b", "move", plan_position(Kinematic(0.0), 10_000_000.0, lim), 0.0, 1e9)
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter_ns()
            for c in range(cycles):
                now = c * 0.001
                for m in ms:
                    m.observe(enabled=True, fault=False, state="operation_enabled", error_code=0, position=0,
                              velocity=0, mode=8, halted=False, commanded=m.target_position)
                    m.step(now)
            best = min(best, (time.perf_counter_ns() - t0) / cycles / 1e3)
        return best

    idle_us, moving_us = run(False), run(True)
    starts, targets = [Kinematic(0.0)] * axes, [float(10_000 * (i + 1)) for i in range(axes)]
    plan_best = float("inf")
    for _ in range(repeats * 4):
        t0 = time.perf_counter_ns()
        plan_group(starts, targets, [lim] * axes, 0.0)
        plan_best = min(plan_best, (time.perf_counter_ns() - t0) / 1e3)
    return {"axes": axes, "idle_us_per_cycle": round(idle_us, 2), "moving_us_per_cycle": round(moving_us, 2),
            "added_us_per_cycle": round(moving_us - idle_us, 2),
            "added_us_per_axis": round((moving_us - idle_us) / axes, 3),
            "plan_group_us": round(plan_best, 1), "method": f"min of {repeats} runs of {cycles} cycles"}


PHASES = {"bare": phase_bare, "idle": phase_idle, "motion": phase_motion, "latency": phase_latency}


def _run_phase(name: str, ifname: str, args, seconds: float, log_file: str) -> dict:
    cmd = [sys.executable, "-m", "bench.bench_motion", "--phase", name, "--ifname", ifname,
           "--drives", str(args.drives), "--seconds", str(seconds), "--cycle-us", str(args.cycle_us),
           "--rt-priority", str(args.rt_priority), "--receive-timeout-us", str(args.receive_timeout_us),
           "--latency-moves", str(args.latency_moves), "--sync-moves", str(args.sync_moves), "--dc", args.dc,
           "--log-file", log_file]
    return run_json(cmd, f"phase {name}", seconds * 4 + 300)


def _merge(parts: list[dict], logs: list[str], cycle_ns: int) -> dict:
    periods = read_period_logs(logs)
    seconds = sum(p["seconds"] for p in parts)
    cpu = sum(p["cpu_s"] for p in parts)
    cycles = sum(p["cycles"] for p in parts)
    out = {"rounds": len(parts), "cycles": cycles, "seconds": round(seconds, 2),
           "overruns": sum(p["overruns"] for p in parts), "wkc_errors": sum(p["wkc_errors"] for p in parts),
           "cpu_pct": round(100 * cpu / seconds, 1) if seconds else None,
           "cpu_us_per_cycle": round(cpu / cycles * 1e6, 1) if cycles else None,
           "jitter_p99_us_per_round": [p["jitter_us"]["p99"] for p in parts], **period_figures(periods, cycle_ns)}
    for key in ("sync_moves", "moves_not_done", "startup_fault_resets"):
        if any(key in p for p in parts):
            out[key] = sum(p.get(key, 0) for p in parts)
    return out


def run(args) -> dict:
    load0 = loadavg()
    with segment("bmo", args.drives, args.sim_rt_priority) as seg:
        phases = ["bare", "idle", "motion"]
        parts, logs = alternate_phases("bench_motion", phases, args.rounds, args.seconds, seg.workdir,
                                       lambda name, s, log: _run_phase(name, seg.master_if, args, s, log))
        results = {name: _merge(parts[name], logs[name], args.cycle_us * 1000) for name in phases}
        print("bench_motion: phase latency...", file=sys.stderr, flush=True)
        latency = _run_phase("latency", seg.master_if, args, 0, os.path.join(seg.workdir, "latency"))
        idle_cpu, motion_cpu = results["idle"]["cpu_us_per_cycle"], results["motion"]["cpu_us_per_cycle"]
        ratios = jitter_ratios(results)
        ratios["motion_cpu_per_cycle_over_idle"] = round(motion_cpu / idle_cpu, 2) if idle_cpu else None
        ratios["motion_cpu_us_per_cycle_added"] = round(motion_cpu - idle_cpu, 1) if idle_cpu else None
        return {"drives": args.drives, "cycle_us": args.cycle_us, "seconds_per_phase": args.seconds,
                "rounds": args.rounds, "rt_priority": args.rt_priority, "sim_rt_priority": args.sim_rt_priority,
                "dc": args.dc, "phases": results, "ratios": ratios, **latency, "step_cost": step_cost(args.drives),
                **run_stamp(load0)}


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_motion", __doc__)
    p.add_argument("--drives", type=int, default=16)
    p.add_argument("--seconds", type=float, default=30.0, help="seconds per phase, split over the rounds")
    p.add_argument("--cycle-us", type=int, default=1000)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority of the loop thread (0: off)")
    p.add_argument("--sim-rt-priority", type=int, default=20, help="SCHED_FIFO priority of ecat-sim (0: off)")
    p.add_argument("--receive-timeout-us", type=int, default=1000)
    p.add_argument("--latency-moves", type=int, default=50)
    p.add_argument("--sync-moves", type=int, default=10)
    p.add_argument("--dc", choices=("auto", "off"), default="auto",
                   help="[dc] mode of the agent phases; auto also starts SYNC0 in the bare loop (as bench_agent)")
    p.add_argument("--phase", choices=sorted(PHASES), help=argparse.SUPPRESS)
    p.add_argument("--ifname", help=argparse.SUPPRESS)
    p.add_argument("--log-file", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.phase:
        print(json.dumps(PHASES[args.phase](args)), flush=True)
        return 0
    return main_result("bench_motion", lambda: run(args), args.out)


if __name__ == "__main__":
    sys.exit(main())
