"""The ``enable_latency`` phase of ``bench.bench_agent``: an enable of every drive, timed to the last reply.

The real agent (gateway process, ``--drives`` pysoem drives on the segment ``bench_agent`` set
up) with every drive disabled. A client process sends a ``CommandRequest`` enable to
``drives/@v1/bench/drive/*/cmd/enable`` (QueryTarget.ALL, ConsolidationMode.NONE) and times
query sent -> last drive's reply;
then it disables every drive (not timed). One warm-up round, then ``--enable-rounds`` rounds.
Each round also times ``--gets-per-round`` bare zenoh gets to a trivial queryable in its own
process, reached the same way (one direct peer link over loopback TCP): the baseline.

Every process of the phase records the hops of each command (:mod:`bus_agent.hops`, into the
phase's directory), so the JSON says where the time goes (``hops``: p50 of each hop's first and
last stamp, ms after the client sent the query) and splits the latency:

- ``cycle_time``: from the command's arrival in the cycle process's inbox (``cy.submit``) to
  the last drive's outcome (``cy.outcome``): the drives' own part, the wait for the next cycle
  start included;
- ``beyond_cycle_time``: the latency minus that;
- ``beyond_cycles`` (the issue's figure): the latency minus max(``CommandReply.cycles``) x the
  cycle; ``cycles`` counts cycle starts from the one that applied the command to the outcome,
  so the wait for that cycle start (up to a cycle) and the drive loop up to the last outcome
  count as "beyond";
- ``beyond_elapsed``: the latency minus max(``CommandReply.elapsed_s``) (gateway receipt ->
  outcome).

Run by ``bench_agent`` (``python -m bench.enable_latency --phase enable_latency ...``); needs root.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
import threading
import time

from bench.agent_phases import ready_to_enable
from bench.common import ROOT, free_port, percentile, proc_cpu_s, stop_process, summary_ms, thread_cpu_ns
from bus_agent import hops

ECHO_KEY = "bench/echo"
#: The enable phase first measures the processes' CPU at rest for this long.
ENABLE_IDLE_S = 2.0


def _echo_config(ep: str, listen: bool):
    from bus_agent.gateway.zenoh_config import make_zenoh_config

    return make_zenoh_config("peer", listen=[ep] if listen else [], connect=[] if listen else [ep])


def phase_echo(args) -> dict:
    """A trivial queryable in its own process (the bare get's far end): replies b"pong"."""
    import signal

    import zenoh

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def on_query(q):
        with q:
            q.reply(q.key_expr, b"pong")

    with zenoh.open(_echo_config(args.listen, listen=True)) as s:
        qb = s.declare_queryable(ECHO_KEY, on_query)
        print("echo ready", flush=True)
        stop.wait()
        qb.undeclare()
    return {}


def _fanout(session, key: str, req, expected: int, timeout_s: float) -> tuple[float | None, list]:
    """One command query to every drive (QueryTarget.ALL, ConsolidationMode.NONE): seconds from
    the query sent to the ``expected``-th reply (None if fewer came), and the decoded replies.

    The replies are taken from zenoh's default channel by this thread. A callback handler
    (``supervisor.Fleet``'s) measured slower and dearer here: 64 replies from another process on
    loopback, 300 alternating rounds at load 4, p50 1.15 ms and 1.0 ms of CPU through the
    channel, 1.93 ms and 1.26 ms through a callback (16 replies: 0.47 against 0.69 ms)."""
    import zenoh

    from schemas.messages import CommandReply, decode, encode

    payload = encode(req)
    replies, last = [], None
    hops.stamp(f"cl.send.{req.op}")
    t0 = time.perf_counter()
    for r in session.get(key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                         payload=payload, timeout=timeout_s):
        if r.ok is None:
            continue
        hops.stamp("cl.reply")
        replies.append(decode(r.ok.payload.to_bytes(), CommandReply))
        if len(replies) == expected:
            last = time.perf_counter() - t0  # the rest of the loop only waits for the query's end
            hops.stamp(f"cl.done.{req.op}")
    return last, replies


def _client_fifo(priority: int) -> None:
    """This process's threads, zenoh's included, under SCHED_FIFO ``priority``
    (``--client-rt-priority``): the client stands in for a supervisor on another host, which the
    agent's own threads would not keep off the CPU."""
    from bus_agent.cycle.realtime import set_thread_fifo
    from bus_agent.gateway.child import ZENOH_THREADS, zenoh_threads_fifo

    set_thread_fifo(priority, "the enable client")
    seen: set[int] = set()
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:  # zenoh names its threads after they start
        zenoh_threads_fifo(priority, seen)
        names = [open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")]
        if sum(n.startswith(ZENOH_THREADS) for n in names) >= len(seen) >= 2:
            break
        time.sleep(0.05)


def phase_enable_client(args) -> dict:
    """The commanding side: ``--enable-rounds`` rounds of [bare gets to the echo queryable,
    enable of every drive timed to the last reply, disable (not timed)]."""
    import zenoh

    from bus_agent.gateway.zenoh_config import make_zenoh_config
    from schemas import keys
    from schemas.messages import CommandRequest

    session = zenoh.open(make_zenoh_config("peer", connect=[args.connect, args.echo]))
    if args.client_rt_priority:
        _client_fifo(args.client_rt_priority)
    cycle_s = args.cycle_us / 1e6
    en_key, dis_key = keys.drive_cmd(args.host, "*", "enable"), keys.drive_cmd(args.host, "*", "disable")
    status_key = keys.drive_status(args.host, "*")
    deadline = time.monotonic() + 30
    while True:  # routes in place: every drive's status queryable and the echo answer
        n = sum(1 for r in session.get(status_key, target=zenoh.QueryTarget.ALL,
                                       consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0) if r.ok is not None)
        echo = [r for r in session.get(ECHO_KEY, timeout=2.0) if r.ok is not None]
        if n >= args.drives and echo:
            break
        if time.monotonic() > deadline:
            raise RuntimeError(f"agent or echo not reachable ({n} drive status, echo {bool(echo)})")
        time.sleep(0.2)
    latency, beyond, beyond_elapsed, cycles, bare, failures = [], [], [], [], [], []
    cpu0 = time.process_time()
    for i in range(-1, args.enable_rounds):  # round -1: warm-up, not counted
        for _ in range(args.gets_per_round):
            t0 = time.perf_counter()
            ok = [r for r in session.get(ECHO_KEY, timeout=2.0) if r.ok is not None]
            if ok and i >= 0:
                bare.append(time.perf_counter() - t0)
        rid = f"bench-{os.getpid()}-{i}"
        if i == 0:
            hops.stamp("cl.counted")  # rounds before this stamp are the warm-up
        lat, replies = _fanout(session, en_key, CommandRequest(request_id=f"{rid}-en", op="enable", timeout_s=5.0),
                               args.drives, 10.0)
        bad = [f"{r.axis}:{r.outcome}:{r.reason}" for r in replies if r.outcome != "done"]
        if lat is None or bad:
            failures.append({"round": i, "replies": len(replies), "not_done": bad[:4]})
        elif i >= 0:
            c = max(r.cycles for r in replies)
            latency.append(lat)
            cycles.append(c)
            beyond.append(lat - c * cycle_s)
            beyond_elapsed.append(lat - max(r.elapsed_s for r in replies))
        _, replies = _fanout(session, dis_key, CommandRequest(request_id=f"{rid}-dis", op="disable", timeout_s=5.0),
                             args.drives, 10.0)
        if len(replies) < args.drives or any(r.outcome != "done" for r in replies):
            failures.append({"round": i, "op": "disable", "replies": len(replies)})
        time.sleep(0.02)  # let the disable's status publications pass before the next round
    session.close()
    out = {"rounds": args.enable_rounds, "drives": args.drives, "timed": len(latency), "failures": failures[:10],
           "client_cpu_s": time.process_time() - cpu0,
           "n_failures": len(failures),
           "latency": summary_ms(latency), "beyond_cycles": summary_ms(beyond),
           "beyond_elapsed": summary_ms(beyond_elapsed), "bare_get": summary_ms(bare),
           "transition_cycles": {"p50": percentile(sorted(cycles), 0.5), "max": max(cycles)} if cycles else {}}
    b = out["bare_get"]
    if b and latency:
        out["ratios"] = {"latency_p50_over_bare_get_p50": round(out["latency"]["p50_ms"] / b["p50_ms"], 2),
                         "beyond_cycles_p50_over_bare_get_p50": round(out["beyond_cycles"]["p50_ms"] / b["p50_ms"], 2),
                         "beyond_cycles_p99_over_bare_get_p99": round(out["beyond_cycles"]["p99_ms"] / b["p99_ms"], 2)}
    return out


def hop_figures(stamps: list[tuple[int, str]], bare_p50_ms: float | None) -> dict:
    """From every process's stamps (``bus_agent.hops``) of the counted enable rounds: the hop
    table, the drives' own time (``cycle_time``: cycle inbox -> last outcome) and the latency
    beyond it, with its ratio to the bare get."""
    counted = [s for s in stamps if s[0] >= next((ns for ns, h in stamps if h == "cl.counted"), 0)]
    rounds = hops.rounds(counted, "cl.send.enable", "cl.done.enable")
    rounds = [r for r in rounds if "cy.submit" in r and "cy.outcome" in r]
    if not rounds:
        return {}
    cycle_ms = [r["cy.outcome"][-1] - r["cy.submit"][0] for r in rounds]
    beyond_ms = [r["cl.done.enable"][0] - c for r, c in zip(rounds, cycle_ms)]
    out = {"hops": hops.breakdown(rounds), "cycle_time": summary_ms([c / 1e3 for c in cycle_ms]),
           "beyond_cycle_time": summary_ms([b / 1e3 for b in beyond_ms])}
    if bare_p50_ms:
        out["beyond_cycle_time_p50_over_bare_get_p50"] = round(out["beyond_cycle_time"]["p50_ms"] / bare_p50_ms, 2)
    return out


def phase_enable_latency(args) -> dict:
    """The real agent (gateway process) with every drive disabled; the client and the echo
    queryable in their own processes, each a direct peer link over loopback TCP."""
    from bus_agent.agent import Agent
    from bus_agent.bus.pysoem_bus import PysoemBus
    from bus_agent.config import AgentConfig, ZenohConfig

    ep, echo_ep = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    cfg = AgentConfig(host="bench", ifname=args.ifname, cycle_us=args.cycle_us, gateway="process",
                      rt_priority=args.rt_priority, zenoh=ZenohConfig(mode="peer", listen=(ep,), scouting=False))
    agent = Agent(cfg, bus=PysoemBus(args.ifname, receive_timeout_us=args.receive_timeout_us))
    procs: list[subprocess.Popen] = []
    me = [sys.executable, "-m", "bench.enable_latency"]
    agent.start()
    try:
        echo = subprocess.Popen([*me, "--phase", "echo", "--listen", echo_ep], cwd=ROOT, stdout=subprocess.PIPE,
                                text=True)
        procs.append(echo)
        ready, _, _ = select.select([echo.stdout], [], [], 20)
        if not ready or echo.stdout.readline().strip() != "echo ready":
            raise RuntimeError("echo queryable did not start")
        cyc = agent.cycle
        resets = ready_to_enable(cyc)
        # CPU of the gateway process: idle for a while, then over the client's rounds, so the
        # rounds' own cost can be told from publishing at rest (CPU time holds up on a loaded
        # machine where wall-clock latencies do not). Not the cycle process: its spin before each
        # deadline varies with the load, so its idle rate does not carry over.
        gw_pid = agent.bridge.pid if agent.bridge is not None else None
        idle_s, g_idle0 = time.monotonic(), proc_cpu_s(gw_pid) if gw_pid else 0.0
        th_idle0 = thread_cpu_ns(gw_pid) if gw_pid else {}
        time.sleep(ENABLE_IDLE_S)
        idle_s = time.monotonic() - idle_s
        g_idle = (proc_cpu_s(gw_pid) if gw_pid else 0.0) - g_idle0
        th_idle = _delta(thread_cpu_ns(gw_pid) if gw_pid else {}, th_idle0)
        ov0, wk0, c0 = cyc.overruns, cyc.wkc_errors, cyc.cycles
        t0, g0 = time.monotonic(), proc_cpu_s(gw_pid) if gw_pid else 0.0
        th0 = thread_cpu_ns(gw_pid) if gw_pid else {}
        client = subprocess.Popen(
            [*me, "--phase", "enable_client", "--connect", ep, "--echo", echo_ep,
             "--client-rt-priority", str(args.client_rt_priority),
             "--host", "bench", "--drives", str(args.drives), "--cycle-us", str(args.cycle_us),
             "--enable-rounds", str(args.enable_rounds), "--gets-per-round", str(args.gets_per_round)],
            cwd=ROOT, stdout=subprocess.PIPE, text=True)
        procs.append(client)
        out, _ = client.communicate(timeout=60 + args.enable_rounds * 25)
        if client.returncode != 0:
            raise RuntimeError(f"enable client failed ({client.returncode})")
        el = time.monotonic() - t0
        res = json.loads(out.strip().splitlines()[-1])
        n = args.enable_rounds + 1  # with the warm-up round
        gateway_s = (proc_cpu_s(gw_pid) if gw_pid else 0.0) - g0 - g_idle / idle_s * el
        th = _delta(thread_cpu_ns(gw_pid) if gw_pid else {}, th0)
        # per thread of the gateway process (gw-publish, gw-command, the reader, zenoh's pools):
        # where the gateway's CPU of a round goes
        res["gateway_cpu_ms_per_round_by_thread"] = {
            name: round((ns - th_idle.get(name, 0) / idle_s * el) / 1e6 / (args.enable_rounds + 1), 3)
            for name, ns in sorted(th.items(), key=lambda kv: -kv[1])}
        res["cpu_ms_per_round_beyond_idle"] = {"gateway_process": round(1e3 * gateway_s / n, 3),
                                               "client_process": round(1e3 * res.pop("client_cpu_s") / n, 3)}
        res["cycle"] = {"cycles": cyc.cycles - c0, "overruns": cyc.overruns - ov0, "wkc_errors": cyc.wkc_errors - wk0}
        res["startup_fault_resets"] = resets
    finally:
        for p in procs:
            stop_process(p)
        agent.stop()  # the gateway process writes its stamps as it exits
    if hops.ENABLED:
        hops.write()
        res.update(hop_figures(hops.read(os.environ[hops.ENV]), (res.get("bare_get") or {}).get("p50_ms")))
    return res


def _delta(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    return {k: v - before.get(k, 0) for k, v in after.items()}


PHASES = {"enable_latency": phase_enable_latency, "enable_client": phase_enable_client, "echo": phase_echo}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.enable_latency", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--phase", choices=sorted(PHASES), required=True)
    p.add_argument("--ifname")
    p.add_argument("--drives", type=int, default=16)
    p.add_argument("--cycle-us", type=int, default=1000)
    p.add_argument("--rt-priority", type=int, default=0)
    p.add_argument("--receive-timeout-us", type=int, default=1000)
    p.add_argument("--enable-rounds", type=int, default=50)
    p.add_argument("--gets-per-round", type=int, default=5)
    p.add_argument("--connect")
    p.add_argument("--echo")
    p.add_argument("--listen")
    p.add_argument("--host", default="bench")
    p.add_argument("--client-rt-priority", type=int, default=0,
                   help="SCHED_FIFO priority of the client process's threads (0: normal scheduling)")
    args, _ = p.parse_known_args(argv)  # bench_agent passes its other phases' options too
    out = PHASES[args.phase](args)
    if args.phase != "echo":
        print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
