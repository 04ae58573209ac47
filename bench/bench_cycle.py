"""Benchmark: the agent cycle's CPU per drive, next to a bare pysoem loop, on the virtual segment.

    python -m bench.bench_cycle [--drives 16,64] [--seconds 20] [--rounds 2] [--rt-priority 10]
                                [--codec-cycles 3000] [--tick-runs 30] [--out FILE]

For each drive count, one veth pair and one ``ecat-sim`` serve two phases that alternate in
``--rounds`` rounds, each phase in its own process:

1. ``bare``: pysoem send/receive on the cycle's timing, every slave's inputs read and outputs
   packed each cycle (``bench.agent_phases.phase_bare``); its one thread is the loop;
2. ``agent``: ``Cycle`` over ``PysoemBus``, every drive enabled and at rest in CSP, snapshots
   handed to a sink (what a gateway does); the cycle thread's own CPU is read from
   /proc/self/task/<tid>/schedstat (nanoseconds), so the management thread is not counted.

CPU is CPU time, not wall-clock time, so the figures hold up under load: ``cycle_cpu_pct`` is the
loop thread's CPU over the phase's elapsed time (% of one core), ``cpu_us_per_cycle`` the same per
cycle and ``cpu_pct_of_period`` that over the cycle period (% of a core at the full 1 kHz, which
cycles a loaded host skipped do not lower; the target), ``beyond_bare_us_per_drive`` the agent's CPU per cycle beyond the bare loop's, per drive.
Jitter |period - cycle| p99/p99.9/max of each phase, and the agent's over the bare loop's.

``ticks`` (a third process on the same segment, :func:`phase_ticks`): one cycle's CPU run by
``tick()`` with the drives at rest skipped, with every drive stepped (``Cycle.fast_paths =
False``) and with one drive moving, next to the bare exchange; best of interleaved runs.

``stage`` (``--stage-only`` alone, no root): the output stage's CPU per axis per cycle, and a
cycle over SimBus with every axis moving with and without it (:func:`stage_figures`).

``codec``: the CPU of one cycle's decode + encode of every drive, in this process (best of many
short runs of thread CPU time): the fixed 13/15-byte structs inline (the decode before per-drive
codecs), ``DriveCodec`` for the default layout and for an Omron-like predefined mapping, and
their ratios to the fixed structs. Needs root (veth, raw sockets). JSON is printed and written to
bench/results/bench_cycle.json.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import time
from typing import Callable

from bench import agent_phases
from bench.codec_cost import codec_figures
from bench.common import (best_of, bench_parser, main_result, period_figures, read_period_logs, run_json, segment,
                          task_cpu_ns)



def phase_agent(args) -> dict:
    """The agent cycle with every drive enabled; the cycle thread's CPU over the phase."""
    from collections import deque

    from bus_agent.bus.dc import DcConfig
    from bus_agent.bus.pysoem_bus import PysoemBus
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import Cycle

    cfg = AgentConfig(host="bench", ifname=args.ifname, cycle_us=args.cycle_us, dc=DcConfig(mode="off"))
    cyc = Cycle(PysoemBus(args.ifname, receive_timeout_us=args.receive_timeout_us), cfg, rt_priority=args.rt_priority)
    sink: deque = deque(maxlen=64)
    cyc.snapshot_sink = sink.append
    cyc.start()
    try:
        resets = agent_phases.enable_all(cyc)
        assert cyc.thread is not None and cyc.thread.native_id is not None
        tid = cyc.thread.native_id
        c0, t0, ns0 = cyc.cycles, time.monotonic(), task_cpu_ns(tid)
        out = agent_phases.measure(cyc, args)
        el, cycles, ns = time.monotonic() - t0, cyc.cycles - c0, task_cpu_ns(tid) - ns0
        out.update(startup_fault_resets=resets, **_cpu(ns, el, cycles, args.cycle_us))
        return out
    finally:
        cyc.stop()


