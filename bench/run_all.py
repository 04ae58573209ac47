"""Run the benchmarks one after the other and write the headline figures of this run.

    python -m bench.run_all [--quick] [--only NAME,...] [--summarize-only] [--markdown]   (``make bench``)

Each benchmark of :data:`BENCHMARKS` runs in its own process, in order, writing its JSON under
bench/results/ (``--quick``: short versions under bench/results/quick/, so the full figures are
left alone). The summary, ``summary.json`` in the same directory, is built only from what this
invocation ran (:mod:`bench.summary`):

- a run that exited 0 and wrote its JSON during this invocation shows its figures and targets;
- a failed run shows ``failed (exit N)`` and a skipped one (root needed) ``skipped``, with no
  figures, even when an older JSON is on disk;
- a benchmark not run this time (``--only``, ``--summarize-only``) shows its older JSON as
  ``stale``, with that JSON's time stamp, and its targets do not count.

The summary also holds this invocation's UTC time stamps and the machine's load average at the
start and end, and around every run. ``--markdown`` prints the README table of the summary on
disk. Exit status 0 only if every benchmark run this time succeeded.

Adding a benchmark is one :class:`Benchmark` entry in :data:`BENCHMARKS`: its name, what it
measures, the module, its arguments in full and quick mode (run_all appends ``--out FILE``), whether
it needs root, and three functions of its JSON: ``figures`` (a dict for summary.json), ``headline``
(one line for the README table) and ``targets`` (a list of :class:`bench.summary.Target`).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

from bench import summary as s
from bench import summary_fleet as sf
from bench.common import RESULTS, ROOT, loadavg


@dataclass(frozen=True)
class Benchmark:
    """One row of the summary: how to run a benchmark and how to read its JSON."""

    name: str
    what: str
    module: str
    full: tuple[str, ...]
    quick: tuple[str, ...]
    root: bool
    figures: Callable[[Mapping[str, Any]], dict]
    headline: Callable[[Mapping[str, Any]], str]
    targets: Callable[[Mapping[str, Any]], list[s.Target]]


BENCHMARKS: tuple[Benchmark, ...] = (
    Benchmark("ecat_16", "pysoem against ecat-sim, 16 drives, 1 kHz", "bench.bench_ecat",
              ("--drives", "16", "--seconds", "60"), ("--drives", "16", "--seconds", "5"), True,
              s.ecat_figures, s.ecat_headline, s.ecat_targets),
    Benchmark("ecat_64", "pysoem against ecat-sim, 64 drives (2 frames per cycle)", "bench.bench_ecat",
              ("--drives", "64", "--seconds", "60"), ("--drives", "64", "--seconds", "3"), True,
              s.ecat_figures, s.ecat_headline, s.no_targets),
    Benchmark("ecat_16_esi", "pysoem against ecat-sim, 16 drives from tests/esi/quirks.xml (bit-level images, "
              "SYNC0), 1 kHz", "bench.bench_ecat",
              ("--drives", "16", "--esi", "tests/esi/quirks.xml*16", "--dc-cycle-ns", "1000000", "--seconds", "60"),
              ("--drives", "16", "--esi", "tests/esi/quirks.xml*16", "--dc-cycle-ns", "1000000", "--seconds", "5"),
              True, s.ecat_figures, s.ecat_headline, s.no_targets),
    Benchmark("agent", "agent cycle (16 drives, 1 kHz) next to a bare pysoem loop; gateway under Zenoh load; "
              "16-drive enable latency", "bench.bench_agent",
              ("--seconds", "60", "--rounds", "6", "--rt-priority", "10"),
              ("--seconds", "8", "--rounds", "2", "--rt-priority", "10", "--enable-rounds", "10"), True,
              s.agent_figures, s.agent_headline, s.agent_targets),
    Benchmark("agent_dc", "agent cycle with 16 DC drives (omron1s:dc-required: predefined PDOs, SYNC0, PI) next to "
              "a bare pysoem loop on the same segment; frame-to-SYNC0 offset", "bench.bench_agent",
              ("--profile", "omron1s:dc-required", "--no-gateway", "--enable-rounds", "0", "--seconds", "60",
               "--rounds", "6", "--rt-priority", "10"),
              ("--profile", "omron1s:dc-required", "--no-gateway", "--enable-rounds", "0", "--seconds", "6",
               "--rounds", "2", "--rt-priority", "10"), True,
              s.agent_dc_figures, s.agent_dc_headline, s.agent_dc_targets),
    Benchmark("cycle_cpu", "the cycle thread's CPU per drive, 16 and 64 drives at 1 kHz, next to a bare pysoem loop; "
              "codec CPU next to the fixed structs", "bench.bench_cycle",
              ("--drives", "16,64", "--seconds", "30", "--rounds", "3", "--rt-priority", "10"),
              ("--drives", "16,64", "--seconds", "4", "--rounds", "1", "--rt-priority", "10", "--tick-runs", "10"), True,
              s.cycle_figures, s.cycle_headline, s.cycle_targets),
    Benchmark("idle", "the idle demo (bus-agent --sim 4): CPU per process and thread; the cycle's spin fixed "
              "against adaptive and none", "bench.bench_idle", ("--seconds", "20", "--rounds", "2"),
              ("--seconds", "4", "--rounds", "1"), False, s.idle_figures, s.idle_headline, s.idle_targets),
    Benchmark("supervisor", "two-phase enable/disable of 4x16 and 32x32 drives; status fan-in", "bench.bench_supervisor",
              (), ("--sizes", "4x16", "--rounds", "1", "--gets", "50"), False,
              sf.supervisor_figures, sf.supervisor_headline, sf.supervisor_targets),
    Benchmark("canopen", "CAN agent, 8 nodes, 1 ms and 4 ms SYNC, next to a bare python-can SYNC loop",
              "bench.bench_canopen", ("--seconds", "30", "--rt-priority", "10"),
              ("--seconds", "3", "--rt-priority", "10"), True,
              s.canopen_figures, s.canopen_headline, s.canopen_targets),
    Benchmark("security", "mutual TLS + ACL against plain TCP in the same run: 16-drive enable, status fan-in",
              "bench.bench_security", ("--rounds", "50", "--fanin", "8x32", "--fanin-rounds", "12"), ("--quick",), False,
              sf.security_figures, sf.security_headline, sf.security_targets),
    Benchmark("trust", "the audit trail per 16-drive command and error texts per status, next to the gateway's "
              "own work", "bench.bench_trust", ("--rounds", "2000"), ("--rounds", "200"), False,
              sf.trust_figures, sf.trust_headline, sf.trust_targets),
    Benchmark("recorder", "flight recorder cost: cycle jitter and CPU with and without it, 16 drives, 1 kHz",
              "bench.bench_recorder", ("--seconds", "20", "--rounds", "3", "--rt-priority", "10"),
              ("--seconds", "3", "--rounds", "1", "--rt-priority", "10"), False,
              s.recorder_figures, s.recorder_headline, s.recorder_targets),
    Benchmark("enable_16", "command latency: enable of 16 drives beyond their transition cycles, next to a bare "
              "zenoh get", "bench.bench_agent",
              ("--drives", "16", "--seconds", "2", "--rounds", "1", "--no-gateway", "--enable-rounds", "100",
               "--rt-priority", "10"),
              ("--drives", "16", "--seconds", "1", "--rounds", "1", "--no-gateway", "--enable-rounds", "10",
               "--rt-priority", "10"), True, s.enable_figures, s.enable_headline, s.enable_targets),
    Benchmark("enable_64", "command latency: enable of 64 drives beyond their transition cycles, next to a bare "
              "zenoh get", "bench.bench_agent",
              ("--drives", "64", "--seconds", "2", "--rounds", "1", "--no-gateway", "--enable-rounds", "100",
               "--rt-priority", "10"),
              ("--drives", "64", "--seconds", "1", "--rounds", "1", "--no-gateway", "--enable-rounds", "10",
               "--rt-priority", "10"), True, s.enable_figures, s.enable_headline, s.enable_targets),
    Benchmark("reflex", "cross-host group reflex over namespaced hosts and routers, next to a bare zenoh put "
              "across the same routers", "bench.bench_reflex", ("--rounds", "50", "--bare", "500"),
              ("--rounds", "8", "--bare", "100"), True, sf.reflex_figures, sf.reflex_headline, sf.reflex_targets),
    Benchmark("motion", "16 axes moving at 1 kHz over ecat-sim: cycle jitter and CPU with motion vs idle vs bare, "
              "query to first target, synchronized arrival spread", "bench.bench_motion",
              ("--seconds", "60", "--rounds", "3", "--rt-priority", "10"),
              ("--seconds", "6", "--rounds", "1", "--rt-priority", "10", "--latency-moves", "10", "--sync-moves", "3"),
              True, s.motion_figures, s.motion_headline, s.motion_targets),
    Benchmark("replies", "CPU of the command reply path per 16/64-drive command, next to bare msgpack",
              "bench.bench_replies", ("--rounds", "500"), ("--rounds", "50"), False,
              sf.replies_figures, sf.replies_headline, s.no_targets),
    Benchmark("dashboard", "drives-dashboard with 1024 drives in headless chromium: CPU, change-to-page time",
              "bench.bench_dashboard", ("--rounds", "20", "--idle-s", "10"), ("--rounds", "4", "--idle-s", "3"),
              False, s.dashboard_figures, s.dashboard_headline, s.dashboard_targets),
    Benchmark("twin", "drives-twin start to ready (3, 10, 32 simulated hosts of 2 drives) and CPU at rest, next to "
              "the bare router and agents", "bench.bench_twin", ("--hosts", "3,10,32", "--rest-s", "10"),
              ("--hosts", "3,10", "--rest-s", "3", "--settle-s", "2"), False,
              sf.twin_figures, sf.twin_headline, sf.twin_targets),
    Benchmark("chaos", "chaos soak: a 3-host twin under a seeded schedule of commands, malformed commands, faults, "
              "unplugs, WKC faults, link cuts, agent and router kills; every promise checked from outside",
              "bench.chaos", ("--seconds", "240", "--seed", "1", "--report-only"),
              ("--seconds", "60", "--seed", "1", "--report-only"), False,
              sf.chaos_figures, sf.chaos_headline, sf.chaos_targets),
    Benchmark("chaos_ecat", "chaos soak over pysoem and ecat-sim: the same twin with each host's agent and segment "
              "in a network namespace", "bench.chaos",
              ("--backend", "ecat", "--seconds", "120", "--seed", "1", "--report-only"),
              ("--backend", "ecat", "--seconds", "30", "--seed", "1", "--report-only"), True,
              sf.chaos_figures, sf.chaos_headline, sf.chaos_targets),
    Benchmark("opcua", "drives-opcua with 1024 drives (real sim agents): CPU at rest, fault to an OPC UA client's data "
              "change next to a plain Fleet subscriber", "bench.bench_opcua", ("--rounds", "20", "--idle-s", "10"),
              ("--rounds", "4", "--idle-s", "3"), False, sf.opcua_figures, sf.opcua_headline, sf.opcua_targets),
)


def utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _load(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def run_one(b: Benchmark, quick: bool, path: Path) -> tuple[str, dict[str, Any]]:
    """Run benchmark ``b`` writing ``path``; (status, time stamps and load around the run)."""
    run: dict[str, Any] = {"started": utc_now(), "loadavg_start": loadavg()}
    if b.root and os.geteuid() != 0:
        print(f"run_all: {b.name} skipped: needs root (veth pairs, raw sockets)", file=sys.stderr)
        return "skipped: needs root", run
    argv = [sys.executable, "-m", b.module, *(b.quick if quick else b.full), "--out", str(path)]
    print(f"run_all: {b.name}: {' '.join(argv[1:])}", file=sys.stderr, flush=True)
    t0_wall, t0 = time.time(), time.monotonic()
    rc = subprocess.run(argv, cwd=ROOT, stdout=subprocess.DEVNULL).returncode
    run.update(finished=utc_now(), seconds=round(time.monotonic() - t0, 1), loadavg_end=loadavg(),
               argv=argv[2:])
    if rc != 0:
        status = f"failed (exit {rc})"
    elif not path.exists() or path.stat().st_mtime < t0_wall:
        status = "failed: exit 0 but no JSON written by this run"
    else:
        status = s.OK
    print(f"run_all: {b.name}: {status} in {run['seconds']:.0f} s", file=sys.stderr, flush=True)
    return status, run


def collect(quick: bool, only: set[str] | None, summarize_only: bool, out: Path) -> dict[str, Any]:
    """Run the selected benchmarks; the summary of this invocation."""
    summary: dict[str, Any] = {"time": utc_now(), "mode": "quick" if quick else "full", "cpus": os.cpu_count(),
                               "loadavg_start": loadavg(), "rows": []}
    for b in BENCHMARKS:
        path = out / f"bench_{b.name}.json"
        if summarize_only or (only is not None and b.name not in only):
            data = _load(path)
            run = {"json_written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(path.stat().st_mtime))} \
                if data is not None else None
            summary["rows"].append(s.build_row(b.name, b.what, s.STALE if data is not None else s.NOT_RUN, data,
                                               b.figures, b.targets, run, b.headline))
            continue
        status, run = run_one(b, quick, path)
        data = _load(path) if status == s.OK else None
        summary["rows"].append(s.build_row(b.name, b.what, status, data, b.figures, b.targets, run, b.headline))
    summary["loadavg_end"] = loadavg()
    summary["targets"] = s.overall(summary["rows"])
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.run_all", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="short runs, results under bench/results/quick/")
    p.add_argument("--only", type=lambda v: {x for x in v.split(",") if x},
                   help=f"comma-separated names to run ({', '.join(b.name for b in BENCHMARKS)}); the others stale")
    p.add_argument("--summarize-only", action="store_true", help="run nothing: every row stale (or not run)")
    p.add_argument("--markdown", action="store_true", help="print the README table of the summary on disk")
    args = p.parse_args(argv)
    out = RESULTS / "quick" if args.quick else RESULTS
    if args.markdown:
        summary = _load(out / "summary.json")
        if summary is None:
            print(f"run_all: no summary at {out / 'summary.json'}", file=sys.stderr)
            return 1
        print(s.render_markdown(summary), end="")
        return 0
    unknown = (args.only or set()) - {b.name for b in BENCHMARKS}
    if unknown:
        p.error(f"unknown benchmark(s): {', '.join(sorted(unknown))}")
    out.mkdir(parents=True, exist_ok=True)
    summary = collect(args.quick, args.only, args.summarize_only, out)
    text = json.dumps(summary, indent=1)
    print(text)
    (out / "summary.json").write_text(text + "\n")
    ran = [r for r in summary["rows"] if r["status"] not in (s.STALE, s.NOT_RUN)]
    return 0 if all(r["status"] == s.OK for r in ran) else 1


if __name__ == "__main__":
    sys.exit(main())
