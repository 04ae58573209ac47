"""The flight recorder's cost in the cycle: 16 drives at 1 kHz, recorder off and on in one run.

    python -m bench.bench_recorder [--drives 16] [--seconds 10] [--rounds 3] [--rt-priority 0] [--out FILE]

The agent's real cycle thread (``Cycle.start``) on the in-process ``SimBus`` (no root needed),
alternating phases without and with the recorder (``[recorder] seconds = 10``), each
``--seconds`` long, ``--rounds`` times, the cycle spinning before each deadline as an operating
agent's does (``spin_at_rest``: the drives stay off, so that the in-process drive models do
not make most of the CPU; with every drive off the agent itself only sleeps); per phase the period jitter (|period - 1 ms|) p50, p99,
p99.9 and max, overruns, and the process CPU per wall second. Also the bare cost of one
``Recorder.record`` call for the same drives (a tight loop, no cycle around it). Jitter and CPU
of the two modes come from the same run (ratios on against off); the machine's load average is
recorded with the figures.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from bench.common import bench_parser, loadavg, quantiles, run_stamp, write_result
from bus_agent.bus.sim_bus import SimBus
from bus_agent.config import AgentConfig, RecorderConfig
from bus_agent.cycle.cycle import Cycle
from bus_agent.cycle.recorder import Recorder


def phase(drives: int, seconds: float, record: bool, rt_priority: int) -> dict[str, Any]:
    cfg = AgentConfig(host="bench", sim_drives=drives, cycle_us=1000,
                      recorder=RecorderConfig(seconds=10.0 if record else 0.0))
    cycle = Cycle(SimBus(drives, sm_watchdog_s=1.0), cfg, record_periods=int(seconds * 1000) + 2000,
                  rt_priority=rt_priority)
    cycle.spin_at_rest = True
    cycle.start()
    time.sleep(0.5)  # settle; the period log starts at the first cycle, cut below
    start_len = cycle.period_log_len
    cpu0, t0 = time.process_time(), time.monotonic()
    time.sleep(seconds)
    cpu1, t1 = time.process_time(), time.monotonic()
    end_len = cycle.period_log_len
    overruns = cycle.overruns
    cycle.stop()
    assert cycle.period_log is not None
    periods = sorted(abs(p - 1_000_000) / 1000 for p in cycle.period_log[start_len:end_len])
    return {"record": record, "cycles": len(periods), "overruns": overruns,
            "jitter_us": quantiles(periods, ("p50", "p99", "p999", "max"), digits=3),
            "cpu_pct": round(100 * (cpu1 - cpu0) / (t1 - t0), 1),
            "memory_bytes": cycle.recorder.memory_bytes if cycle.recorder else 0}


def record_call_ns(drives: int, calls: int = 4000, repeats: int = 5) -> float:
    """CPU time (thread time) of one ``Recorder.record`` for ``drives`` drives, no cycle around
    it: the lowest mean of ``repeats`` runs of ``calls`` (min-of-N: what other processes do to
    the caches while it runs does not inflate it)."""
    return min(_record_call_mean_ns(drives, calls) for _ in range(repeats))


def _record_call_mean_ns(drives: int, calls: int) -> float:
    from types import SimpleNamespace

    from bus_agent.bus.pdo import DriveInputs

    # what the recorder reads of a drive (recorder.RecordedDrive): the targets as written, in ``out``
    ds = [SimpleNamespace(inputs=DriveInputs(0x0237, i, i, i, 8, 0), index=i, controlword=0x000F,
                          out=SimpleNamespace(target_position=i, target_velocity=0, target_torque=0))
          for i in range(drives)]
    rec = Recorder([f"a{i}" for i in range(drives)], 1000)
    t0 = time.thread_time_ns()
    for c in range(calls):
        rec.record(c, c, 1_000_000, 3 * drives, ds, ())
    return (time.thread_time_ns() - t0) / calls


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_recorder", __doc__)
    p.add_argument("--drives", type=int, default=16)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--rt-priority", type=int, default=0)
    a = p.parse_args(argv)
    load_start = loadavg()
    phases = []
    for _ in range(a.rounds):
        for record in (False, True):
            phases.append(phase(a.drives, a.seconds, record, a.rt_priority))

    def merged(record: bool) -> dict[str, Any]:
        ps = [x for x in phases if x["record"] is record]
        return {"jitter_p99_us": max(x["jitter_us"]["p99"] for x in ps),
                "jitter_p999_us": max(x["jitter_us"]["p999"] for x in ps),
                "jitter_max_us": max(x["jitter_us"]["max"] for x in ps),
                "cpu_pct": round(sum(x["cpu_pct"] for x in ps) / len(ps), 1),
                "overruns": sum(x["overruns"] for x in ps), "cycles": sum(x["cycles"] for x in ps)}

    off, on = merged(False), merged(True)
    call_ns = record_call_ns(a.drives)
    result = {
        "benchmark": "recorder", **run_stamp(load_start), "drives": a.drives, "cycle_us": 1000,
        "seconds_per_phase": a.seconds, "rounds": a.rounds, "rt_priority": a.rt_priority,
        "off": off, "on": on,
        "ratio_on_off": {k: (round(on[k] / off[k], 2) if off[k] else None)
                         for k in ("jitter_p99_us", "jitter_p999_us", "cpu_pct")},
        "record_call_us": round(call_ns / 1000, 2),
        "record_call_pct_of_period": round(call_ns / 1e4, 2),
        "memory_bytes": next((x["memory_bytes"] for x in phases if x["record"]), 0),
        "phases": phases,
    }
    write_result(result, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
