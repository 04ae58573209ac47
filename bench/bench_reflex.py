"""Benchmark (root): the cross-host group reflex over the namespaced multi-host bed with routers,
next to a bare zenoh put-to-subscriber latency across the same routers in the same run.

Bed (``tests/system/multihost.py``): network namespaces h1, h2 and sup on one bridge; in h1 and
h2 ``ecat-sim`` with ``--drives`` drives, a ``drives-router`` (h2's connects to h1's) and
``bus-agent`` (pysoem, real EtherCAT frames, gateway process) with group ``xg = h1/axis0 +
h2/axis0``. Per round, a ``supervisor.Fleet`` in sup enables both members (two-phase), ecat-sim
faults h1's slave 0 (error 0x7305), and the figures come from the agents' own event time stamps
(the wall time of the cycle that saw it; one clock for every namespace), not from polling:

- ``fault_to_reflex``: h1/axis0's ``fault`` event -> h2/axis0's ``reflex`` event (the cycle on
  h2 applied the group's reflex: h1's status through both routers, h2's gateway, the bridge);
- ``fault_to_leave``: -> h2/axis0's transition out of ``operation_enabled`` (the drive obeyed:
  the target, p50 <= 2 ms and p99 <= 3 ms): the cycle on h2 that read a statusword other than
  operation enabled, stamped as that cycle's snapshot;
- ``reflex_to_leave``: h2's share after the reflex (the express frame carrying the quick stop,
  the drive's own step in ecat-sim, the next frame reading its statusword);
- ``fault_to_status_in_sup``: -> h1/axis0's fault status arriving in sup through h1's router
  (the origin's share: h1's cycle, bridge, gateway and one router hop).

Then the Fleet resets the fault on h1/axis0. The bare figure: a publisher in h1 connected to h1's
router puts its ``time.time_ns()`` every 10 ms (express), a subscriber in h2 connected to h2's
router takes the difference on arrival. The baseline of the express exchange (``next_cycle``):
a second bed whose agents have ``[cycle] express_reflex = false``, the same rounds.

    python -m bench.bench_reflex [--rounds N] [--drives N] [--bare N] [--rt-priority N] [--no-router-rt]
                                 [--no-next-cycle] [--out PATH]

The agents run at ``--rt-priority`` (default 10) and each host's router at their helper priority
(9), as docs/deployment.md says to deploy them (``--no-router-rt``: routers under SCHED_OTHER).

Writes ``bench/results/bench_reflex.json`` (ms percentiles, ratios to the bare put, load).
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import struct
import sys
import tempfile
import threading
import time
from typing import Any

from bench.common import ROOT, bench_parser, loadavg, percentile, run_stamp, write_result

GROUP = ("h1/axis0", "h2/axis0")
BARE_KEY = "bench/reflex/bare"
BARE_PERIOD_S = 0.01
BARE_WARMUP = 50
FAULT_CODE = 0x7305
#: A round whose reflex did not come within this is a failure (a safety bound, not a figure).
ROUND_TIMEOUT_S = 5.0


def _ms(values_ns: list[int]) -> dict:
    v = sorted(x / 1e6 for x in values_ns)
    if not v:
        return {"n": 0}
    return {"n": len(v), "p50_ms": round(percentile(v, 0.5), 3), "p99_ms": round(percentile(v, 0.99), 3),
            "max_ms": round(v[-1], 3)}


def _session(connect: str) -> Any:
    import zenoh

    from bus_agent.gateway.zenoh_config import make_zenoh_config

    return zenoh.open(make_zenoh_config("client", connect=[connect]))


# ---- children (run inside a namespace) -----------------------------------------------------------


def child_bare_sub(connect: str, count: int) -> int:
    s = _session(connect)
    got: list[int] = []
    done = threading.Event()

    def on(sample: Any) -> None:
        now = time.time_ns()
        seq, sent = struct.unpack("<qq", sample.payload.to_bytes())
        if seq >= BARE_WARMUP:
            got.append(now - sent)
        if seq >= BARE_WARMUP + count - 1:
            done.set()

    sub = s.declare_subscriber(BARE_KEY, on)
    print("sub ready", flush=True)
    done.wait(60 + count * BARE_PERIOD_S * 4)
    sub.undeclare()
    s.close()
    print(json.dumps({"bare_ns": got}), flush=True)
    return 0


def child_bare_pub(connect: str, count: int) -> int:
    import zenoh

    s = _session(connect)
    pub = s.declare_publisher(BARE_KEY, express=True, congestion_control=zenoh.CongestionControl.BLOCK)
    next_s = time.monotonic()
    for seq in range(BARE_WARMUP + count):
        next_s += BARE_PERIOD_S
        time.sleep(max(0.0, next_s - time.monotonic()))
        pub.put(struct.pack("<qq", seq, time.time_ns()))
    pub.undeclare()
    s.close()
    print("pub done", flush=True)
    return 0


def child_reflex(connect: str, control: str, rounds: int, drives: int) -> int:
    """In sup: a Fleet enables the group, ecat-sim faults h1's slave 0, the events are timed."""
    from schemas import keys
    from schemas import messages as m
    from supervisor.fleet import Fleet
    from tests.system.multihost import PathControlClient

    events: "queue.SimpleQueue[m.Event]" = queue.SimpleQueue()
    ctl = PathControlClient(control)
    out: dict[str, list] = {"fault_to_reflex_ns": [], "fault_to_leave_ns": [], "reflex_to_leave_ns": [],
                            "fault_to_status_here_ns": [], "failures": []}
    with Fleet(connect=[connect], name="bench-reflex", mode="client", connect_timeout_s=10.0) as fleet:
        def on_event(sample: Any) -> None:
            try:
                events.put(m.decode(sample.payload.to_bytes(), m.Event))
            except m.SchemaError:
                pass

        seen: "queue.SimpleQueue[int]" = queue.SimpleQueue()  # arrival of h1/axis0's fault status here

        def on_status(sample: Any) -> None:
            now = time.time_ns()
            try:
                st = m.decode(sample.payload.to_bytes(), m.DriveStatus)
            except m.SchemaError:
                return
            if st.state in ("fault", "fault_reaction_active"):
                seen.put(now)

        sub = fleet.session.declare_subscriber(keys.drive_event("*", "axis0"), on_event)
        status_sub = fleet.session.declare_subscriber(keys.drive_status("h1", "axis0"), on_status)
        if not fleet.wait_for_agents(["h1", "h2"], timeout_s=30.0, drives=2 * drives):
            raise RuntimeError("agents h1 and h2 not seen within 30 s")
        print("reflex ready", flush=True)
        for i in range(-1, rounds):  # round -1 warms the routes up, not counted
            report = fleet.enable(*GROUP)
            if not report.ok:
                out["failures"].append({"round": i, "enable": report.reason})
                fleet.fault_reset("h1/axis0")
                continue
            for q in (events, seen):
                while not q.empty():
                    q.get_nowait()
            reply = ctl.request("fault", slave=0, error_code=FAULT_CODE)
            if not reply.get("ok"):
                raise RuntimeError(f"ecat-sim refused the fault: {reply}")
            fault_ns = reflex_ns = leave_ns = None
            deadline = time.monotonic() + ROUND_TIMEOUT_S
            while leave_ns is None or fault_ns is None:
                try:
                    ev = events.get(timeout=max(0.0, deadline - time.monotonic()))
                except queue.Empty:
                    break
                if ev.host == "h1" and ev.kind == "fault" and fault_ns is None:
                    fault_ns = ev.time_ns
                elif ev.host == "h2" and ev.kind == "reflex" and reflex_ns is None:
                    reflex_ns = ev.time_ns
                elif ev.host == "h2" and ev.kind == "transition" and ev.from_state == "operation_enabled":
                    leave_ns = ev.time_ns
            if fault_ns is None or leave_ns is None or reflex_ns is None:
                out["failures"].append({"round": i, "fault": fault_ns, "reflex": reflex_ns, "leave": leave_ns})
            elif i >= 0:
                out["fault_to_reflex_ns"].append(reflex_ns - fault_ns)
                out["fault_to_leave_ns"].append(leave_ns - fault_ns)
                out["reflex_to_leave_ns"].append(leave_ns - reflex_ns)
                if not seen.empty():
                    out["fault_to_status_here_ns"].append(seen.get_nowait() - fault_ns)
            fleet.fault_reset("h1/axis0")
        sub.undeclare()
        status_sub.undeclare()
    ctl.close()
    print(json.dumps(out), flush=True)
    return 0


