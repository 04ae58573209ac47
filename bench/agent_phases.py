"""The pysoem side shared by the cycle benchmarks (``bench_agent``, ``bench_cycle``,
``bench_motion``, ``enable_latency``): the bare pysoem loop (:func:`phase_bare`, the baseline),
bringing every drive of a running ``Cycle`` to enabled (:func:`enable_all`) and the periods of
its next seconds of cycles (:func:`measure`). Each phase runs in its own process.
"""

from __future__ import annotations

import sys
import threading
import time
from array import array

from bench.common import paced_loop, period_figures, pysoem_to_op, self_cpu_s


def dump_periods(args, periods, dc_offsets=None) -> None:
    """The phase's periods (ns) into its log file; frame-to-SYNC0 offsets (ns) into ``<file>.dc``."""
    if getattr(args, "log_file", None):
        with open(args.log_file, "wb") as f:
            array("q", periods).tofile(f)
        if dc_offsets is not None:
            with open(args.log_file + ".dc", "wb") as f:
                array("q", dc_offsets).tofile(f)


def phase_bare(args) -> dict:
    """Bare pysoem: the loop any pysoem program would write, with the cycle's timing method."""
    import pysoem

    from bus_agent.bus.pdo import RX_STRUCT

    m = pysoem.Master()
    expected = pysoem_to_op(m, args.ifname, args.drives, dc_cycle_ns=args.cycle_us * 1000 if args.dc == "auto" else 0)
    slaves = list(m.slaves)
    # outputs of each slave's size: the default 13-byte layout packed as any program would
    pack = [(lambda: RX_STRUCT.pack(0, 0, 0, 0, 8)) if len(s.output) == RX_STRUCT.size
            else (lambda n=len(s.output): bytes(n)) for s in slaves]
    period = args.cycle_us * 1000
    wkc_errors = 0
    send, receive, timeout_us = m.send_processdata, m.receive_processdata, args.receive_timeout_us
    cycles = int(args.seconds * 1e9 / period)
    # the frame's phase in the SYNC0 period (no PI: the bare loop does not follow DC time)
    offsets = array("q", bytes(8 * cycles)) if args.dc == "auto" and m.dc_time else None

    def step(i: int) -> None:
        nonlocal wkc_errors
        send(release_gil=True)
        if receive(timeout_us, release_gil=True) != expected:
            wkc_errors += 1
        if offsets is not None:
            offsets[i] = m.dc_time % period
        for s, pk in zip(slaves, pack):  # what any program does each cycle: read inputs, write outputs
            _ = s.input
            s.output = pk()

    run = paced_loop(cycles, period, step, args.rt_priority)
    m.state = pysoem.INIT_STATE
    m.write_state()
    m.close()
    periods = run.periods[1:]
    dump_periods(args, periods, offsets)
    return {"cycles": len(run.periods), "seconds": round(run.elapsed_s, 2), "overruns": run.overruns,
            "wkc_errors": wkc_errors, "cpu_s": round(run.cpu_s, 3), "cpu_pct": round(100 * run.cpu_s / run.elapsed_s, 1),
            **period_figures(list(periods), period)}


def command_all(cyc, op: str, axes, timeout_s: float = 10.0) -> list:
    """Submit ``op`` for ``axes`` to the cycle; its outcomes, one per axis."""
    from bus_agent.runtime import DriveCommand

    done = threading.Semaphore(0)
    outs: list = []

    def on(o):
        outs.append(o)
        done.release()

    assert cyc.submit(DriveCommand(request_id=f"bench-{op}-{time.monotonic_ns()}", op=op, axes=tuple(axes),
                                   on_outcome=on, received_ns=time.monotonic_ns(), timeout_s=timeout_s))
    for _ in axes:
        if not done.acquire(timeout=timeout_s + 2):
            raise RuntimeError(f"{op} did not finish")
    return outs


def ready_to_enable(cyc) -> int:
    """Every slave in OP and no drive in fault; the number of drives fault-reset to get there.

    On a loaded host the start-up can stall the process data past the slaves' SM watchdog: the
    agent brings such a slave back to OP itself, but its drive reports the communication loss as a
    fault (0x8130), which the agent never resets on its own. The benchmark resets it explicitly,
    once, and reports how many it reset (``startup_fault_resets``)."""
    deadline = time.monotonic() + 30.0
    while not (cyc.latest is not None and all(d.al_state == "op" and not d.lost for d in cyc.latest.drives)):
        if time.monotonic() > deadline:
            raise RuntimeError(f"slaves not in OP: {[(d.axis, d.al_state) for d in cyc.latest.drives]}")
        time.sleep(0.05)
    faulted = [d.axis for d in cyc.latest.drives if d.state in ("fault", "fault_reaction_active")]
    if faulted:
        print(f"bench_agent: start-up faults on {len(faulted)} drive(s), reset explicitly", file=sys.stderr)
        bad = [o for o in command_all(cyc, "fault_reset", faulted) if o.outcome != "done"]
        if bad:
            raise RuntimeError(f"fault reset failed: {bad[:3]}")
    return len(faulted)


def enable_all(cyc, timeout_s: float = 10.0) -> int:
    """:func:`ready_to_enable`, then enable every drive; the start-up fault resets."""
    resets = ready_to_enable(cyc)
    bad = [o for o in command_all(cyc, "enable", cyc.axes, timeout_s) if o.outcome != "done"]
    if bad:
        raise RuntimeError(f"enable failed: {bad[:3]}")
    return resets


def measure(cyc, args) -> dict:
    """Periods (and, with SYNC0, frame-to-SYNC0 offsets) of the next ``args.seconds`` of cycles."""
    period = args.cycle_us * 1000
    n = int(args.seconds * 1e9 / period)
    cyc.dc_log = array("q", bytes(8 * n)) if "sync0" in cyc.dc_states else None
    ov0, wk0, c0 = cyc.overruns, cyc.wkc_errors, cyc.cycles
    cpu0 = self_cpu_s()
    t0 = time.monotonic()
    cyc.period_log_len = 0
    cyc.period_log = array("q", bytes(8 * n))
    while cyc.period_log_len < n and time.monotonic() - t0 < args.seconds * 3 + 10:
        time.sleep(0.05)
    elapsed = time.monotonic() - t0
    cpu = self_cpu_s() - cpu0
    got = cyc.period_log_len
    log = list(cyc.period_log[:got])
    cyc.period_log = None
    dc_log, cyc.dc_log = cyc.dc_log, None
    dump_periods(args, array("q", log), None if dc_log is None else dc_log[:got])
    return {"cycles": cyc.cycles - c0, "seconds": round(elapsed, 2), "overruns": cyc.overruns - ov0,
            "wkc_errors": cyc.wkc_errors - wk0, "cpu_s": round(cpu, 3), "cpu_pct": round(100 * cpu / elapsed, 1),
            **period_figures(log, period)}