def phase_bare(args) -> dict:
    args.dc = "off"
    out = agent_phases.phase_bare(args)
    # one thread: the process's CPU is the loop's
    out.update(_cpu(int(out["cpu_s"] * 1e9), out["seconds"], out["cycles"], args.cycle_us))
    return out


def _cpu(ns: int, elapsed_s: float, cycles: int, cycle_us: int) -> dict:
    """The loop thread's CPU: over the elapsed time, per cycle, and per cycle over the period (% of
    a core at the full rate: not lowered by cycles a loaded host skipped)."""
    per = ns / 1e3 / cycles if cycles else None
    return {"cycle_cpu_pct": round(100 * ns / 1e9 / elapsed_s, 1) if elapsed_s else None,
            "cpu_us_per_cycle": round(per, 1) if per is not None else None,
            "cpu_pct_of_period": round(100 * per / cycle_us, 1) if per is not None else None}


def _tick_command(cyc, op: str, axes, timeout_s: float = 10.0) -> list:
    """Submit ``op`` and tick (about 2 kHz) until every axis answered; the outcomes."""
    from bus_agent.runtime import DriveCommand

    outs: list = []
    assert cyc.submit(DriveCommand(request_id=f"bench-{op}", op=op, axes=tuple(axes), on_outcome=outs.append,
                                   received_ns=time.monotonic_ns(), timeout_s=timeout_s))
    deadline = time.monotonic() + timeout_s + 2
    while len(outs) < len(axes):
        if time.monotonic() > deadline:
            raise RuntimeError(f"{op} did not finish")
        cyc.tick()
        time.sleep(0.0005)
    return outs


def phase_ticks(args) -> dict:
    """Thread CPU of one cycle, run by ``tick()`` in this process with every drive enabled and at
    rest (no waiting, no spin: the cycle's own work), next to its parts on the same segment:
    ``bare_exchange`` (pysoem send + receive), ``bus_exchange`` (PysoemBus.exchange: + the input
    check and decode), ``tick_rest`` (the fast path: drives at rest skipped), ``tick_full`` (every
    drive stepped, ``Cycle.fast_paths = False``: the work the fast path skips) and ``tick_one_moving``
    (one drive in a long move, the others at rest). ``own_us``: a tick's CPU without its exchange
    (timed inside the tick): pysoem's receive polls for the frame, so the emulator's answer time
    shows in the exchange's CPU, not in the cycle's own work. Best of interleaved runs of
    ``--tick-runs`` x 100 ticks; robust under load (CPU time, minimum)."""
    from bus_agent.bus.dc import DcConfig
    from bus_agent.bus.pysoem_bus import PysoemBus
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import Cycle

    cfg = AgentConfig(host="bench", ifname=args.ifname, cycle_us=args.cycle_us, dc=DcConfig(mode="off"))
    bus = PysoemBus(args.ifname, receive_timeout_us=args.receive_timeout_us)
    cyc = Cycle(bus, cfg, manage_gc=False, switch_interval_s=None)
    cyc.open()
    gc.collect()
    gc.freeze()
    gc.disable()  # as the agent's loop runs (Cycle.manage_gc): no collection inside a measured run
    try:
        for _ in range(200):
            cyc.tick()
            time.sleep(0.0005)
        assert cyc.latest is not None
        faulted = [d.axis for d in cyc.latest.drives if d.state in ("fault", "fault_reaction_active")]
        if faulted:
            _tick_command(cyc, "fault_reset", faulted)
        bad = [o for o in _tick_command(cyc, "enable", cyc.axes) if o.outcome != "done"]
        if bad:
            raise RuntimeError(f"enable failed: {bad[:3]}")
        m = bus._master
        timeout_us = args.receive_timeout_us
        exchange, in_exchange = bus.exchange, [0]

        def timed_exchange() -> int:
            t0 = time.thread_time_ns()
            wkc = exchange()
            in_exchange[0] += time.thread_time_ns() - t0
            return wkc

        bus.exchange = timed_exchange  # type: ignore[method-assign]  # the cycle calls it through the instance

        def bare() -> None:
            m.send_processdata()
            m.receive_processdata(timeout_us)

        def full() -> None:
            cyc.fast_paths = False
            cyc.tick()
            cyc.fast_paths = True

        for _ in range(100):
            cyc.tick()
        runs: dict[str, Callable[[], object]] = {"bare_exchange": bare, "bus_exchange": exchange,
                                                 "tick_rest": cyc.tick, "tick_full": full}
        best, own = best_of(runs, args.tick_runs, inner=in_exchange)
        stepped0, cycles0 = cyc.drives_stepped, cyc.cycles
        for _ in range(100):
            cyc.tick()
        rest_stepped = (cyc.drives_stepped - stepped0) / (cyc.cycles - cycles0)
        # one drive moving, the others at rest (a move long enough for every run)
        moving: list = []
        assert cyc.submit(_move(cyc.axes[0], moving))
        for _ in range(5):
            cyc.tick()
        b2, o2 = best_of({"tick_one_moving": cyc.tick}, args.tick_runs, inner=in_exchange)
        best.update(b2)
        own.update(o2)
        if moving:
            raise RuntimeError(f"the move ended during the runs: {moving}")
    finally:
        cyc.stop(ordered=False)
    n = args.drives
    bare_us = best["bare_exchange"]
    ticks = ("tick_rest", "tick_full", "tick_one_moving")
    return {"drives": n, "runs": args.tick_runs, "us": {k: round(v, 1) for k, v in best.items()},
            "own_us": {k: round(own[k], 1) for k in ticks}, "drives_stepped_at_rest": rest_stepped,
            "rest_beyond_bare_us_per_drive": round((best["tick_rest"] - bare_us) / n, 2),
            "full_beyond_bare_us_per_drive": round((best["tick_full"] - bare_us) / n, 2),
            "moving_drive_us": round(own["tick_one_moving"] - own["tick_rest"], 1),
            "full_over_rest": round(best["tick_full"] / best["tick_rest"], 2),
            "loadavg": list(os.getloadavg())}