# ---- the parent (root namespace) -------------------------------------------------------------


def _last_json(proc: Any, timeout_s: float) -> dict:
    proc.popen.wait(timeout_s)
    for line in reversed(proc.lines):
        if line.startswith("{"):
            return json.loads(line)
    raise RuntimeError(f"{proc.name} gave no result (exit {proc.popen.poll()}):\n{proc.output()}")


#: The hops of a reflex (bus_agent.hops), from h1's cycle seeing the fault to h2's express frame.
REFLEX_HOPS = ("cy.fault", "cy.sink.ev", "cy.woke.ev", "cy.forwarded.ev", "gw.update.ev", "pub.bad", "gw.remote",
               "gw.trigger", "cy.wake", "cy.express")


def reflex_hops(directory: str) -> dict:
    """Where a reflex's time goes: p50 of each hop's first stamp (ms after h1's cycle saw the
    fault) over the rounds, from every process's stamps in ``directory``."""
    from bus_agent import hops

    stamps = [s for s in hops.read(directory) if s[1] in REFLEX_HOPS]
    return hops.breakdown(hops.rounds(stamps, "cy.fault", "cy.express"))


def _bed(args: Any, express: bool, bare_puts: int) -> tuple[dict, list[int]]:
    """One bed: the agents with ``[cycle] express_reflex`` as given; the bare puts first (if any).
    With the express exchange every process stamps the hops (``hops`` in the result)."""
    from bus_agent import hops
    from tests.system.multihost import MultiHostRun, Proc

    from bus_agent.cycle.realtime import helper_priority

    # Each host's router beside its real-time agent at the agent's helper priority, as
    # docs/deployment.md says to run it: under SCHED_OTHER it waited about a millisecond behind
    # the agents' real-time threads right after a fault (docs/benchmarks.md).
    rt = args.rt_priority
    bed = MultiHostRun(hosts=2, drives=args.drives, groups={"xg": list(GROUP)}, prefix=f"zr{os.getpid() % 100000}",
                       agent_args=["--rt-priority", str(rt)] if rt else [],
                       agent_toml="" if express else "\n[cycle]\nexpress_reflex = false\n",
                       router_args=["--rt-priority", str(helper_priority(rt))] if rt and args.router_rt else [])
    me = [sys.executable, "-m", "bench.bench_reflex"]
    bare: list[int] = []
    hop_dir = tempfile.mkdtemp(prefix="bench-reflex-hops-")
    old_env = os.environ.get(hops.ENV)
    if express:
        os.environ[hops.ENV] = hop_dir  # the bed's processes inherit it
    result: dict = {}
    try:
        bed.start()
        if bare_puts:
            sub = bed.spawn(Proc, "bare sub", "h2", [*me, "--child", "bare_sub", "--connect",
                                                     bed.router_endpoint("h2"), "--bare", str(bare_puts)],
                            ready_marker="sub ready")
            sub.expect_ready(30)
            pub = bed.spawn(Proc, "bare pub", "h1", [*me, "--child", "bare_pub", "--connect",
                                                     bed.router_endpoint("h1"), "--bare", str(bare_puts)],
                            ready_marker="pub done")
            bare = _last_json(sub, 90 + bare_puts * BARE_PERIOD_S * 4)["bare_ns"]
            pub.popen.wait(10)
        reflex = bed.spawn(Proc, "reflex", "sup", [
            *me, "--child", "reflex", "--connect", bed.router_endpoint("h1"), "--drives", str(args.drives),
            "--rounds", str(args.rounds), "--control", os.path.join(bed.workdir, "h1.sock")], ready_marker="reflex ready")
        result = _last_json(reflex, 120 + args.rounds * 15)
    except BaseException:
        print(bed.diagnostics(), file=sys.stderr)
        raise
    finally:
        if old_env is None:
            os.environ.pop(hops.ENV, None)
        else:
            os.environ[hops.ENV] = old_env
        bed.close()  # the processes write their stamps as they stop
    if express:
        result["hops"] = reflex_hops(hop_dir)
    shutil.rmtree(hop_dir, ignore_errors=True)
    return result, bare


