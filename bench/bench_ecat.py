"""Benchmark: unmodified pysoem cycling against ``ecat-sim`` over a veth pair.

    python -m bench.bench_ecat --drives 16 --seconds 60 --cycle-us 1000 [--out FILE]
    python -m bench.bench_ecat --drives 16 --esi tests/esi/quirks.xml*16 --dc-cycle-ns 1000000

Brings the segment to OP, then runs send_processdata + receive_processdata on drift-free
deadlines (t0 + k * cycle). Reports round-trip percentiles, missed frames (no answer within
the receive timeout), WKC errors (answer with a wrong working counter), deadline overruns
and the emulator's CPU time per frame (from /proc/<pid>/stat). Prints JSON and writes
bench/results/bench_ecat.json. Needs root (veth, raw sockets).
"""

from __future__ import annotations

import gc
import os
import sys
import time

from bench.common import bench_parser, main_result, percentile, pysoem_to_op, proc_cpu_s, segment, set_rt_priority


def run(args) -> dict:
    import pysoem

    from bus_agent.sim.ecat.control import ControlClient

    with segment("ecb", args.drives, args.sim_rt_priority, esi=args.esi) as seg:
        control = ControlClient(seg.control_path)
        m = pysoem.Master()
        try:
            set_rt_priority(args.master_rt_priority, required=True)
            return _measure(m, seg, control, args, pysoem)
        finally:
            try:
                m.state = pysoem.INIT_STATE
                m.write_state()
                m.close()
            except Exception:
                pass
            control.close()


def _measure(m, seg, control, args, pysoem) -> dict:
    expected = pysoem_to_op(m, seg.master_if, args.drives, args.timeout_us, args.dc_cycle_ns)

    cycles = int(args.seconds * 1e6 / args.cycle_us)
    cycle_s = args.cycle_us / 1e6
    rtts: list[float] = [0.0] * cycles
    missed = wkc_errors = overruns = 0
    send, receive, timeout_us = m.send_processdata, m.receive_processdata, args.timeout_us
    perf, sleep = time.perf_counter, time.sleep
    counters0 = control.request("status")["counters"]
    cpu0 = proc_cpu_s(seg.sim.pid)
    gc.collect()
    gc.disable()
    t0 = perf()
    for k in range(cycles):
        start = perf()
        send()
        wkc = receive(timeout_us)
        end = perf()
        rtts[k] = (end - start) * 1e6
        if wkc <= 0:
            missed += 1
        elif wkc != expected:
            wkc_errors += 1
        next_t = t0 + (k + 1) * cycle_s
        delay = next_t - perf()
        if delay > 0:
            sleep(delay)
        else:
            overruns += 1
    elapsed = perf() - t0
    gc.enable()
    cpu1 = proc_cpu_s(seg.sim.pid)
    counters1 = control.request("status")["counters"]
    frames = counters1["frames"] - counters0["frames"]
    rtts.sort()
    return {
        "drives": args.drives, "esi": args.esi, "cycle_us": args.cycle_us, "seconds": round(elapsed, 3), "cycles": cycles,
        "frames": frames, "frames_per_cycle": round(frames / cycles, 2) if cycles else 0,
        "expected_wkc": expected,
        "rtt_us": {"p50": round(percentile(rtts, 0.5), 1), "p99": round(percentile(rtts, 0.99), 1),
                   "p999": round(percentile(rtts, 0.999), 1), "max": round(rtts[-1], 1) if rtts else None},
        "missed": missed, "missed_pct": round(100.0 * missed / cycles, 4) if cycles else 0,
        "wkc_errors": wkc_errors, "overruns": overruns,
        "sim_cpu_pct": round(100.0 * (cpu1 - cpu0) / elapsed, 1),
        "sim_cpu_us_per_frame": round((cpu1 - cpu0) / frames * 1e6, 1) if frames else None,
        "sim_counters": {k: counters1[k] - counters0[k] for k in counters1},
        "sim_rt_priority": args.sim_rt_priority, "master_rt_priority": args.master_rt_priority,
        "loadavg_1m": os.getloadavg()[0], "cpus": os.cpu_count(),
    }


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_ecat", __doc__)
    p.add_argument("--drives", type=int, default=16)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--cycle-us", type=int, default=1000)
    p.add_argument("--timeout-us", type=int, default=2000, help="receive_processdata timeout")
    p.add_argument("--sim-rt-priority", type=int, default=20, help="SCHED_FIFO priority of ecat-sim (0: off)")
    p.add_argument("--master-rt-priority", type=int, default=10, help="SCHED_FIFO priority of this master (0: off)")
    p.add_argument("--esi", metavar="SPEC", help="slaves from an ESI file: ecat-sim --esi SPEC (e.g. "
                   "tests/esi/quirks.xml*16: 1-bit and padding entries, bit-level images)")
    p.add_argument("--dc-cycle-ns", type=int, default=0, help="config_dc and SYNC0 at this cycle before OP "
                   "(slaves whose ESI offers only DC need it)")
    args = p.parse_args(argv)
    return main_result("bench_ecat", lambda: run(args), args.out)


if __name__ == "__main__":
    sys.exit(main())