def _move(axis: str, outs: list):
    from bus_agent.runtime import DriveCommand

    return DriveCommand(request_id="bench-move", op="move", axes=(axis,), args={"by": 1e7}, on_outcome=outs.append,
                        received_ns=time.monotonic_ns(), timeout_s=600.0)


PHASES = {"bare": phase_bare, "agent": phase_agent}


class _PassThrough:
    """What the cycle did before the output stage: the targets copied as they are."""

    __slots__ = ("position", "velocity", "clamps", "settled")

    def __init__(self) -> None:
        self.position = self.velocity = self.clamps = 0
        self.settled = True

    def step(self, mode: int, position: int, velocity: int) -> None:
        self.position = position
        self.velocity = velocity


def _moving_sim_cycle(drives: int, stage: bool):
    """A cycle over SimBus (injected clock: no waiting) with every drive enabled in CSP and in a
    long move; with its output stages, or with them replaced by :class:`_PassThrough`."""
    from bus_agent.bus.sim_bus import SimBus
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import Cycle

    clock = [1_000_000_000]
    bus = SimBus(drives, "generic", clock=lambda: clock[0] / 1e9)
    cyc = Cycle(bus, AgentConfig(host="bench", sim_drives=drives), clock_ns=lambda: clock[0],
                wall_ns=lambda: clock[0], manage_gc=False, switch_interval_s=None)
    cyc.open()
    if not stage:
        for d in cyc.drives:
            d.stage = _PassThrough()  # type: ignore[assignment]

    def tick() -> None:
        clock[0] += 1_000_000
        cyc.tick()

    for _ in range(20):
        tick()
    done: list = []
    from bus_agent.runtime import DriveCommand
    cyc.submit(DriveCommand(request_id="bench-enable", op="enable", axes=cyc.axes, on_outcome=done.append,
                            received_ns=clock[0], timeout_s=5.0))
    while len(done) < drives:
        tick()
    moving: list = []
    for a in cyc.axes:
        cyc.submit(_move(a, moving))
    for _ in range(300):  # past the acceleration: every axis at speed
        tick()
    return cyc, tick, moving


