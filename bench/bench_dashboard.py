"""``drives-dashboard`` serving 1024 drives: its CPU, and the time from a state change to the page.

    python -m bench.bench_dashboard [--hosts 8] [--drives 128] [--rounds 20] [--idle-s 10] [--out FILE]

A router, ``--hosts`` agents of ``--drives`` simulated drives each (20 ms cycle, one process, a
gateway process each), the dashboard as a process with Debian's headless chromium showing ``/``.
Per round one drive is faulted through the simulator's key space; the page records when its row
turned ``fault`` (its clock) minus the agent's status time (the agent's clock, same machine): the
change-to-browser time. In the same run a plain ``supervisor.Fleet`` subscriber timestamps the
same status (the baseline: what Zenoh alone takes). Dashboard CPU is measured idle (heartbeats
of every drive, counted by the plain subscriber: CPU per status, a figure the machine's load
does not inflate) and during the rounds. The machine's load average is recorded with the figures.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import zenoh

from bench.common import fleet_bench_main, loadavg, p50_ratio, proc_cpu_s, run_stamp, stats_ms
from bus_agent.sim.child import wait_for
from bus_agent.sim.control import sim_inject
from schemas.messages import DriveStatus
from supervisor.fleet import Fleet
from supervisor.session import zenoh_config
from supervisor.testbed import headless_chromium, start_agents, start_dashboard, start_router


def run(hosts: int, drives: int, rounds: int, idle_s: float) -> dict[str, Any]:
    load_start = loadavg()
    names = [f"bd{i}" for i in range(hosts)]
    router, ep = start_router()
    agents = dash = None
    try:
        agents = start_agents(names, drives, ep, cycle_us=20000, sm_watchdog_s=2.0, ready_timeout_s=240)
        dash, url = start_dashboard(ep, ready_timeout_s=120)
        total = hosts * drives
        statuses = [0]
        seen: dict[tuple[str, str], float] = {}
        page_lag: list[float] = []
        zenoh_lag: list[float] = []
        missed = 0
        with headless_chromium() as driver, Fleet(connect=[ep]) as fleet, \
                zenoh.open(zenoh_config("client", [ep])) as s:
            def on_status(st: DriveStatus) -> None:
                statuses[0] += 1
                if st.state == "fault" and (st.host, st.axis) not in seen:
                    seen[(st.host, st.axis)] = time.time() * 1e3 - st.time_ns / 1e6
            fleet.on("status", on_status)
            driver.get(url + "/")
            wait_for(lambda: driver.execute_script("return document.querySelectorAll('#drives tbody tr').length;")
                     >= total, 180, f"{total} rows on the page", poll_s=0.5)
            pid = dash.popen.pid
            # Idle: every drive's heartbeat; the plain subscriber counts the same publications.
            n0, c0, t0 = statuses[0], proc_cpu_s(pid), time.monotonic()
            time.sleep(idle_s)
            idle_wall, idle_cpu, idle_n = time.monotonic() - t0, proc_cpu_s(pid) - c0, statuses[0] - n0
            c1, t1 = proc_cpu_s(pid), time.monotonic()
            for r in range(rounds):
                host, slave = names[r % hosts], (r // hosts) % drives
                axis = f"axis{slave}"
                sim_inject(s, host, slave, "fault", error_code=0x2310)
                key = f"{host}/{axis}"
                upd = wait_for(lambda: (driver.execute_script("return window.dashboardUpdates[arguments[0]];", key)
                                        or {}).get("state") == "fault" and
                               driver.execute_script("return window.dashboardUpdates[arguments[0]];", key), 30,
                               f"{key} fault on the page", poll_s=0.05)
                page_lag.append(float(upd["lag_ms"]))
                try:
                    wait_for(lambda: (host, axis) in seen, 10, "the baseline subscriber")
                    zenoh_lag.append(seen[(host, axis)])
                except AssertionError:
                    missed += 1  # reported: the subscriber never saw it (a starved machine drops links)
            busy_cpu = 100 * (proc_cpu_s(pid) - c1) / (time.monotonic() - t1)
        return {"benchmark": "dashboard", **run_stamp(load_start), "drives": total, "hosts": hosts, "rounds": rounds,
                "idle_s": round(idle_wall, 1), "statuses_per_s_idle": round(idle_n / idle_wall, 1),
                "dashboard_cpu_idle_pct": round(100 * idle_cpu / idle_wall, 1),
                "dashboard_cpu_us_per_status": round(idle_cpu * 1e6 / idle_n, 1) if idle_n else None,
                "dashboard_cpu_changes_pct": round(busy_cpu, 1),
                "change_to_page_ms": stats_ms(page_lag), "change_to_subscriber_ms": stats_ms(zenoh_lag),
                "subscriber_missed": missed,
                "page_over_subscriber_p50": p50_ratio(page_lag, zenoh_lag)}
    finally:
        for p in (dash, agents, router):
            if p is not None:
                p.stop()


def main(argv: list[str] | None = None) -> int:
    return fleet_bench_main("bench_dashboard", __doc__, run, argv)


if __name__ == "__main__":
    sys.exit(main())
