"""What the benchmarks share: the virtual segment (veth pair + ``ecat-sim``), real-time
priority, the bare drift-free timing loop, process CPU time, percentiles, and writing a result
(time stamp, load average, JSON printed and written).

A benchmark that needs a segment writes::

    with segment("ecb", drives=16, sim_rt_priority=20) as seg:
        master = pysoem.Master(); master.open(seg.master_if) ...

The pair is named ``<prefix><pid % 100000>`` so parallel runs do not collide, and it is
removed (with the emulator stopped and its work directory deleted) however the block ends.
Needs root (veth pairs, raw sockets).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import logging
import os
import resource
import select
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from array import array
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
#: How long ecat-sim may take to print its ready line.
SIM_READY_TIMEOUT_S = 20.0
#: The timing loops sleep until this long before a deadline, then spin (as the agent's cycle does).
SPIN_NS = 150_000


@dataclass(frozen=True)
class Segment:
    """A running virtual EtherCAT segment: give ``master_if`` to pysoem."""

    master_if: str
    sim_if: str
    workdir: str
    control_path: str
    sim: subprocess.Popen


@contextlib.contextmanager
def segment(prefix: str, drives: int, sim_rt_priority: int = 20, profile: str = "generic",
            esi: str | None = None) -> Iterator[Segment]:
    """veth pair up, ``ecat-sim`` with ``drives`` drives of ``profile`` (or of ``esi``, an
    ``--esi`` spec) on its far end (SCHED_FIFO ``sim_rt_priority``, 0: off), ready to be scanned;
    everything torn down on exit."""
    from bus_agent.sim.netns import pair_names, veth_down, veth_up

    master_if, sim_if = pair_names(f"{prefix}{os.getpid() % 100000:05d}", 0)
    workdir = tempfile.mkdtemp(prefix=f"bench-{prefix}-")
    ctl = os.path.join(workdir, "ctl.sock")
    veth_up(master_if, sim_if)
    sim = None
    try:
        with open(os.path.join(workdir, "sim.log"), "w") as sim_log:
            sim = subprocess.Popen(
                [sys.executable, "-m", "bus_agent.sim.cli", "--ifname", sim_if, "--drives", str(drives),
                 "--control", ctl, "--rt-priority", str(sim_rt_priority),
                 *(("--esi", esi) if esi else ("--profile", profile))],
                cwd=ROOT, stdout=subprocess.PIPE, stderr=sim_log, text=True)
        ready, _, _ = select.select([sim.stdout], [], [], SIM_READY_TIMEOUT_S)
        if not ready or not sim.stdout.readline().startswith("ecat-sim ready"):
            raise RuntimeError("ecat-sim did not start")
        yield Segment(master_if, sim_if, workdir, ctl, sim)
    finally:
        if sim is not None:
            stop_process(sim)
        veth_down(master_if)
        shutil.rmtree(workdir, ignore_errors=True)


def pysoem_to_op(m, ifname: str, drives: int, receive_timeout_us: int = 2000, dc_cycle_ns: int = 0) -> int:
    """Open ``ifname`` with pysoem master ``m``, scan and map ``drives`` slaves, bring them to
    SAFE-OP, then OP (process data flowing meanwhile); returns the expected working counter.
    ``dc_cycle_ns``: config_dc, and SYNC0 at that cycle on every DC slave before OP."""
    import struct
    import time

    import pysoem

    m.open(ifname)
    if m.config_init() != drives:
        raise RuntimeError("config_init did not find every drive")
    if dc_cycle_ns:
        m.config_dc()
    m.config_map()
    if m.state_check(pysoem.SAFEOP_STATE, 2_000_000) != pysoem.SAFEOP_STATE:
        raise RuntimeError("SAFE-OP not reached")
    if dc_cycle_ns:
        for s in m.slaves:
            if struct.unpack("<H", bytes(s._fprd(0x0008, 2, 2000))[:2])[0] & 0x0004:
                s.dc_sync(True, dc_cycle_ns)
        until = time.monotonic() + 0.15  # SOEM starts SYNC0 100 ms after dc_sync
        while time.monotonic() < until:
            m.send_processdata()
            m.receive_processdata(receive_timeout_us)
            time.sleep(0.001)
    m.send_processdata()
    m.receive_processdata(receive_timeout_us)
    m.state = pysoem.OP_STATE
    m.write_state()
    deadline = time.monotonic() + 5
    while m.state_check(pysoem.OP_STATE, 5000) != pysoem.OP_STATE:
        if time.monotonic() > deadline:
            raise RuntimeError("OP not reached")
        m.send_processdata()
        m.receive_processdata(receive_timeout_us)
    return m.expected_wkc


def stop_process(p: subprocess.Popen, timeout_s: float = 5.0) -> None:
    """SIGTERM, then SIGKILL after ``timeout_s``; reaped either way."""
    if p.poll() is not None:
        return
    p.terminate()
    try:
        p.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()


def bench_parser(name: str, doc: str | None) -> argparse.ArgumentParser:
    """The argument parser of ``python -m bench.<name>``: described by the first paragraph of
    ``doc`` (the module's docstring), with ``--out FILE`` (default bench/results/<name>.json)."""
    p = argparse.ArgumentParser(prog=f"python -m bench.{name}", description=(doc or "").split("\n\n")[0])
    p.add_argument("--out", type=Path, default=RESULTS / f"{name}.json", help="the JSON result")
    return p


def write_result(result: dict, out: Path) -> None:
    """Print ``result`` as JSON and write it to ``out`` (its folder made if missing)."""
    text = json.dumps(result, indent=2)
    print(text)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text + "\n")