def _figures(res: dict) -> dict:
    return {**({"hops": res["hops"]} if "hops" in res else {}),
            "fault_to_reflex": _ms(res["fault_to_reflex_ns"]), "fault_to_leave": _ms(res["fault_to_leave_ns"]),
            "reflex_to_leave": _ms(res["reflex_to_leave_ns"]),
            "fault_to_status_in_sup": _ms(res["fault_to_status_here_ns"]),
            "failures": res["failures"][:10], "n_failures": len(res["failures"])}


def run(args: Any) -> dict:
    start = loadavg()
    res, bare = _bed(args, True, args.bare)
    out: dict[str, Any] = {"rounds": args.rounds, "drives_per_host": args.drives, "group": list(GROUP),
                           "rt_priority": args.rt_priority, "router_rt": bool(args.rt_priority and args.router_rt), **_figures(res), "bare_put": _ms(bare)}
    leave, b = out["fault_to_leave"], out["bare_put"]
    if leave.get("n") and b.get("n"):
        out["ratios"] = {"leave_p50_over_bare_p50": round(leave["p50_ms"] / b["p50_ms"], 2),
                         "leave_p99_over_bare_p99": round(leave["p99_ms"] / b["p99_ms"], 2)}
    if args.next_cycle:
        # the baseline of the express exchange: the same rounds with the reflex applied by the next cycle
        nxt = out["next_cycle"] = _figures(_bed(args, False, 0)[0])
        nl = nxt["fault_to_leave"]
        if leave.get("n") and nl.get("n"):
            out["ratios"].update({"leave_p50_express_over_next_cycle": round(leave["p50_ms"] / nl["p50_ms"], 2),
                                  "leave_p99_express_over_next_cycle": round(leave["p99_ms"] / nl["p99_ms"], 2)})
    out.update(run_stamp(start))
    return out


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_reflex", __doc__)
    p.add_argument("--rounds", type=int, default=50, help="fault/reset rounds (default 50)")
    p.add_argument("--drives", type=int, default=2, help="drives per host (default 2)")
    p.add_argument("--bare", type=int, default=500, help="bare puts timed (default 500)")
    p.add_argument("--rt-priority", type=int, default=10,
                   help="SCHED_FIFO priority of the agents' cycle threads (0: off; default 10)")
    p.add_argument("--no-router-rt", dest="router_rt", action="store_false",
                   help="routers under normal scheduling (default: SCHED_FIFO at the agents' helper priority)")
    p.add_argument("--no-next-cycle", dest="next_cycle", action="store_false",
                   help="skip the baseline bed with [cycle] express_reflex = false")
    p.add_argument("--child", choices=("bare_sub", "bare_pub", "reflex"), help=_suppress())
    p.add_argument("--connect")
    p.add_argument("--control")
    args = p.parse_args(argv)
    if args.child == "bare_sub":
        return child_bare_sub(args.connect, args.bare)
    if args.child == "bare_pub":
        return child_bare_pub(args.connect, args.bare)
    if args.child == "reflex":
        return child_reflex(args.connect, args.control, args.rounds, args.drives)
    if os.geteuid() != 0 or shutil.which("ip") is None:
        print("bench_reflex: needs root and iproute2 (network namespaces, veth pairs)", file=sys.stderr)
        return 1
    write_result(run(args), args.out)
    return 0


def _suppress() -> str:
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    raise SystemExit(main())
