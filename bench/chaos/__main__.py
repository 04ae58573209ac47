"""The chaos soak: a twin of three hosts under a seeded schedule of commands and faults, every
promise checked from outside.

    python -m bench.chaos [--seconds 60] [--seed 1] [--backend sim|ecat] [--out FILE] [--schedule-out FILE]
    python -m bench.chaos --seed 1 --seconds 60 --print-schedule      # the schedule alone, nothing run
    python -m bench.chaos --self-test                                  # every monitor shown able to fail

Real processes (``drives-twin``'s router, one bus agent per host behind a cuttable link; with
``--backend ecat``, as root, pysoem against ``ecat-sim`` in a namespace per host). A plain Zenoh
client speaking the README's wire contract sends commands (and malformed ones) and injects drive
faults, unplugs and WKC faults on ``drives/@sim/...``, while the twin cuts links, SIGKILLs and
restarts agents and the router, on a schedule drawn from ``--seed`` (the same seed and length give
the same schedule; it is written to ``--schedule-out``). Monitors written against the contract
alone judge the statuses, events, replies and flight recordings (bench/chaos/monitors.py). The
JSON result counts commands, faults and the cases each monitor checked, and lists every
violation; the exit status is 1 on any violation (or when the harness itself failed), else 0.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from twin import TwinError

from bench.common import RESULTS, bench_parser, loadavg, run_stamp, write_result

from .monitors import MONITORS, REFLEX_REMOTE_DEADLINE_MS, group_reflex, run_monitors
from .run import Soak
from .schedule import make_schedule, schedule_json
from .selftest import self_test
from .trace import Trace, trace_from_json

#: Most violations listed in full in the result (every one is counted).
MAX_LISTED = 200


def verdict(soak: Soak, seed: int, seconds: float, backend: str, reflex_deadline_ms: float,
            load0: list[float], elapsed_s: float, schedule_out: Path) -> dict[str, Any]:
    """The result JSON of a finished soak."""
    tr = soak.trace
    results = run_monitors(tr)
    results["group_reflex"] = group_reflex(tr, reflex_deadline_ms)
    violations = [asdict(v) for r in results.values() for v in r.violations]
    c = soak.counts
    return {
        "benchmark": "chaos", "seed": seed, "seconds": seconds, "backend": backend, **run_stamp(load0),
        "elapsed_s": round(elapsed_s, 1), "schedule": str(schedule_out),
        "replay": f"python -m bench.chaos --seed {seed} --seconds {seconds:g} --backend {backend}",
        "counts": {
            "commands": sum(c.commands.values()), "commands_by_op": dict(sorted(c.commands.items())),
            "malformed": c.commands.get("malformed", 0), "replies": sum(len(x.replies) for x in tr.commands),
            "faults_injected": sum(c.injections.values()), "injections": dict(sorted(c.injections.items())),
            "injections_refused": c.injections_refused, "statuses_seen": len(tr.statuses),
            "events_seen": len(tr.events), "recordings": c.recordings, "recordings_missed": c.recordings_missed,
            "recorded_cycles": sum(r.n_cycles for r in tr.recordings),
        },
        "reflex_remote_deadline_ms": reflex_deadline_ms,
        "monitors": {n: {"promise": MONITORS[n][0], "checked": r.checked, "skipped": r.skipped,
                         "violations": len(r.violations), **r.figures} for n, r in results.items()},
        "violations_total": len(violations),
        "violations": violations[:MAX_LISTED],
        "harness_errors": c.harness_errors,
    }


def trace_json(tr: Trace) -> dict[str, Any]:
    """The trace as JSON, without the flight recordings (large; their verdict is in the result)."""
    return {k: [asdict(x) for x in v] if isinstance(v, list) and k != "unexpected_exits" else v
            for k, v in ((f, getattr(tr, f)) for f in ("hosts", "groups", "statuses", "agents", "events", "commands",
                                                        "injections", "unexpected_exits", "processes", "sim_in_agent",
                                                        "final_ns"))} | {
        "final": {r: asdict(s) if s else None for r, s in tr.final.items()}}


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("chaos", __doc__)
    p.set_defaults(out=RESULTS / "chaos.json")
    p.add_argument("--seconds", type=float, default=60.0, help="length of the schedule")
    p.add_argument("--seed", type=int, default=1, help="the schedule's seed (same seed, same schedule)")
    p.add_argument("--backend", choices=("sim", "ecat"), default="sim",
                   help="the twin's drives: simulated in the agent, or pysoem against ecat-sim (root)")
    p.add_argument("--reflex-deadline-ms", type=float, default=REFLEX_REMOTE_DEADLINE_MS,
                   help="a remote group member's reflex deadline")
    p.add_argument("--schedule-out", type=Path, help="the schedule's JSON (default: next to --out)")
    p.add_argument("--print-schedule", action="store_true", help="print the schedule's JSON and exit")
    p.add_argument("--report-only", action="store_true",
                   help="exit 0 when the soak ran, whatever it found (run_all: the violations are its target)")
    p.add_argument("--self-test", action="store_true", help="feed each monitor a trace that breaks it and one that "
                                                             "keeps it; exit 1 unless each tells them apart")
    p.add_argument("--judge", type=Path, metavar="TRACE",
                   help="judge a saved *.trace.json again (no recordings: wire_limits checks nothing) and print the "
                        "monitors' verdicts")
    args = p.parse_args(argv)
    if args.judge:
        tr = trace_from_json(json.loads(args.judge.read_text()))
        results = run_monitors(tr)
        results["group_reflex"] = group_reflex(tr, args.reflex_deadline_ms)
        print(json.dumps({n: {"checked": r.checked, "skipped": r.skipped, **r.figures,
                              "violations": [asdict(v) for v in r.violations]} for n, r in results.items()}, indent=1))
        return 1 if any(r.violations for r in results.values()) else 0
    if args.self_test:
        out = self_test()
        print(json.dumps(out, indent=2))
        return 0 if out["ok"] else 1
    steps = make_schedule(args.seed, args.seconds)
    sched = schedule_json(args.seed, args.seconds, steps)
    if args.print_schedule:
        print(json.dumps(sched, indent=1))
        return 0
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    schedule_out = args.schedule_out or args.out.with_name(args.out.stem + ".schedule.json")
    schedule_out.parent.mkdir(parents=True, exist_ok=True)
    schedule_out.write_text(json.dumps(sched, indent=1) + "\n")
    print(f"chaos: seed {args.seed}, {args.seconds:g} s, {len(steps)} steps (schedule {schedule_out})",
          file=sys.stderr, flush=True)
    load0, t0 = loadavg(), time.monotonic()
    soak = Soak(steps, args.seed)
    try:
        soak.run(args.backend)
    except TwinError as exc:  # the twin did not start: nothing was judged, and the result says why
        soak.counts.harness_errors.append(f"the twin did not start: {exc}")
    result = verdict(soak, args.seed, args.seconds, args.backend, args.reflex_deadline_ms, load0,
                     time.monotonic() - t0, schedule_out)
    write_result(result, args.out)
    trace_out = args.out.with_name(args.out.stem + ".trace.json")
    trace_out.write_text(json.dumps(trace_json(soak.trace)) + "\n")
    print(f"chaos: what was seen (without the recordings): {trace_out}", file=sys.stderr)
    for name, m in result["monitors"].items():
        print(f"chaos: {name}: {m['checked']} checked, {m['skipped']} skipped, {m['violations']} violations",
              file=sys.stderr)
    return 0 if args.report_only else 1 if result["violations_total"] or result["harness_errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
