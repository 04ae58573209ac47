"""``drives-opcua`` over 1024 drives: its CPU at rest, and the time from a fault to an OPC UA client's data change.

    python -m bench.bench_opcua [--hosts 8] [--drives 128] [--rounds 20] [--idle-s 10] [--out FILE]

A router, ``--hosts`` real agents of ``--drives`` simulated drives each (20 ms cycle, one
process, a gateway process each: the same fleet as bench_dashboard), ``drives-opcua`` as a
process (insecure fleet, anonymous session), and in this process an asyncua client subscribed
(publishing interval :data:`PUBLISH_MS`) to the ``State`` of every drive the rounds fault, next to
a plain ``supervisor.Fleet`` subscriber (the baseline: what Zenoh alone takes). Per round one
drive is faulted through the simulator's key space; both times are measured from the agent's
status time stamp (the agent's clock, same machine) to the arrival here. The server's CPU is
measured at rest (every drive's heartbeat, counted by the plain subscriber: CPU per status) and
during the rounds. The machine's load average is recorded with the figures.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Any

from bench.common import fleet_bench_main, free_port, loadavg, p50_ratio, proc_cpu_s, run_stamp, stats_ms
from bus_agent.sim.child import wait_for
from bus_agent.sim.control import sim_inject
from drives_opcua.model import HOST_VARIABLES
from schemas.messages import DriveStatus
from supervisor.fleet import Fleet
from supervisor.testbed import _spawn_ready, start_agents, start_router

#: The client's requested publishing interval (what a SCADA typically asks: 50-1000 ms; fast here).
PUBLISH_MS = 20


class _Changes:
    """asyncua subscription handler: when each State node first read ``fault``."""

    def __init__(self) -> None:
        self.fault_at: dict[str, float] = {}
        self.lock = threading.Lock()

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        if val == "fault":
            with self.lock:
                self.fault_at.setdefault(node.nodeid.Identifier, time.time())


def run(hosts: int, drives: int, rounds: int, idle_s: float) -> dict[str, Any]:
    from asyncua import ua
    from asyncua.sync import Client

    load_start = loadavg()
    names = [f"bo{i}" for i in range(hosts)]
    router, ep = start_router()
    agents = server = None
    endpoint = f"opc.tcp://127.0.0.1:{free_port()}"
    try:
        agents = start_agents(names, drives, ep, cycle_us=20000, sm_watchdog_s=2.0, ready_timeout_s=240)
        t_start = time.monotonic()
        server = _spawn_ready("drives-opcua", [sys.executable, "-m", "drives_opcua.cli", "--connect", ep,
                                               "--endpoint", endpoint], "drives-opcua ready", 240)
        total = hosts * drives
        statuses = [0]
        seen: dict[tuple[str, str], DriveStatus] = {}
        arrived: dict[tuple[str, str], float] = {}
        changes = _Changes()
        with Fleet(connect=[ep]) as fleet, Client(endpoint, timeout=30) as client:
            def on_status(st: DriveStatus) -> None:
                statuses[0] += 1
                if st.state == "fault" and (st.host, st.axis) not in seen:
                    seen[(st.host, st.axis)] = st
                    arrived[(st.host, st.axis)] = time.time()
            fleet.on("status", on_status)
            idx = client.get_namespace_index("urn:zenoh-drives")
            host_nodes = [client.get_node(ua.NodeId(f"Drives/{h}", idx)) for h in names]

            def shown() -> bool:
                # Every drive object of every host (its agent variables besides): the address space
                # is complete, so the idle window below measures rest, not the fleet being added.
                try:
                    return all(len(n.get_children()) >= drives + len(HOST_VARIABLES) for n in host_nodes)
                except Exception:
                    return False
            wait_for(shown, 240, f"{total} drives in the address space", poll_s=0.5)
            ready_s = time.monotonic() - t_start
            time.sleep(2.0)
            targets = [(names[r % hosts], f"axis{(r // hosts) % drives}") for r in range(rounds)]
            sub = client.create_subscription(PUBLISH_MS, changes)
            sub.subscribe_data_change([client.get_node(ua.NodeId(f"Drives/{h}/{a}/State", idx)) for h, a in targets])
            pid = server.popen.pid
            n0, c0, t0 = statuses[0], proc_cpu_s(pid), time.monotonic()
            time.sleep(idle_s)
            idle_wall, idle_cpu, idle_n = time.monotonic() - t0, proc_cpu_s(pid) - c0, statuses[0] - n0
            c1, t1 = proc_cpu_s(pid), time.monotonic()
            client_lag: list[float] = []
            zenoh_lag: list[float] = []
            missed = 0
            for (host, axis), r in zip(targets, range(rounds)):
                sim_inject(fleet.session, host, int(axis[4:]), "fault", error_code=0x2310)
                nid = f"Drives/{host}/{axis}/State"
                try:
                    wait_for(lambda: nid in changes.fault_at and (host, axis) in seen, 30, f"{host}/{axis} fault")
                except AssertionError:
                    missed += 1
                    continue
                stamp = seen[(host, axis)].time_ns / 1e6
                client_lag.append(changes.fault_at[nid] * 1e3 - stamp)
                zenoh_lag.append(arrived[(host, axis)] * 1e3 - stamp)
            busy_cpu = 100 * (proc_cpu_s(pid) - c1) / (time.monotonic() - t1)
            sub.delete()
        return {"benchmark": "opcua", **run_stamp(load_start), "drives": total, "hosts": hosts, "rounds": rounds,
                "fleet": "real agents (bus-agent sim, 20 ms cycle)", "publishing_interval_ms": PUBLISH_MS,
                "server_ready_s": round(ready_s, 1),
                "idle_s": round(idle_wall, 1), "statuses_per_s_idle": round(idle_n / idle_wall, 1),
                "server_cpu_idle_pct": round(100 * idle_cpu / idle_wall, 1),
                "server_cpu_us_per_status": round(idle_cpu * 1e6 / idle_n, 1) if idle_n else None,
                "server_cpu_changes_pct": round(busy_cpu, 1),
                "fault_to_client_ms": stats_ms(client_lag), "fault_to_subscriber_ms": stats_ms(zenoh_lag),
                "missed": missed,
                "client_over_subscriber_p50": p50_ratio(client_lag, zenoh_lag)}
    finally:
        for p in (server, agents, router):
            if p is not None:
                p.stop()


def main(argv: list[str] | None = None) -> int:
    return fleet_bench_main("bench_opcua", __doc__, run, argv)


if __name__ == "__main__":
    sys.exit(main())