def main_result(name: str, run: Callable[[], dict], out: Path) -> int:
    """The shell of a root benchmark: refuse without root, else ``run()``, print the JSON and
    write it to ``out``."""
    if os.geteuid() != 0:
        print(f"{name}: needs root (veth pairs, raw sockets)", file=sys.stderr)
        return 1
    write_result(run(), out)
    return 0


def loadavg() -> list[float]:
    """The machine's 1, 5 and 15 minute load averages, rounded to 0.01."""
    return [round(x, 2) for x in os.getloadavg()]


def run_stamp(loadavg_start: list[float]) -> dict:
    """What every result carries: UTC time, CPU count, load average at the start (taken by the
    caller with :func:`loadavg`) and now."""
    return {"time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "cpus": os.cpu_count(),
            "loadavg_start": loadavg_start, "loadavg_end": loadavg()}


def set_rt_priority(prio: int, *, required: bool = False) -> None:
    """SCHED_FIFO ``prio`` for the calling thread (0: leave the policy alone). A refusal raises
    if ``required``, else it is said on stderr and the run goes on at normal priority."""
    if not prio:
        return
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
    except OSError as e:
        if required:
            raise
        print(f"SCHED_FIFO {prio} refused: {e}", file=sys.stderr)


def best_of(runs: dict[str, Callable[[], object]], n: int, per_run: int = 100,
             inner: list[int] | None = None) -> tuple[dict[str, float], dict[str, float]]:
    """Thread CPU (us) of one call of each, best of ``n`` interleaved runs of ``per_run`` calls;
    and the same without the CPU the calls add to ``inner[0]`` (ns; a timed part inside them)."""
    best = {k: float("inf") for k in runs}
    own = dict(best)
    for _ in range(n):  # interleaved, so a burst of load lands on all alike
        for k, fn in runs.items():
            if inner is not None:
                inner[0] = 0
            t0 = time.thread_time_ns()
            for _ in range(per_run):
                fn()
            ns = time.thread_time_ns() - t0
            best[k] = min(best[k], ns / per_run / 1000)
            own[k] = min(own[k], (ns - (inner[0] if inner is not None else 0)) / per_run / 1000)
    return best, own