def stage_figures(drives: int, runs: int) -> dict:
    """The output stage's CPU (bus_agent/motion/output_stage.py; in this process, no root):
    ``step_us`` one ``OutputStage.step`` of one axis as the cycle calls it for a moving axis in
    CSP (the target within the limits: written as given), for a target beyond them (limited),
    and following (not enabled); ``tick_us``: one cycle over SimBus (its simulated drives
    included) with ``drives`` axes all moving, with the stages and with them replaced by a
    pass-through (the targets copied, as before the stage), best of ``runs`` interleaved runs of
    100 ticks; ``stage_us_per_axis`` the difference per axis and ``ratio`` the two ticks."""
    from bus_agent.motion.output_stage import MODE_CSP, OutputStage

    s_pass, s_limit, s_follow = (OutputStage(100_000, 1_000_000, 0.001) for _ in range(3))
    x = [0]

    def passing() -> None:
        x[0] += 50
        s_pass.step(MODE_CSP, x[0], 0)

    flip = [1]

    def limited() -> None:
        flip[0] = -flip[0]
        s_limit.step(MODE_CSP, flip[0] * 1_000_000, 0)

    def follow() -> None:
        s_follow.step(0, 5, 0)

    micro = best_of({"csp_within_limits": passing, "csp_limited": limited, "follow": follow}, runs, 2000)[0]
    with_stage, tick_stage, m1 = _moving_sim_cycle(drives, True)
    without, tick_plain, m2 = _moving_sim_cycle(drives, False)
    try:
        best = best_of({"with_stage": tick_stage, "pass_through": tick_plain}, runs)[0]
        if m1 or m2 or any(d.stage.clamps for d in with_stage.drives):
            raise RuntimeError(f"a move ended or was clamped during the runs: {m1 + m2}")
    finally:
        with_stage.stop(ordered=False)
        without.stop(ordered=False)
    return {"drives": drives, "runs": runs, "step_us": {k: round(v, 3) for k, v in micro.items()},
            "tick_us": {k: round(v, 1) for k, v in best.items()},
            "stage_us_per_axis": round((best["with_stage"] - best["pass_through"]) / drives, 3),
            "ratio": round(best["with_stage"] / best["pass_through"], 3)}


def _run_phase(name: str, ifname: str, drives: int, args, seconds: float, log_file: str) -> dict:
    return run_json([sys.executable, "-m", "bench.bench_cycle", "--phase", name, "--ifname", ifname, "--drives",
                     str(drives), "--seconds", str(seconds), "--cycle-us", str(args.cycle_us), "--rt-priority",
                     str(args.rt_priority), "--receive-timeout-us", str(args.receive_timeout_us), "--log-file",
                     log_file], f"phase {name} ({drives} drives)", seconds * 4 + 120)


def _merge(parts: list[dict], logs: list[str], cycle_ns: int) -> dict:
    cycles = sum(p["cycles"] for p in parts)
    seconds = sum(p["seconds"] for p in parts)
    ns = sum(p["cpu_us_per_cycle"] * 1e3 * p["cycles"] for p in parts if p["cpu_us_per_cycle"] is not None)
    return {"rounds": len(parts), "cycles": cycles, "seconds": round(seconds, 2),
            "overruns": sum(p["overruns"] for p in parts), "wkc_errors": sum(p["wkc_errors"] for p in parts),
            "startup_fault_resets": sum(p.get("startup_fault_resets", 0) for p in parts),
            "cycle_cpu_pct_per_round": [p["cycle_cpu_pct"] for p in parts],
            **_cpu(int(ns), seconds, cycles, cycle_ns // 1000), **period_figures(read_period_logs(logs), cycle_ns)}


def run(args) -> dict:
    load_start = list(os.getloadavg())
    sizes = {}
    for drives in args.drives:
        with segment("bcy", drives, args.sim_rt_priority) as seg:
            parts: dict[str, list[dict]] = {p: [] for p in PHASES}
            logs: dict[str, list[str]] = {p: [] for p in PHASES}
            per_round = args.seconds / args.rounds
            for r in range(args.rounds):
                for name in PHASES:
                    print(f"bench_cycle: {drives} drives, round {r + 1}/{args.rounds}, {name} ({per_round:g} s)...",
                          file=sys.stderr, flush=True)
                    log_file = os.path.join(seg.workdir, f"{name}-{r}.periods")
                    parts[name].append(_run_phase(name, seg.master_if, drives, args, per_round, log_file))
                    logs[name].append(log_file)
            res = {name: _merge(parts[name], logs[name], args.cycle_us * 1000) for name in PHASES}
            print(f"bench_cycle: {drives} drives, ticks...", file=sys.stderr, flush=True)
            ticks = run_json([sys.executable, "-m", "bench.bench_cycle", "--phase", "ticks", "--ifname", seg.master_if,
                              "--drives", str(drives), "--receive-timeout-us", str(args.receive_timeout_us),
                              "--tick-runs", str(args.tick_runs)], f"phase ticks ({drives} drives)", 300)
        bare, agent = res["bare"], res["agent"]
        extra = (agent["cpu_us_per_cycle"] - bare["cpu_us_per_cycle"]) / drives
        sizes[str(drives)] = {
            "phases": res, "beyond_bare_us_per_drive": round(extra, 2),
            "cpu_over_bare": round(agent["cpu_us_per_cycle"] / bare["cpu_us_per_cycle"], 2),
            "jitter_p999_over_bare": (round(agent["jitter_us"]["p999"] / bare["jitter_us"]["p999"], 2)
                                      if bare["jitter_us"]["p999"] else None),
            "ticks": ticks}
    return {"drives": args.drives, "cycle_us": args.cycle_us, "seconds_per_phase": args.seconds, "rounds": args.rounds,
            "rt_priority": args.rt_priority, "sizes": sizes,
            "codec": codec_figures(max(args.drives), args.codec_cycles),
            "stage": stage_figures(min(args.drives), args.tick_runs),
            "loadavg_start": load_start, "loadavg": list(os.getloadavg()), "cpus": os.cpu_count(),
            "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_cycle", __doc__)
    p.add_argument("--drives", type=lambda v: [int(x) for x in v.split(",") if x], default=[16, 64],
                   help="drive counts, comma-separated (default 16,64)")
    p.add_argument("--seconds", type=float, default=20.0, help="seconds per phase and drive count (default 20)")
    p.add_argument("--rounds", type=int, default=2, help="phases alternate in this many rounds (default 2)")
    p.add_argument("--cycle-us", type=int, default=1000)
    p.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority of the loop thread (0: off)")
    p.add_argument("--sim-rt-priority", type=int, default=20, help="SCHED_FIFO priority of ecat-sim (0: off)")
    p.add_argument("--receive-timeout-us", type=int, default=1000)
    p.add_argument("--codec-cycles", type=int, default=3000, help="cycles of the codec microbenchmark (default 3000)")
    p.add_argument("--tick-runs", type=int, default=30, help="interleaved runs of 100 ticks each (default 30)")
    p.add_argument("--phase", choices=sorted(PHASES) + ["ticks"], help=argparse.SUPPRESS)
    p.add_argument("--stage-only", action="store_true",
                   help="only the output stage's figures (no root; printed, not written)")
    p.add_argument("--ifname", help=argparse.SUPPRESS)
    p.add_argument("--log-file", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.stage_only:
        print(json.dumps(stage_figures(min(args.drives), args.tick_runs), indent=2), flush=True)
        return 0
    if args.phase:
        args.drives = args.drives[0]
        print(json.dumps(phase_ticks(args) if args.phase == "ticks" else PHASES[args.phase](args)), flush=True)
        return 0
    return main_result("bench_cycle", lambda: run(args), args.out)


if __name__ == "__main__":
    sys.exit(main())