def proc_cpu_s(pid: int) -> float:
    """utime + stime of process ``pid`` in seconds (/proc/<pid>/stat fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def thread_cpu_ns(pid: int) -> dict[str, int]:
    """CPU time (ns) of the live threads of process ``pid``, summed per thread name with digits
    dropped (a pool's threads add up): /proc/<pid>/task/*/schedstat, nanoseconds rather than the
    10 ms ticks of /proc/<pid>/stat. Threads that ended are not counted."""
    out: dict[str, int] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip().rstrip("0123456789-_") or "?"
            ns = int((task / "schedstat").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            continue  # the thread ended meanwhile
        out[name] = out.get(name, 0) + ns
    return out


def task_cpu_ns(tid: int, pid: int | None = None) -> int:
    """CPU time (ns) of thread ``tid`` of process ``pid`` (default: this one), from
    /proc/<pid>/task/<tid>/schedstat; 0 when the thread is gone."""
    try:
        return int(Path(f"/proc/{pid or os.getpid()}/task/{tid}/schedstat").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 0


def read_period_logs(paths: Sequence[str]) -> list[int]:
    """The periods (ns, int64) of every file in ``paths``, in order: what phases wrote."""
    out: list[int] = []
    for path in paths:
        a = array("q")
        with open(path, "rb") as f:
            a.frombytes(f.read())
        out.extend(a)
    return out


def alternate_phases(tag: str, phases: Sequence[str], rounds: int, seconds: float, workdir: str,
                     run_phase: Callable[[str, float, str], dict]) -> tuple[dict[str, list[dict]], dict[str, list[str]]]:
    """Run ``phases`` in ``rounds`` alternating rounds of ``seconds / rounds`` each, so that a burst
    of load from other work lands on every phase alike. ``run_phase(name, seconds, period_log)``
    runs one; returns each phase's results and period log files, in round order."""
    per_round = seconds / rounds
    parts: dict[str, list[dict]] = {p: [] for p in phases}
    logs: dict[str, list[str]] = {p: [] for p in phases}
    for r in range(rounds):
        for name in phases:
            print(f"{tag}: round {r + 1}/{rounds} phase {name} ({per_round:g} s)...", file=sys.stderr, flush=True)
            log_file = os.path.join(workdir, f"{name}-{r}.periods")
            parts[name].append(run_phase(name, per_round, log_file))
            logs[name].append(log_file)
    return parts, logs


def run_json(cmd: Sequence[str], what: str, timeout_s: float, env: Mapping[str, str] | None = None) -> dict:
    """Run a phase process in the repository root (with ``env`` as its environment, if given); the
    JSON of its last line of output. Raises RuntimeError naming ``what`` with the end of its stderr
    when it fails."""
    p = subprocess.run(list(cmd), cwd=ROOT, capture_output=True, text=True, timeout=timeout_s,
                       env=dict(env) if env is not None else None)
    if p.returncode != 0:
        raise RuntimeError(f"{what} failed ({p.returncode}): {p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def self_cpu_s() -> float:
    """User + system CPU time of this process in seconds (getrusage)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


@dataclass(frozen=True)
class PacedRun:
    """What :func:`paced_loop` measured: ``periods[i]`` is the start of cycle i minus the start of
    cycle i-1 in ns (``periods[0]`` is 0: no cycle before it)."""

    periods: array
    overruns: int
    elapsed_s: float
    cpu_s: float


def paced_loop(cycles: int, period_ns: int, step: Callable[[int], None], rt_priority: int = 0) -> PacedRun:
    """The bare loop any program would write, timed as the agent's cycle is: ``step(i)`` on
    drift-free deadlines t0 + k * period (sleep until :data:`SPIN_NS` before, then spin), GC
    frozen and off, a 0.5 ms switch interval, SCHED_FIFO ``rt_priority`` (0: off). A cycle that
    starts more than a period late is an overrun and the deadlines skip ahead (no catch-up burst).
    The baseline the cycle benchmarks compare the agent with."""
    log = array("q", bytes(8 * cycles))
    clock, sleep = time.monotonic_ns, time.sleep
    overruns = 0
    old = sys.getswitchinterval()
    sys.setswitchinterval(0.0005)
    gc.collect()
    gc.freeze()
    gc.disable()
    set_rt_priority(rt_priority)
    cpu0 = self_cpu_s()
    t0 = clock()
    last = k = 0
    try:
        for i in range(cycles):
            dl = t0 + k * period_ns
            rem = dl - clock() - SPIN_NS
            if rem > 0:
                sleep(rem / 1e9)
            while clock() < dl:
                pass
            now = clock()
            if now - dl > period_ns:
                overruns += 1
                k = (now - t0) // period_ns
            if last:
                log[i] = now - last
            last = now
            step(i)
            k += 1
        return PacedRun(log, overruns, (clock() - t0) / 1e9, self_cpu_s() - cpu0)
    finally:
        gc.enable()
        sys.setswitchinterval(old)


#: Quantile names and their ranks, for :func:`quantiles`.
QUANTILES = {"p1": 0.01, "p50": 0.5, "p99": 0.99, "p999": 0.999}


def quantiles(sorted_values: Sequence[float], names: Sequence[str] = ("p50", "p99", "max"), scale: float = 1.0,
              digits: int = 1) -> dict:
    """``{name: value * scale}`` rounded to ``digits`` for names of :data:`QUANTILES` and ``max``,
    of an ascending sequence (nan if empty, max None)."""
    out: dict = {}
    for name in names:
        if name == "max":
            out[name] = round(sorted_values[-1] * scale, digits) if sorted_values else None
        else:
            out[name] = round(percentile(sorted_values, QUANTILES[name]) * scale, digits)
    return out


def period_figures(periods: Sequence[int], cycle_ns: int) -> dict:
    """Cycle start-to-start periods in ns: sample count, period and jitter |period - cycle_ns|
    p50/p99/p99.9/max in us ({} if none)."""
    if not periods:
        return {}
    ps = sorted(periods)
    js = sorted(abs(p - cycle_ns) for p in periods)
    names = ("p50", "p99", "p999", "max")
    return {"samples": len(ps), "period_us": quantiles(ps, names, 1e-3), "jitter_us": quantiles(js, names, 1e-3)}


def percentile(sorted_values: Sequence[float], q: float) -> float:
    """The value at rank ``int(q * n)`` of an ascending sequence (nan if empty)."""
    if not sorted_values:
        return float("nan")
    return sorted_values[min(len(sorted_values) - 1, int(q * len(sorted_values)))]


def summary_ms(values_s: Sequence[float]) -> dict:
    """p50 / p99 / max in ms of a list of durations in seconds ({} if empty)."""
    if not values_s:
        return {}
    v = sorted(values_s)
    return {"n": len(v), "p50_ms": round(percentile(v, 0.5) * 1e3, 3), "p99_ms": round(percentile(v, 0.99) * 1e3, 3),
            "max_ms": round(v[-1] * 1e3, 3)}


def free_port() -> int:
    """A TCP port free on loopback right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stats_ms(values_ms: Sequence[float]) -> dict:
    """``n`` and p50/p99/max of latencies in ms (``{"n": 0}`` when none)."""
    return {"n": len(values_ms), **quantiles(sorted(values_ms))} if values_ms else {"n": 0}


def p50_ratio(values: Sequence[float], baseline: Sequence[float]) -> float | None:
    """Median of ``values`` over the median of ``baseline`` (at least 1 us), to 0.1; None when
    either is empty (bench_dashboard, bench_opcua: a client next to a plain subscriber)."""
    if not values or not baseline:
        return None
    return round(percentile(sorted(values), 0.5) / max(percentile(sorted(baseline), 0.5), 1e-3), 1)


def fleet_bench_main(name: str, doc: str | None, run: Callable[[int, int, int, float], dict],
                     argv: list[str] | None) -> int:
    """``main`` of a benchmark over a fleet of simulated agents that idles, then faults a drive
    per round (bench_dashboard, bench_opcua): ``--hosts``, ``--drives``, ``--rounds``, ``--idle-s``."""
    p = bench_parser(name, doc)
    p.add_argument("--hosts", type=int, default=8)
    p.add_argument("--drives", type=int, default=128)
    p.add_argument("--rounds", type=int, default=20)
    p.add_argument("--idle-s", type=float, default=10.0)
    a = p.parse_args(argv)
    write_result(run(a.hosts, a.drives, a.rounds, a.idle_s), a.out)
    return 0
